"""Every file and folder nerfbake writes appears whole or not at all.

A file is written under a temporary name in its own folder (``.NAME.tmp-PID-RANDOM``, keeping NAME's suffix so
writers that pick a format from it still do) and renamed over the target; a folder is built the same way and
swapped in: an existing one is first renamed aside, then the new one renamed in, then the old one removed, so a
kill at any moment leaves either the old or the new output, never a mix or nothing. Outputs get the modes the
process's umask gives any new file (``tempfile`` would leave 0600/0700: trees unreadable to other users and web
servers). Temporary names carry the pid, so a cleanup only removes the leftovers of processes that are gone,
never a concurrent writer's work.
"""
from __future__ import annotations

import json
import os
import re
import secrets
import shutil
from contextlib import contextmanager
from pathlib import Path

from nerfbake.errors import NerfbakeError


def _umask() -> int:
    mask = os.umask(0o022)
    os.umask(mask)
    return mask


UMASK = _umask()
FILE_MODE = 0o666 & ~UMASK
DIR_MODE = 0o777 & ~UMASK


class OutputExistsError(NerfbakeError):
    """An output folder that holds something and was not allowed to be replaced."""


def temp_name(path: Path, tag: str = "tmp", keep_suffix: bool = True) -> Path:
    path = Path(path)
    suffix = "".join(path.suffixes[-2:]) if keep_suffix else ""
    return path.with_name(f".{path.name}.{tag}-{os.getpid()}-{secrets.token_hex(3)}{suffix}")


def _pid_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def remove_stale_temps(path: Path) -> None:
    """Remove temporaries of ``path`` left by processes that no longer run (a killed writer's half output)."""
    path = Path(path)
    pattern = re.compile(rf"\.{re.escape(path.name)}\.(?:tmp|old)-(\d+)-[0-9a-f]+")
    if not path.parent.is_dir():
        return
    for entry in path.parent.iterdir():
        m = pattern.match(entry.name)
        if m and int(m.group(1)) != os.getpid() and not _pid_alive(int(m.group(1))):
            if entry.is_dir() and not entry.is_symlink():
                shutil.rmtree(entry, ignore_errors=True)
            else:
                entry.unlink(missing_ok=True)


@contextmanager
def atomic_file(path: str | Path):
    """Yields a temporary path beside ``path`` to write; on success it replaces ``path``, on error it is removed."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    remove_stale_temps(path)
    tmp = temp_name(path)
    try:
        yield tmp
        os.chmod(tmp, FILE_MODE)
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)


def write_bytes(path: str | Path, data: bytes) -> Path:
    with atomic_file(path) as tmp:
        tmp.write_bytes(data)
    return Path(path)


def write_text(path: str | Path, text: str) -> Path:
    return write_bytes(path, text.encode())


def write_json(path: str | Path, obj, indent: int | None = 2) -> Path:
    return write_text(path, json.dumps(obj, indent=indent))


def write_image(path: str | Path, image) -> Path:
    """An 8-bit image (format from the suffix), written atomically."""
    import imageio.v3 as iio  # here, not at the top: the CLI imports this module at start-up

    with atomic_file(path) as tmp:
        iio.imwrite(tmp, image, extension=Path(path).suffix)
    return Path(path)


def check_output_folder(path: str | Path, overwrite: bool, what: str = "output") -> None:
    """Refuse a non-empty existing ``path`` unless ``overwrite``: the clear error before any work starts."""
    path = Path(path)
    if path.exists() and not path.is_dir():
        raise OutputExistsError(f"{path}: exists and is not a folder; choose another --out")
    if path.is_dir() and any(path.iterdir()) and not overwrite:
        raise OutputExistsError(f"{path}: the {what} folder exists and is not empty; pass --overwrite to replace it "
                                "or choose another --out")


@contextmanager
def atomic_folder(path: str | Path, overwrite: bool = False, what: str = "output"):
    """Yields an empty temporary folder beside ``path`` to fill; on success it becomes ``path`` (an existing one is
    renamed aside first and removed after the swap; refused unless ``overwrite`` when it is not empty), on error
    it is removed and ``path`` is untouched."""
    path = Path(path)
    check_output_folder(path, overwrite, what)
    path.parent.mkdir(parents=True, exist_ok=True)
    remove_stale_temps(path)
    tmp = temp_name(path, keep_suffix=False)
    tmp.mkdir(mode=DIR_MODE)
    os.chmod(tmp, DIR_MODE)
    try:
        yield tmp
        replace_folder(tmp, path)
    finally:
        if tmp.exists():
            shutil.rmtree(tmp, ignore_errors=True)


def replace_folder(new: Path, path: Path) -> None:
    """Rename ``new`` to ``path``, swapping out (then removing) an existing ``path``."""
    old = None
    if path.exists():
        old = temp_name(path, "old", keep_suffix=False)
        os.replace(path, old)
    os.replace(new, path)
    if old is not None:
        shutil.rmtree(old, ignore_errors=True) if old.is_dir() else old.unlink(missing_ok=True)


def check_output_file(path: str | Path, overwrite: bool) -> None:
    """Refuse an existing file output unless ``overwrite`` (it is then replaced atomically when the new one is done)."""
    path = Path(path)
    if path.is_dir():
        raise OutputExistsError(f"{path}: is a folder; --out takes a file path here")
    if path.exists() and not overwrite:
        raise OutputExistsError(f"{path}: exists; pass --overwrite to replace it or choose another --out")
