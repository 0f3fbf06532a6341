"""The shared training loop (:func:`run_steps`) and its machinery; the teacher and the SMERF student both run it,
each supplying one optimisation step, its checkpoint state and its validation.

* Determinism: every step draws its randomness from ``step_generator(seed, step)``, so a resumed run sees
  exactly the batches an uninterrupted one would, and ranks of a data-parallel run can each take their
  slice of the same global batch.
* Checkpoints are written atomically (temporary file, then rename) every N steps and on Ctrl-C.
* ``torchrun`` launches are detected from the environment; gradients are summed across ranks (gloo on
  CPU, NCCL on GPU); rank 0 writes files.
"""
from __future__ import annotations

import ctypes
import json
import os
import signal
import subprocess
import time
from dataclasses import asdict, is_dataclass
from pathlib import Path

import torch
import torch.distributed as dist

from nerfbake import atomic
from nerfbake.errors import RunFolderError
from nerfbake.kernels import flush_denormals
from nerfbake.progress import console, progress_bar


def step_generator(seed: int, step: int) -> torch.Generator:
    return torch.Generator().manual_seed((seed * 1_000_003 + step) % (2**63 - 1))


def git_revision() -> str:
    try:
        root = Path(__file__).resolve().parents[3]
        out = subprocess.run(["git", "rev-parse", "HEAD"], cwd=root, capture_output=True, text=True, timeout=5)
        rev = out.stdout.strip()
        if rev:
            dirty = subprocess.run(["git", "status", "--porcelain", "--untracked-files=no"], cwd=root,
                                   capture_output=True, text=True, timeout=5).stdout.strip()
            return rev + ("-dirty" if dirty else "")
    except (OSError, subprocess.SubprocessError):
        pass
    return "unknown"


def to_jsonable(obj):
    if is_dataclass(obj):
        return to_jsonable(asdict(obj))
    if isinstance(obj, dict):
        return {k: to_jsonable(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [to_jsonable(v) for v in obj]
    if isinstance(obj, Path):
        return str(obj)
    if getattr(obj, "ndim", None) == 0 and hasattr(obj, "item"):  # numpy / torch scalars
        return obj.item()
    return obj


def write_json_atomic(path: Path, obj) -> None:
    atomic.write_json(path, to_jsonable(obj))


def save_checkpoint(path: Path, state: dict) -> None:
    with atomic.atomic_file(path) as tmp:
        torch.save(state, tmp)


def load_checkpoint(path: Path) -> dict:
    """Tensors and plain containers only (``weights_only``): a checkpoint from elsewhere cannot run pickled code."""
    path = Path(path)
    if not path.is_file():
        raise RunFolderError(f"{path}: no checkpoint here; train first or point --run at a training output folder")
    try:
        return torch.load(path, map_location="cpu", weights_only=True)
    except Exception as exc:  # torch raises many types for truncated/corrupt files
        raise RunFolderError(f"{path}: cannot read the checkpoint ({type(exc).__name__}: {' '.join(str(exc).split())[:200]}); "
                             "it is corrupt, from an incompatible version or holds more than tensors -- retrain or "
                             "restore it") from None


class Interrupt:
    """Turns the first Ctrl-C (SIGINT) or SIGTERM into a flag the loop checks, so it can checkpoint and stop cleanly."""

    def __init__(self):
        self.requested = False
        self._old = None

    def __enter__(self):
        def handler(signum, frame):
            if self.requested:  # second Ctrl-C: give up immediately
                raise KeyboardInterrupt
            self.requested = True

        try:  # SIGTERM (kill, a scheduler) stops a run the same way: checkpoint, then exit
            self._old = {sig: signal.signal(sig, handler) for sig in (signal.SIGINT, signal.SIGTERM)}
        except ValueError:  # not the main thread
            self._old = None
        return self

    def __exit__(self, *exc):
        if self._old is not None:
            for sig, old in self._old.items():
                signal.signal(sig, old)
        return False


def default_device() -> torch.device:
    """This process's device: the GPU of its local rank when CUDA is available (``NERFBAKE_DEVICE=cpu`` forces the
    CPU), else the CPU."""
    if torch.cuda.is_available() and os.environ.get("NERFBAKE_DEVICE", "") != "cpu":
        return torch.device("cuda", int(os.environ.get("LOCAL_RANK", "0")))
    return torch.device("cpu")


class DataParallel:
    """Rank, world size and device (:func:`default_device`) under ``torchrun``; one process otherwise."""

    def __init__(self):
        flush_denormals()  # a trainer builds this first, before its first parallel op starts torch's threads
        self.world = int(os.environ.get("WORLD_SIZE", "1"))
        self.rank = int(os.environ.get("RANK", "0"))
        self.device = default_device()
        use_cuda = self.device.type == "cuda"
        if use_cuda:
            torch.cuda.set_device(self.device)
        if self.world > 1 and not dist.is_initialized():
            dist.init_process_group("nccl" if use_cuda else "gloo")

    @property
    def is_main(self) -> bool:
        return self.rank == 0

    def shard(self, n: int) -> slice:
        """This rank's slice of a global batch of n items."""
        lo, hi = n * self.rank // self.world, n * (self.rank + 1) // self.world
        return slice(lo, hi)

    def all_reduce_grads(self, params) -> None:
        if self.world == 1:
            return
        grads = [p.grad for p in params if p.grad is not None]
        if not grads:
            return
        flat = torch.cat([g.reshape(-1) for g in grads])
        dist.all_reduce(flat)
        offset = 0
        for g in grads:
            g.copy_(flat[offset: offset + g.numel()].view_as(g))
            offset += g.numel()

    def all_reduce_masks(self, masks) -> None:
        """Union of uint8 row masks over ranks, in place (after :meth:`all_reduce_grads`, the rows any rank wrote)."""
        if self.world == 1:
            return
        for m in masks:
            dist.all_reduce(m, op=dist.ReduceOp.MAX)

    def all_reduce_sum(self, value: float) -> float:
        if self.world == 1:
            return value
        t = torch.tensor([value], dtype=torch.float64, device=self.device)
        dist.all_reduce(t)
        return float(t)

    def barrier(self) -> None:
        if self.world > 1:
            dist.barrier()

    def mine(self, n: int) -> range:
        """Work items 0..n-1 dealt out round-robin: this rank's share."""
        return range(self.rank, n, self.world)

    def combine(self, tensor: torch.Tensor, op: str = "sum") -> torch.Tensor:
        """In place, the elementwise sum (or max) over ranks of a tensor each rank filled its share of."""
        if self.world > 1:
            dist.all_reduce(tensor, dist.ReduceOp.SUM if op == "sum" else dist.ReduceOp.MAX)
        return tensor


def log_linear_lr(step: int, total: int, lr_init: float, lr_final: float, warmup: int = 0) -> float:
    """Log-linear decay from lr_init to lr_final with an optional linear warm-up (mip-NeRF/Zip-NeRF schedule)."""
    frac = min(max(step / max(total, 1), 0.0), 1.0)
    lr = lr_init ** (1 - frac) * lr_final**frac
    if warmup > 0 and step < warmup:
        lr *= (step + 1) / warmup
    return lr


def step_decay_lr(step: int, total: int, lr_init: float, warmup: int = 0, milestones=(0.5, 0.75, 0.9),
                  gamma: float = 0.33) -> float:
    """Constant, then multiplied by ``gamma`` at each milestone fraction (instant-ngp/nerfacc style); warm-up."""
    lr = lr_init * gamma ** sum(step >= m * total for m in milestones)
    if warmup > 0 and step < warmup:
        lr *= (step + 1) / warmup
    return lr


class RateMeter:
    """Rays per second over the recent window, for the progress bar."""

    def __init__(self):
        self.t0, self.n = time.perf_counter(), 0

    def add(self, n: int) -> float:
        self.n += n
        dt = time.perf_counter() - self.t0
        rate = self.n / dt if dt > 0 else 0.0
        if dt > 10:
            self.t0, self.n = time.perf_counter(), 0
        return rate


def tensorboard_writer(run: Path):
    """A TensorBoard event writer in ``run/tensorboard`` (``tensorboard --logdir run``)."""
    try:
        from torch.utils.tensorboard import SummaryWriter
    except ImportError as exc:
        raise ValueError(f"--tensorboard needs the tensorboard package ({exc}); pip install tensorboard") from None
    return SummaryWriter(str(Path(run) / "tensorboard"))


def trim_log(path: Path, last_step: int) -> None:
    """Keep the records of ``path`` (JSON lines) up to ``last_step``, dropping later and torn ones; atomically."""
    kept = []
    for line in path.read_text().splitlines():
        try:
            rec = json.loads(line)
        except json.JSONDecodeError:
            continue  # a line torn by a kill mid-write
        if isinstance(rec, dict) and rec.get("step", 0) <= last_step:
            kept.append(line)
    atomic.write_text(path, "".join(k + "\n" for k in kept))


class RunLog:
    """A run's ``metrics.jsonl`` and, optionally, TensorBoard scalars (``train/*``, ``val/psnr``). Only the main
    rank of a data-parallel run writes; the others get a no-op log."""

    def __init__(self, run: Path, enabled: bool = True, tensorboard: bool = False, start_step: int = 0):
        """``start_step``: the step the run (re)starts from; records after it, written by a run killed after its
        last checkpoint, are dropped so a resumed log holds each step once."""
        path = Path(run) / "metrics.jsonl"
        if enabled and path.is_file():
            trim_log(path, start_step)
        self.file = open(path, "a") if enabled else None
        self.tb = tensorboard_writer(run) if enabled and tensorboard else None

    def train(self, rec: dict) -> None:
        if self.file is None:
            return
        self.file.write(json.dumps(rec) + "\n")
        self.file.flush()
        if self.tb is not None:
            for k, v in rec.items():
                if k not in ("step", "time"):
                    self.tb.add_scalar(f"train/{k}", v, rec["step"])

    def validation(self, step: int, psnr: float, **extra) -> None:
        if self.file is None:
            return
        self.file.write(json.dumps({"step": step, "val_psnr": psnr, **extra}) + "\n")
        if self.tb is not None:
            self.tb.add_scalar("val/psnr", psnr, step)

    def close(self) -> None:
        if self.file is not None:
            self.file.close()
        if self.tb is not None:
            self.tb.close()


def training_curve(run: Path, key: str, points: int | None = None) -> list[dict]:
    """The records of a run's ``metrics.jsonl`` (written by :class:`RunLog`) that hold ``step`` and ``key``, in order;
    with ``points``, about that many evenly spaced ones, the last always kept."""
    path = Path(run) / "metrics.jsonl"
    recs = [json.loads(line) for line in path.read_text().splitlines() if line.strip()] if path.is_file() else []
    recs = [r for r in recs if key in r and "step" in r]
    if points is None or not recs:
        return recs
    every = max(1, len(recs) // points)
    return recs[::every] + ([recs[-1]] if (len(recs) - 1) % every else [])


RUN_CONFIG = "config.json"  # every training run folder's config (teacher and student); finish_run records "complete"


def run_complete(folder: Path) -> bool:
    """Whether the run in ``folder`` reached its last step, as :func:`finish_run` recorded it."""
    path = Path(folder) / RUN_CONFIG
    return path.is_file() and bool(json.loads(path.read_text()).get("complete"))


def finish_run(dp: "DataParallel", ckpt_path: Path, state_fn, config_path: Path, meta: dict, step: int, total: int) -> None:
    """End of a (possibly interrupted) run: the main rank saves the last checkpoint and records in the config
    whether the run is complete; every rank waits; an unfinished run says how to continue."""
    if dp.is_main:
        save_checkpoint(ckpt_path, state_fn(step))
        meta["complete"] = step >= total
        meta["steps_done"] = step
        write_json_atomic(config_path, meta)
    dp.barrier()
    if step < total:
        console.print(f"stopped at step {step}; checkpoint saved — continue with --resume")


def _glibc_malloc_trim():
    """glibc's ``malloc_trim``, or None off glibc (macOS, musl)."""
    try:
        return ctypes.CDLL("libc.so.6").malloc_trim
    except (OSError, AttributeError):
        return None


# Every step hands the heap's free pages back to the system: a trainer whose tensors change size from step to step
# (the grid marcher's sample counts) otherwise leaves glibc's heap fragmented and its RSS climbing. The house's K = 2
# distillation, 150 steps: peak 1.94 GB untrimmed, 1.70 trimmed, 1.39 trimmed with oneDNN's cache capped (see
# nerfbake/__init__.py).
HEAP_TRIM = _glibc_malloc_trim()


def run_steps(out: Path, dp: "DataParallel", desc: str, total: int, start: int, seed: int, step_fn, state_fn,
              checkpoint: Path, checkpoint_every: int, validate=None, val_every: int = 0, tensorboard: bool = False,
              stop_at: int | None = None, summary=None) -> int:
    """Steps ``start`` .. ``total`` of a trainer; returns the step it stopped at (``total``, or earlier on Ctrl-C or
    at ``stop_at``; the caller then saves with :func:`finish_run`).

    ``step_fn(step, generator)`` runs one optimisation step with the step's own generator (so a resumed run draws
    exactly what an uninterrupted one would) and returns (rays in the global batch, a record of plain floats for
    ``metrics.jsonl``). Every 25 steps the record is logged with the step, the rays/s and the time; every 250 the
    main rank prints ``summary(record)``. Every ``val_every`` steps ``validate(step)`` returns (PSNR, extra record
    fields, a line to print); every ``checkpoint_every`` the state ``state_fn(step)`` is saved."""
    rate = RateMeter()
    step = start
    with Interrupt() as interrupt, progress_bar(desc, total, unit="step") as advance:
        advance(start)
        runlog = RunLog(out, dp.is_main, tensorboard, start_step=start)
        try:
            while step < total:
                if interrupt.requested or (stop_at is not None and step >= stop_at):
                    break
                rays, record = step_fn(step, step_generator(seed, step))
                if HEAP_TRIM is not None:
                    HEAP_TRIM(0)
                step += 1
                rays_s = rate.add(rays)
                advance(1)
                if dp.is_main and (step % 25 == 0 or step == total):
                    record = {"step": step, **record, "rays_per_s": rays_s, "time": time.time()}
                    runlog.train(record)
                    if summary is not None and step % 250 == 0:
                        console.print(f"step {step:6d}  {summary(record)}", highlight=False)
                if dp.is_main and validate is not None and val_every and step % val_every == 0:
                    psnr, extra, line = validate(step)
                    runlog.validation(step, psnr, **extra)
                    console.print(f"step {step:6d}  validation PSNR {psnr:.2f} dB {line}")
                if dp.is_main and step % checkpoint_every == 0 and step < total:
                    save_checkpoint(checkpoint, state_fn(step))
        finally:
            runlog.close()
    return step
