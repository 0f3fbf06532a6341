"""Dataset readers and format auto-detection: Blender, LLFF, COLMAP, instant-ngp/nerfstudio transforms.json."""
from __future__ import annotations

from pathlib import Path

from nerfbake.data.dataset import Dataset
from nerfbake.data.errors import DatasetError
from nerfbake.data.formats.blender import read_blender
from nerfbake.data.formats.colmap import find_sparse_dir, read_colmap
from nerfbake.data.formats.llff import read_llff
from nerfbake.data.formats.transforms import read_transforms
from nerfbake.data.normalization import NORMALIZATIONS
from nerfbake.errors import reading

READERS = {"blender": read_blender, "llff": read_llff, "colmap": read_colmap, "transforms": read_transforms}
FORMATS = tuple(READERS)


def detect_format(root: Path) -> str:
    """Name the format of the dataset at ``root`` from the files it contains."""
    root = Path(root)
    if not root.exists():
        raise DatasetError(f"{root}: no such dataset directory")
    if root.is_file():
        if root.name == "transforms.json":
            return "transforms"
        raise DatasetError(f"{root}: pass the dataset directory, not a file")
    if (root / "transforms_train.json").is_file():
        return "blender"
    if (root / "transforms.json").is_file():
        return "transforms"
    if (root / "poses_bounds.npy").is_file():
        return "llff"
    if find_sparse_dir(root) is not None:
        return "colmap"
    raise DatasetError(
        f"{root}: no dataset found; expected transforms_train.json (Blender), transforms.json (instant-ngp/nerfstudio), "
        "poses_bounds.npy (LLFF) or sparse/0/{cameras,images}.{bin,txt} (COLMAP)"
    )


def load_dataset(root: str | Path, format: str | None = None, downscale: float = 1.0, normalize: str = "auto",
                 **options) -> Dataset:
    """Read any supported dataset; ``format`` None auto-detects. ``normalize`` overrides the scene normalisation
    the cameras suggest (Blender scenes keep their own frame). Options are passed to the format's reader."""
    root = Path(root)
    fmt = format or detect_format(root)
    if normalize not in NORMALIZATIONS:
        raise DatasetError(f"{root}: unknown normalisation {normalize!r}; choose one of {', '.join(NORMALIZATIONS)}")
    if normalize != "auto":
        if fmt == "blender":
            raise DatasetError(f"{root}: a Blender-format scene keeps the frame it was rendered in; --normalize applies to "
                               "LLFF, COLMAP and transforms.json captures (leave it at auto)")
        options["normalize"] = normalize
    reader = READERS.get(fmt)
    if reader is None:
        raise DatasetError(f"{root}: unknown dataset format {fmt!r}; choose one of {', '.join(FORMATS)}")
    if root.is_file():
        root = root.parent
    with reading(root, DatasetError, "check the dataset's files (nerfbake data info shows what is read)"):
        return reader(root, downscale=downscale, **options)
