"""NVIDIA Warp kernels, one source for CPU and CUDA, behind thin torch wrappers.

Warp runs a CPU launch on one thread, so :func:`parallel_launch` splits a launch over a thread pool (ctypes
releases the GIL while a kernel runs) along an axis whose work items write disjoint memory.
"""
from __future__ import annotations

import contextlib
import ctypes
import functools
import os
import sys
from concurrent.futures import ThreadPoolExecutor

import torch


@functools.lru_cache(maxsize=1)
def warp():
    """The ``warp`` module, initialised once (quietly on machines without a CUDA driver)."""
    import warp as wp

    wp.config.log_level = 30  # warnings only: no banner on every command
    if _has_cuda_driver():
        wp.init()
    else:
        with _quiet_stderr():  # Warp's native init prints a driver warning on every CPU-only machine
            wp.init()
    return wp


def _has_cuda_driver() -> bool:
    for name in ("libcuda.so.1", "libcuda.so", "nvcuda.dll"):
        try:
            ctypes.CDLL(name)
            return True
        except OSError:
            continue
    return False


@contextlib.contextmanager
def _quiet_stderr():
    sys.stderr.flush()
    saved = os.dup(2)
    devnull = os.open(os.devnull, os.O_WRONLY)
    try:
        os.dup2(devnull, 2)
        yield
    finally:
        os.dup2(saved, 2)
        os.close(saved)
        os.close(devnull)


def device_of(tensor) -> str:
    """Warp's device string for a torch tensor's device ("cpu" or "cuda:N")."""
    return "cpu" if tensor.device.type == "cpu" else f"cuda:{tensor.device.index or 0}"


def flush_denormals() -> None:
    """Round subnormal floats to zero on this CPU thread and on the threads it starts later.

    Adam's moments of the grid cells a distillation no longer reaches decay by β every step and are subnormal
    after ~800 steps (8 % of a lego student's sparse-grid moments by step 2300); x86 arithmetic on subnormals is
    ~20× slower, so the dense Adam step over the student's 160 M grid values grew from 0.13 s to 0.8 s and the
    distillation from 8k to 3.6k rays/s (``benchmarks/subnormal_floats.py``). Values that small change no result.
    The mode is per thread and a new thread copies its creator's: torch's worker threads keep the mode they were
    started with, so this must run before the process's first parallel op (trainers do it as they start: see
    ``DataParallel``); the kernel pool sets it in each of its workers. It stays on for the rest of the process."""
    torch.set_flush_denormal(True)


@functools.lru_cache(maxsize=1)
def _pool() -> ThreadPoolExecutor:
    return ThreadPoolExecutor(max_workers=cpu_threads(), initializer=flush_denormals)


def cpu_threads() -> int:
    """Threads a CPU launch is split over: ``NERFBAKE_THREADS`` or the cores this process may use."""
    return max(1, int(os.environ.get("NERFBAKE_THREADS", len(os.sched_getaffinity(0)))))


_LOADED: set = set()


def ensure_loaded(kernel, device: str) -> None:
    """Compile/load a kernel's module once, before threads race to do it."""
    key = (kernel.module.name, device)
    if key not in _LOADED:
        warp().load_module(kernel.module, device=device)
        _LOADED.add(key)


def parallel_map(fn, chunks):
    """Run ``fn(chunk)`` for every chunk on the CPU thread pool (or inline for one chunk)."""
    chunks = list(chunks)
    if len(chunks) <= 1:
        return [fn(c) for c in chunks]
    return list(_pool().map(fn, chunks))


def launch_chunks(n: int, device: str, parts: int | None = None) -> list[tuple[int, int]]:
    """Split ``n`` work items into contiguous [start, end) ranges: one on a GPU, ~2 per CPU thread on the CPU."""
    if parts is None:
        parts = 1 if device != "cpu" or n < 4096 else cpu_threads() * 2
    bounds = [round(i * n / parts) for i in range(parts + 1)]
    return [(bounds[i], bounds[i + 1]) for i in range(parts) if bounds[i + 1] > bounds[i]]
