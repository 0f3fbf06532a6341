"""``nerfbake teacher train``: fit a teacher to a dataset with the shared loop (checkpoints, resume, Ctrl-C,
data parallelism). A run folder holds ``config.json``, ``checkpoint.pt``, ``metrics.jsonl`` and ``val/``."""
from __future__ import annotations

from dataclasses import asdict
from pathlib import Path

import numpy as np
import torch

from nerfbake.data.dataset import Dataset, object_box
from nerfbake.data.formats import load_dataset
from nerfbake.data.pixels import PixelStore
from nerfbake.eval.views import validation_image
from nerfbake.progress import console, progress_bar
from nerfbake.teacher.appearance import APPEARANCE_LR_SCALE, ImageAppearance, resolve_appearance
from nerfbake.teacher.evaluate import render_camera
from nerfbake.teacher.models import SceneBox, build_teacher
from nerfbake.teacher.presets import TeacherTrainConfig
from nerfbake.teacher.run import CHECKPOINT, CONFIG
from nerfbake.train.loop import (DataParallel, finish_run, git_revision, load_checkpoint, log_linear_lr, run_complete,
                                 run_steps, step_decay_lr, step_generator, to_jsonable, write_json_atomic)


def scene_box(ds: Dataset) -> SceneBox:
    """The region the teacher models, from :meth:`Dataset.scene_kind`. Blender scenes live in [-1.5, 1.5]^3 between
    near 2 and far 6 (unless their transforms give ``aabb``/``near``/``far``, as nerfbake's indoor synthetic scenes
    do). Other captures are normalised so cameras lie in [-1, 1]^3.

    * Object-centred captures with sparse points (cameras around, outside the points' box: ``object_box``) are
      modelled inside that box with the occupancy grid, like Blender scenes, and rays leaving it end on a learned
      directional background. Contracted, such a capture is explained by screens in front of each camera, which
      no other camera sees (the synthetic textured scene, 32 views, 1000 steps: 11 dB on held-out views).
    * Everything else (forward-facing, unbounded 360°, and Blender scenes whose cameras stand inside their box) is
      covered at full resolution in the box ([-1, 1]^3 for real captures), with the contraction taking in
      everything beyond. A Blender scene whose cameras stand inside its box is an indoor scene (``SceneBox.indoor``):
      its teacher marches the occupancy grid rather than sampling with the proposal network (see
      ``HashTeacherConfig.unbounded_sampler``).

    The near plane is 0.9 x the near bound of the sparse points (LLFF's rule) where the dataset has one: space in
    front of it is seen by one camera alone, and a contracted teacher left to use it explains each view with a
    screen there (lego as an opaque capture, 1000 steps: 8.7 dB held-out with near 0.01, 16.5 with near at 0.45
    normalised)."""
    kind, _ = ds.scene_kind()
    if ds.format == "blender":
        near, far = ds.bounds or (2.0, 6.0)
        lo, hi = ds.extras.get("aabb", ([-1.5] * 3, [1.5] * 3))
        if kind != "object-centric":
            return SceneBox(list(lo), list(hi), near, 1e10, contracted=True, indoor=True)
        return SceneBox(list(lo), list(hi), near, far)
    near = 0.01 if ds.bounds is None else max(0.01, 0.9 * ds.bounds[0])
    if kind == "object-centric":
        lo, hi = object_box(ds.training_frames(), ds.points)
        return SceneBox([float(v) for v in lo], [float(v) for v in hi], near, 1e10, learned_background=True)
    return SceneBox([-1.0] * 3, [1.0] * 3, near, 1e10, contracted=True)


def make_optimizer(model, cfg: TeacherTrainConfig, appearance: ImageAppearance | None = None):
    """Adam (instant-ngp's betas, eps 1e-15), fused, with weight decay on the MLPs only. A group's ``lr_scale``
    multiplies the schedule's rate (the per-image appearance learns slower than the field)."""
    grid_params = [p for n, p in model.named_parameters() if n.endswith("grid.table")]
    other = [p for n, p in model.named_parameters() if not n.endswith("grid.table")]
    groups = [{"params": other, "weight_decay": cfg.weight_decay}]
    if grid_params:
        groups.append({"params": grid_params, "weight_decay": 0.0})
    if appearance is not None:
        groups.append({"params": list(appearance.parameters()), "weight_decay": 0.0, "lr_scale": APPEARANCE_LR_SCALE})
    return torch.optim.Adam(groups, lr=cfg.lr, betas=(0.9, 0.99), eps=1e-15, fused=True)


def draw_batch(store: PixelStore, model, cfg: TeacherTrainConfig, gen: torch.Generator, dp: DataParallel) -> dict:
    """The global batch with all its per-ray randomness (background colour, sample jitter), then this rank's
    slice: every rank of a data-parallel run, and a single process, see the same rays with the same noise."""
    n = cfg.batch_rays
    batch = store.sample_uniform_rays(n, gen)
    batch["background"] = torch.rand(n, 3, generator=gen) if cfg.random_background else torch.ones(n, 3)
    batch["noise"] = torch.rand(n, model.noise_dims, generator=gen)
    mine = dp.shard(n)
    return {k: v[mine].to(dp.device) for k, v in batch.items()}


def loss_terms(model, batch: dict, total_rays: int, gen: torch.Generator, world: int = 1,
               appearance: ImageAppearance | None = None):
    """Photometric loss of one (rank's share of a) batch, normalised by the global batch size so gradients
    summed over ranks equal one process's mean; plus the teacher's own regularisers. ``appearance`` turns the
    teacher's colour into each training photo's before the comparison."""
    target, bg = batch["target"], batch["background"]
    # RGBA renders: prediction and target on the same colour. Opaque photos: the prediction alone is put on it, so
    # a ray that leaves any light through is wrong on every colour and the field learns to be opaque. (On black, as
    # before, a ray could darken a pixel by letting light through, and every later render on another background
    # showed it: fern's held-out views lost 3.3 dB to a white haze.)
    gt = target[:, :3] * target[:, 3:] + bg * (1 - target[:, 3:]) if target.shape[-1] == 4 else target
    out = model.render_rays(batch["origins"], batch["directions"], bg, noise=batch["noise"])
    if appearance is not None:
        out["rgb"] = appearance(out["rgb"], batch["cam_idx"])
    sq = ((out["rgb"] - gt) ** 2).sum()
    loss = sq / (3 * total_rays)
    terms = {"mse": loss.detach()}
    if "rgb_coarse" in out:
        loss = loss + ((out["rgb_coarse"] - gt) ** 2).sum() / (3 * total_rays)
    for name, value in model.extra_losses(out, gen).items():
        loss = loss + value / world  # per-rank means; summed over ranks by the gradient all-reduce
        terms[name] = value.detach()
    return loss, terms, out, sq.detach()


def render_validation(model, ds: Dataset, index: int, out_dir: Path, step: int) -> float:
    """One held-out view next to its ground truth in ``out_dir``, rendered in eval mode; returns PSNR."""
    def render(cam):
        was_training = model.training
        model.eval()
        try:
            return render_camera(model, cam, ds.background or (1.0, 1.0, 1.0))["rgb"]
        finally:
            model.train(was_training)

    return validation_image(render, ds, index, out_dir, step)


def train_teacher(data: str | Path, out: str | Path, cfg: TeacherTrainConfig, resume: bool = False,
                  stop_at: int | None = None) -> Path:
    """Train (or, with ``resume``, continue) a teacher. ``stop_at`` stops early as Ctrl-C would (for tests
    and time-boxed runs); the run can then be resumed to the same result as an uninterrupted one."""
    out = Path(out)
    dp = DataParallel()
    torch.manual_seed(cfg.seed)
    ds = load_dataset(data, downscale=cfg.downscale, normalize=cfg.normalize)
    box = scene_box(ds)
    ckpt_path = out / CHECKPOINT
    if not resume and dp.is_main and run_complete(out):
        raise ValueError(f"{out}: already holds a finished teacher; pass --resume to continue or choose another --out")
    model = build_teacher(cfg.field, cfg.model_config, box).to(dp.device)
    appearance_mode = resolve_appearance(cfg.appearance, ds.background is not None)
    appearance = ImageAppearance(len(ds.split("train"))).to(dp.device) if appearance_mode == "affine" else None
    optimizer = make_optimizer(model, cfg, appearance)
    trained = [p for g in optimizer.param_groups for p in g["params"]]  # what every rank's gradients must agree on
    start = 0
    if resume and ckpt_path.is_file():
        state = load_checkpoint(ckpt_path)
        model.load_state_dict(state["model"])
        if appearance is not None:
            appearance.load_state_dict(state["appearance"])
        optimizer.load_state_dict(state["optimizer"])  # moves the moments onto the parameters' device
        start = int(state["step"])
        if dp.is_main:
            console.print(f"resuming {out} at step {start}")
    meta = {"train": to_jsonable(cfg), "box": asdict(box), "data": str(Path(data).resolve()), "dataset": ds.info(),
            "git": git_revision(), "world_size": dp.world, "complete": False,
            "appearance": appearance_mode}
    if dp.is_main:
        write_json_atomic(out / CONFIG, meta)
    with progress_bar("loading images", len(ds.split("train")), unit="img") as adv:
        store = PixelStore(ds, "train", progress=lambda k, n: adv())

    def state_dict(step):
        state = {"model": model.state_dict(), "optimizer": optimizer.state_dict(), "step": step, "kind": cfg.field}
        if appearance is not None:
            state["appearance"] = appearance.state_dict()
        return state

    val_split = "val" if "val" in ds.splits else "test"
    val_index = ds.split(val_split)[0]
    val_name = ds.frames[val_index].name

    def validate(step):
        return (render_validation(model, ds, val_index, out / "val", step), {"val_view": val_name},
                f"({val_name}) -> {out / 'val'}")

    def one_step(step, gen):
        model.train()
        model.before_step(step, gen)
        if cfg.lr_schedule == "step":
            lr = step_decay_lr(step, cfg.steps, cfg.lr, cfg.warmup_steps)
        else:
            lr = log_linear_lr(step, cfg.steps, cfg.lr, cfg.lr_final, cfg.warmup_steps)
        for g in optimizer.param_groups:
            g["lr"] = lr * g.get("lr_scale", 1.0)
        batch = draw_batch(store, model, cfg, gen, dp)
        loss, terms, render, sq = loss_terms(model, batch, cfg.batch_rays, gen, dp.world, appearance)
        optimizer.zero_grad(set_to_none=False)  # keeps the hash table's gradient buffer
        loss.backward()
        dp.all_reduce_grads(trained)
        optimizer.step()
        mse = dp.all_reduce_sum(float(sq)) / (3 * cfg.batch_rays)
        rec = {"loss": float(loss.detach()), "psnr": -10 * np.log10(max(mse, 1e-10)), "lr": lr,
               "samples_per_ray": render["num_samples"] / max(1, batch["target"].shape[0])}
        if hasattr(model, "grid"):
            rec["occupancy"] = model.grid.occupancy_fraction
        return cfg.batch_rays, rec

    step = run_steps(out, dp, f"teacher {cfg.field}", cfg.steps, start, cfg.seed, one_step, state_dict, ckpt_path,
                     cfg.checkpoint_every, validate, cfg.val_every, cfg.tensorboard, stop_at,
                     summary=lambda r: f"loss {r['loss']:.5f}  psnr {r['psnr']:5.2f}  {r['rays_per_s']:8.0f} rays/s  "
                                       f"{r['samples_per_ray']:.1f} samples/ray")
    if start < cfg.steps <= step:  # this call finished the run
        model.after_training(step_generator(cfg.seed, cfg.steps), log=console.print if dp.is_main else None)
    if appearance is not None:
        meta["appearance_spread"] = appearance.summary()  # finish_run records it in config.json
    finish_run(dp, ckpt_path, state_dict, out / CONFIG, meta, step, cfg.steps)
    return out
