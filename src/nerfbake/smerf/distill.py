"""``nerfbake distill``: train the SMERF student from a teacher run (SMERF paper section 5, appendix B).

Every step draws 3x3 pixel patches from the training cameras, jitters them (origin and, per patch, direction),
assigns each ray to the submodel of its (jittered) origin and moves 20% of rays to a neighbouring submodel, asks
the teacher for colours and its ray intervals with weights, and renders the student on exactly those intervals.
Losses: RMSE + 1.5 DSSIM (3x3 patches) on colour, an L1 geometry loss between the student's and the teacher's
compositing weights on the shared intervals (multiplier 0.015 -> 0.001), L2 total variation across the
deferred-MLP lattice (0.1) and, with K > 1, the consistency loss between a ray's home submodel and a neighbour.
Alpha culling ramps from 5e-4 to 5e-3 (log-linear) over the middle of training, as the authors'.

One departure: the first ``mse_warmup`` of the run uses an MSE colour loss without DSSIM. On object scenes with a
plain background (lego) most rays are empty, and in SNeRG mode their colour can only come from the deferred MLP;
under the L1-like RMSE the MLP learns "white everywhere" within a few steps, saturates, and the diffuse colour can
then only make things worse, so density collapses. MSE weights the few wrong foreground rays enough to avoid that.

A second departure: an opacity term, mean |opacity_student - opacity_teacher| per ray (``opacity_mult``). The
deferred MLP sees each ray's remaining visibility, so a student that is only partly opaque on the teacher's
intervals can paint the missing colour in and still match the teacher's pixels; the teacher's intervals end soon
after its surface, so nothing in training shows what such a half-transparent surface lets through. Any other
sampling (the viewer's dense march, other intervals) then shows the room behind through the foreground (bonsai:
opacity 0.37 where the teacher's is 1.0 on the table cloth).

A student folder holds ``config.json`` (this config, the partition, the teacher it came from), ``student.pt``
(checkpoint) and ``metrics.jsonl``; ``--resume`` continues it, Ctrl-C saves it.
"""
from __future__ import annotations

from dataclasses import replace
import json
import math
import time
from pathlib import Path

import numpy as np
import torch

from nerfbake.data.formats import load_dataset
from nerfbake.data.pixels import PixelStore
from nerfbake.data.rays import camera_rays
from nerfbake.eval.metrics import patch_dssim
from nerfbake.eval.views import validation_image
from nerfbake.progress import console, progress_bar
from nerfbake.render.packed import packed_free_depth, packed_median_depth
from nerfbake.render.quantize import RANGE_DENSITY
from nerfbake.smerf.partition import Partition, PartitionError
from nerfbake.smerf.run import CHECKPOINT, CONFIG, DistillConfig
from nerfbake.smerf.student import Student
from nerfbake.teacher.clearance import CameraClearance
from nerfbake.teacher.protocol import Teacher
from nerfbake.teacher.run import load_teacher
from nerfbake.train.loop import (DataParallel, finish_run, git_revision, load_checkpoint, log_linear_lr, run_complete,
                                 run_steps, to_jsonable, write_json_atomic)
from nerfbake.train.row_adam import RowAdam


FREE_SPACE_SAMPLES = 4  # points per training ray in front of the teacher's first surface (free_space_loss)
FREE_SPACE_WEIGHT = 0.01  # the teacher's accumulated weight that ends a ray's free stretch
FREE_SPACE_MARGIN = 0.9  # the stretch stops this fraction of the way there: the student's surface ramps up in front


def charbonnier(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """The authors' per-ray "RMSE": mean of sqrt(1e-6 + d^2)."""
    return torch.sqrt(1e-6 + (a - b) ** 2).mean()


def empty_space_loss(student: Student, teacher: Teacher, clearance: CameraClearance, num_points: int,
                     gen: torch.Generator, quantize: bool) -> torch.Tensor:
    """Mean |alpha_student - alpha_teacher| at the viewer's step length, at random points of every submodel's
    contracted volume (half of them in the uncontracted core). The ray losses only ever see the teacher's
    intervals; without this the grids keep arbitrary density wherever the teacher never sampled, and the baked
    scene, which the viewer marches densely, shows it as floaters (the role of the authors' sparsity loss). The
    teacher is read with its ``clearance`` emptied (space no training ray of it reached)."""
    dev = student.sparse.device
    n = num_points
    z = torch.rand(n, 3, generator=gen) * 4 - 2
    z[: n // 2] *= 0.5
    sm = torch.randint(0, student.partition.num_alive, (n,), generator=gen)
    z, sm = z.to(dev), sm.to(dev)
    world = student.world_from_contracted(z, sm)
    with torch.no_grad():
        sigma_t = clearance.density(teacher, world)
    step = student.realtime_step(uncontract_norm(z))
    alpha_t = 1 - torch.exp(-sigma_t * step / student.partition.scale)  # teacher sigma is per world unit
    alpha_s = 1 - torch.exp(-student.features(z, sm, quantize)["density"] * step)
    return (alpha_s - alpha_t).abs().mean()


def free_depth(tout: dict, num_rays: int, radius: float) -> torch.Tensor:
    """(R,) world distance along each training ray that the student must leave empty: up to
    ``FREE_SPACE_MARGIN`` of the way to where the teacher's accumulated weight passes ``FREE_SPACE_WEIGHT``, and at
    least the teacher's near bound ``radius`` (rays the teacher shows nothing on get that bound alone)."""
    first = packed_free_depth(tout["w"], tout["t0"], tout["ray_idx"], num_rays, FREE_SPACE_WEIGHT)
    first = torch.where(torch.isfinite(first), FREE_SPACE_MARGIN * first, torch.zeros_like(first))
    return first.clamp_min(radius)


def free_space_loss(student: Student, origins: torch.Tensor, dirs: torch.Tensor, params_idx: torch.Tensor,
                    depth: torch.Tensor, u: torch.Tensor, quantize: bool) -> torch.Tensor:
    """Mean opacity the student gives the stretch of each training ray in front of the teacher's first surface
    (``depth`` (R,) world units, from :func:`free_depth`), its optical depth estimated from the points at ``u``
    (R, m) uniform in [0, 1) along it. The ray losses only see the intervals the teacher hands on, and a marching
    teacher hands on none in the empty cells it skips or where its alpha is below its cull bound: there the student
    kept density the viewer then draws (rooms, K = 1: the student marched densely scored 2.1-2.4 dB under the same
    student on the teacher's intervals, a haze over the floor, and its bake 1.75 dB under it). The first stretch,
    up to the teacher's near bound, is never sampled by any teacher; the triplanes, shared along each axis with
    surfaces further on, fill it (the phone clip: coloured blocks over the floor)."""
    r, m = u.shape
    t = u.to(origins.device) * depth[:, None]
    pts = (origins[:, None] + t[..., None] * dirs[:, None]).reshape(-1, 3)
    sm = params_idx[:, None].expand(r, m).reshape(-1)
    z, _ = student.contracted(pts, sm)
    sigma = student.features(z, sm, quantize)["density"].view(r, m)
    optical = sigma.mean(1) * depth * student.partition.scale  # density is per cube unit
    return (1.0 - torch.exp(-optical)).mean()


@torch.no_grad()
def warm_start_density(student: Student, teacher: Teacher, clearance: CameraClearance, floor: float = -4.0,
                       chunk: int = 1 << 18) -> None:
    """Start every submodel's sparse density from the teacher's: at each voxel centre of each alive submodel, the
    pre-activation whose density (per cube unit) is the teacher's there, at least ``floor`` (exp(floor - 1) per cube
    unit: invisible at the viewer's step, yet not so deep that gradients cannot raise it). Explicit grids learn only
    where training rays pass; without this, a submodel's space that few of its rays cross keeps the uniform starting
    density (K > 1 splits the rays between submodels, so much of each one's space is such). The teacher's
    ``clearance`` around its cameras starts at the floor: it never rendered that space."""
    s, dev = student.cfg.sparse_resolution, student.sparse.device
    centres = (torch.arange(s, dtype=torch.float32) + 0.5) / s * 4.0 - 2.0
    grid = torch.stack(torch.meshgrid(centres, centres, centres, indexing="ij"), -1).reshape(-1, 3)
    with progress_bar("warm start from the teacher", student.partition.num_alive * grid.shape[0], unit="voxels") as adv:
        for sm in range(student.partition.num_alive):
            for a in range(0, grid.shape[0], chunk):
                z = grid[a:a + chunk].to(dev)
                world = student.world_from_contracted(z, torch.full((z.shape[0],), sm, device=dev))
                sigma = clearance.density(teacher, world).float() / student.partition.scale
                pre = torch.log(sigma.clamp_min(1e-30)) + 1.0
                student.sparse[sm * s ** 3 + a: sm * s ** 3 + a + z.shape[0], 0] = pre.clamp(floor, RANGE_DENSITY[1])
                adv(z.shape[0])


def uncontract_norm(z: torch.Tensor) -> torch.Tensor:
    """Inf-norm of the uncontracted point of contracted points (how much the contraction squeezes there)."""
    m = z.abs().amax(-1)
    return torch.where(m > 1, 1 / (2 - m.clamp(max=2 - 1e-6)), torch.ones_like(m))


def jitter_patches(rays: dict, cfg: DistillConfig, partition: Partition, gen: torch.Generator) -> dict:
    """Gaussian origin jitter per ray; one small random direction offset per 3x3 patch."""
    o, d = rays["origins"], rays["directions"]
    n = o.shape[0]
    o = o + torch.randn(n, 3, generator=gen) * (cfg.jitter_origin / partition.scale)
    patch_offset = torch.randn(n // 9, 1, 3, generator=gen) * cfg.jitter_direction
    d = (d.view(-1, 9, 3) + patch_offset).view(n, 3)
    return {**rays, "origins": o, "directions": d / d.norm(dim=-1, keepdim=True)}


def _neighbour_table(partition: Partition) -> list[list[int]]:
    return [partition.neighbours(p) for p in range(partition.num_alive)]


def reassign(params_idx: np.ndarray, partition: Partition, fraction: float, gen: torch.Generator) -> np.ndarray:
    """Move a random ``fraction`` of rays to a random alive neighbour of their submodel (where one exists)."""
    out = params_idx.copy()
    draw = torch.rand(len(out), generator=gen).numpy()
    pick = torch.rand(len(out), generator=gen).numpy()
    if partition.num_alive < 2 or fraction <= 0:
        return out
    table = _neighbour_table(partition)
    for i in np.nonzero(draw < fraction)[0]:
        nb = table[int(out[i])]
        if nb:
            out[i] = nb[int(pick[i] * len(nb))]
    return out


def random_neighbour(params_idx: np.ndarray, partition: Partition, gen: torch.Generator) -> np.ndarray:
    """For each ray a random alive neighbour of its submodel, or -1 where it has none."""
    pick = torch.rand(len(params_idx), generator=gen).numpy()
    table = _neighbour_table(partition)
    counts = np.array([len(t) for t in table])[params_idx]
    padded = np.array([t + [-1] * (26 - len(t)) for t in table])
    choice = np.minimum((pick * counts).astype(int), np.maximum(counts - 1, 0))
    out = padded[params_idx, choice]
    return np.where(counts > 0, out, -1)


def teacher_background(ds) -> tuple[float, float, float]:
    """The background colour the teacher was trained against (white when the dataset has none)."""
    return tuple(ds.background or (1.0, 1.0, 1.0))


@torch.no_grad()
def surface_distances(teacher: Teacher, store: PixelStore, background, device, seed: int, num_rays: int = 4096) -> np.ndarray:
    """Inf-norm distances from the world origin of the surfaces the training views see: the teacher's median depth
    along ``num_rays`` random training rays, for the rays it makes at least half opaque (M,)."""
    rays = store.sample_rays(num_rays, torch.Generator().manual_seed(seed))
    o, d = rays["origins"].to(device), rays["directions"].to(device)
    out = []
    for a in range(0, num_rays, 1024):
        oc, dc = o[a:a + 1024], d[a:a + 1024]
        t = teacher.render_rays(oc, dc, torch.tensor(background, device=device).expand(oc.shape[0], 3))
        depth = packed_median_depth(t["w"], t["t0"], t["t1"], t["ray_idx"], oc.shape[0])
        keep = (t["acc"] >= 0.5) & torch.isfinite(depth)
        out.append((oc[keep] + depth[keep, None] * dc[keep]).abs().amax(-1).cpu())
    return torch.cat(out).double().numpy()


def distill(teacher_run: str | Path, out: str | Path, cfg: DistillConfig, resume: bool = False,
            stop_at: int | None = None) -> Path:
    """Train a student from the teacher run ``teacher_run`` into ``out`` (see the module docstring); ``resume``
    continues a saved folder, ``stop_at`` ends early at that step (for tests of resuming). Returns ``out``."""
    out = Path(out)
    dp = DataParallel()
    teacher, tcfg, tmeta, _ = load_teacher(Path(teacher_run))
    teacher.to(dp.device)
    downscale = cfg.downscale or tcfg.downscale
    ds = load_dataset(tmeta["data"], downscale=downscale, normalize=tcfg.normalize)
    train_idx = ds.split("train")
    if not resume and dp.is_main and run_complete(out):
        raise ValueError(f"{out}: already holds a finished student; pass --resume to continue or choose another --out")
    with progress_bar("loading images", len(train_idx), unit="img") as adv:
        store = PixelStore(ds, "train", progress=lambda k, n: adv())
    bg = teacher_background(ds)
    clearance = CameraClearance.of_teacher(tmeta, ds.cameras("train"))
    if resume and (out / CONFIG).is_file():  # the partition the checkpoint was trained in
        partition = Partition.from_json(json.loads((out / CONFIG).read_text())["partition"])
    else:
        origins = np.stack([ds.frames[i].camera.origin for i in train_idx])
        sized_by_surfaces = cfg.k == 1 and (cfg.core_quantile > 0 or cfg.core_fill_quantile > 0)
        reach = surface_distances(teacher, store, bg, dp.device, cfg.seed) if sized_by_surfaces else None
        partition = Partition.from_cameras(origins, cfg.k, surface_distances=reach, core_quantile=cfg.core_quantile,
                                           fill_quantile=cfg.core_fill_quantile)
    asked = cfg
    cfg = replace(cfg, steps=cfg.total_steps(partition.num_alive))  # every schedule spans the whole run
    torch.manual_seed(cfg.seed)
    student = Student(cfg.student, partition, cfg.seed).to(dp.device)
    if cfg.warm_start and not (resume and (out / CHECKPOINT).is_file()):
        warm_start_density(student, teacher, clearance)
    opt = RowAdam([{"params": [student.sparse, student.planes], "lr": cfg.lr_grid},
                   {"params": list(student.mlp.parameters()), "lr": cfg.lr_mlp}],
                  row_masks=student.row_masks(), betas=(0.9, 0.99), eps=1e-15)
    start = 0
    ckpt = out / CHECKPOINT
    if resume and ckpt.is_file():
        state = load_checkpoint(ckpt)
        student.load_state_dict(state["model"])
        opt.load_state_dict(state["optimizer"])
        start = int(state["step"])
        if dp.is_main:
            console.print(f"resuming {out} at step {start}")
    meta = {"kind": "smerf-student", "distill": to_jsonable(asked), "total_steps": cfg.steps,
            "partition": partition.to_json(),
            "teacher": str(Path(teacher_run).resolve()), "data": tmeta["data"], "downscale": downscale,
            "normalize": tcfg.normalize,
            "num_submodels": partition.num_alive, "git": git_revision(), "world_size": dp.world, "complete": False}
    if dp.is_main:
        out.mkdir(parents=True, exist_ok=True)
        write_json_atomic(out / CONFIG, meta)
    val_index = ds.split("val" if "val" in ds.splits else "test")[0]

    def state_dict(step):
        return {"model": student.state_dict(), "optimizer": opt.state_dict(), "step": step, "kind": "smerf-student"}

    n_rays = cfg.batch_patches * 9
    t_start = time.time()

    def one_step(step, gen):
        lr_g = log_linear_lr(step, cfg.steps, cfg.lr_grid, cfg.lr_grid_final, cfg.warmup_steps)
        lr_m = log_linear_lr(step, cfg.steps, cfg.lr_mlp, cfg.lr_mlp_final, cfg.warmup_steps)
        opt.param_groups[0]["lr"], opt.param_groups[1]["lr"] = lr_g, lr_m
        drawn = store.sample_rays(n_rays, gen, patch=3)
        rays = jitter_patches(drawn, cfg, partition, gen)
        home = partition.assign(rays["origins"].double().numpy())
        params_idx = reassign(home, partition, cfg.reassign_fraction, gen)
        noise = torch.rand(n_rays, teacher.noise_dims, generator=gen)
        neighbour = random_neighbour(params_idx, partition, gen) if partition.num_alive > 1 else None
        mine = dp.shard(cfg.batch_patches)
        sl = slice(mine.start * 9, mine.stop * 9)
        o, d = rays["origins"][sl].to(dp.device), rays["directions"][sl].to(dp.device)
        cams = drawn["origins"][sl].to(dp.device)  # un-jittered camera centres: where the MLP lattice is read
        with torch.no_grad():
            tout = teacher.render_rays(o, d, torch.tensor(bg, device=dp.device).expand(o.shape[0], 3),
                                       noise=noise[sl].to(dp.device))
        pidx = torch.as_tensor(params_idx[sl], device=dp.device)
        s_out = student.render(o, d, pidx, tout["t0"], tout["t1"], tout["ray_idx"], cfg.cull_threshold(step),
                               cfg.quantize, cams)
        share = (sl.stop - sl.start) / n_rays  # this rank's share of the global mean
        target = tout["rgb"]
        ssim_l = patch_dssim(s_out["rgb"].view(-1, 3, 3, 3), target.view(-1, 3, 3, 3))
        if step < cfg.mse_warmup * cfg.steps:
            rgb_l = 10.0 * ((s_out["rgb"] - target) ** 2).mean()
            ssim_l = ssim_l * 0
        else:
            rgb_l = charbonnier(s_out["rgb"], target)
        geo_l = (s_out["w"] - tout["w"]).abs().sum() / o.shape[0]
        opacity_l = (s_out["acc"] - tout["acc"]).abs().mean()
        loss = share * (cfg.rgb_mult * rgb_l + cfg.dssim_mult * ssim_l + cfg.geometry_weight(step) * geo_l
                        + cfg.opacity_mult * opacity_l)
        loss = loss + cfg.mlp_tv_mult * student.mlp.tv_loss() / dp.world
        if cfg.empty_space_mult > 0:
            empty_l = empty_space_loss(student, teacher, clearance, cfg.empty_space_points, gen, cfg.quantize)
            u = torch.rand(n_rays, FREE_SPACE_SAMPLES, generator=gen)[sl]  # drawn whole: every rank's stream agrees
            free = free_depth(tout, o.shape[0], clearance.radius)
            free_l = free_space_loss(student, o, d, pidx, free, u, cfg.quantize)
            loss = loss + cfg.empty_space_mult * (empty_l / dp.world + share * free_l)
        terms = {"rgb": float(rgb_l.detach()), "dssim": float(ssim_l.detach()), "geometry": float(geo_l.detach()),
                 "opacity": float(opacity_l.detach())}
        if cfg.empty_space_mult > 0:
            terms["empty_space"] = float(empty_l.detach())
            terms["free_space"] = float(free_l.detach())
        if neighbour is not None:
            nb = torch.as_tensor(neighbour[sl], device=dp.device)
            keep = (nb >= 0)
            if keep.any():
                nb = torch.where(keep, nb, pidx)
                alt = student.render(o, d, nb, tout["t0"], tout["t1"], tout["ray_idx"], cfg.cull_threshold(step),
                                     cfg.quantize, cams)
                cons = charbonnier(alt["rgb"][keep], s_out["rgb"][keep])
                loss = loss + share * cfg.consistency_mult * cons
                terms["consistency"] = float(cons.detach())
        opt.zero_grad(set_to_none=False)
        loss.backward()
        dp.all_reduce_grads(student.parameters())
        dp.all_reduce_masks(student.row_masks().values())  # every rank visits the rows any rank wrote
        opt.step()
        mse = dp.all_reduce_sum(float(((s_out["rgb"].detach().clamp(0, 1) - target) ** 2).sum())) / (3 * n_rays)
        return n_rays, {"loss": float(loss.detach()), "psnr_vs_teacher": -10 * math.log10(max(mse, 1e-10)),
                        "lr_grid": lr_g, "cull_alpha": cfg.cull_threshold(step + 1), **terms}

    def validate(step):
        return validate_student(student, teacher, ds, val_index, out / "val", step, bg), {}, f"-> {out / 'val'}"

    step = run_steps(out, dp, f"distill K={cfg.k}", cfg.steps, start, cfg.seed, one_step, state_dict, ckpt,
                     cfg.checkpoint_every, validate, cfg.val_every, cfg.tensorboard, stop_at,
                     summary=lambda r: f"loss {r['loss']:.5f}  psnr(teacher) {r['psnr_vs_teacher']:5.2f}  "
                                       f"{r['rays_per_s']:7.0f} rays/s")
    meta["seconds"] = meta.get("seconds", 0.0) + (time.time() - t_start)
    finish_run(dp, ckpt, state_dict, out / CONFIG, meta, step, cfg.steps)
    return out


@torch.no_grad()
def render_student_camera(student: Student, teacher: Teacher, camera, background, chunk: int = 1 << 13,
                          params_idx: int | None = None) -> np.ndarray:
    """(H, W, 3) image of the student on the teacher's (deterministic) intervals; the camera's submodel is chosen
    from its position (inf-norm rule) unless ``params_idx`` is given."""
    rays = camera_rays(camera)
    o, d = rays["origins"].reshape(-1, 3), rays["directions"].reshape(-1, 3)
    dev = student.sparse.device
    if params_idx is None:
        params_idx = int(student.partition.assign(camera.origin[None], strict=True)[0])
    out = []
    for a in range(0, o.shape[0], chunk):
        oc, dc = o[a:a + chunk].to(dev), d[a:a + chunk].to(dev)
        bg = torch.tensor(background, device=dev).expand(oc.shape[0], 3)
        t = teacher.render_rays(oc, dc, bg)
        pidx = torch.full((oc.shape[0],), params_idx, dtype=torch.long, device=dev)
        out.append(student.render(oc, dc, pidx, t["t0"], t["t1"], t["ray_idx"])["rgb"].clamp(0, 1).cpu())
    return torch.cat(out).reshape(camera.height, camera.width, 3).numpy()


def validate_student(student, teacher: Teacher, ds, index: int, out_dir: Path, step: int, background) -> float:
    """One held-out view next to its ground truth in ``out_dir``; returns PSNR (NaN when the view's camera lies
    outside the partition cube)."""
    try:
        return validation_image(lambda cam: render_student_camera(student, teacher, cam, background), ds, index,
                                out_dir, step)
    except PartitionError:
        return float("nan")
