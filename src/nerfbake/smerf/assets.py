"""Reading SMERF asset directories in the official web viewer's layout (one ``sm_XXX/`` folder per submodel).

Arrays are gzip'd uint8 (``raw.gz``) written after reversing the spatial axes, so numpy axis 0 of the baked
array is the fastest texture axis: a 3-D grid of side n arrives as an image with rows ``w * n + v`` and columns
``u``; the sparse atlas arrives one depth slice (w) per file. Here every grid is returned indexed ``[u, v, w, c]``
in the viewer's frame (x' = -x, y' = z, z' = y of the training frame). See ``shared/reference/smerf_anchors.md``.
"""
from __future__ import annotations

import gzip
import json
import zlib
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from nerfbake.errors import NerfbakeError, reading

# The viewer's world axes from the training frame's: (x', y', z') = (-x, z, y), its own inverse. The baked assets,
# the viewer's camera and the student's deferred-MLP view directions all use it.
VIEWER_FROM_TRAIN = np.array([[-1.0, 0, 0], [0, 0, 1], [0, 1, 0]])


class AssetError(NerfbakeError):
    """A SMERF asset directory that cannot be read; names the file and the fix."""


def _read_raw(path: Path, shape) -> np.ndarray:
    for candidate in (path, path.with_suffix("")):  # X.raw.gz, or an already-decompressed X.raw
        if candidate.is_file():
            data = candidate.read_bytes()
            if candidate.suffix == ".gz":
                try:
                    data = gzip.decompress(data)
                except (OSError, EOFError, zlib.error) as exc:
                    raise AssetError(f"{candidate}: not a valid gzip file ({exc}); re-export the submodel") from None
            arr = np.frombuffer(data, np.uint8)
            if arr.size != int(np.prod(shape)):
                raise AssetError(f"{candidate}: {arr.size} bytes, expected {int(np.prod(shape))} for shape {list(shape)} "
                                 "in scene_params.json's asset_metadata; the file is truncated or from another export")
            return arr.reshape(shape)
    raise AssetError(f"{path}: missing; the asset directory is incomplete (re-run the bake/export)")


def _grid_from_image(img: np.ndarray, n: int) -> np.ndarray:
    """(n*n, n, C) image rows w*n+v, columns u  ->  [u, v, w, C]."""
    return np.ascontiguousarray(img.reshape(n, n, n, -1).transpose(2, 1, 0, 3))


@dataclass
class Submodel:
    """One submodel's arrays (uint8, [u, v, w, C] / planes [u, v, C]) and parameters."""

    root: Path
    params: dict
    block_indices: np.ndarray  # (nB, nB, nB, 3)
    atlas_rgb: np.ndarray  # (AW, AH, AD, 3)
    atlas_density: np.ndarray  # (AW, AH, AD, 2): density, gate
    atlas_features: np.ndarray  # (AW, AH, AD, 3)
    plane_rgb: np.ndarray  # (3, T, T, 3)
    plane_density: np.ndarray  # (3, T, T, 1)
    plane_features: np.ndarray  # (3, T, T, 4)
    occupancy: dict[int, np.ndarray] = field(default_factory=dict)  # factor -> (n, n, n) packed bits
    distance: dict[int, np.ndarray] = field(default_factory=dict)  # factor -> (n, n, n)


FIX = "re-bake it with `nerfbake bake`, or re-export it from the authors' code"


def _read_json(path: Path) -> dict:
    """A JSON object from ``path`` (gzip when it ends in .gz), every failure an :class:`AssetError` naming it."""
    with reading(path, AssetError, FIX):
        data = path.read_bytes()
        if path.suffix == ".gz":
            data = gzip.decompress(data)
        obj = json.loads(data)
    if not isinstance(obj, dict):
        raise AssetError(f"{path}: holds a JSON {type(obj).__name__}, expected an object; {FIX}")
    return obj


def params_path(sm_dir: Path) -> Path:
    """``scene_params.json``, or its ``.gz`` when only that is there."""
    path = Path(sm_dir) / "scene_params.json"
    return path if path.is_file() else path.with_name("scene_params.json.gz")


def read_params(sm_dir: Path) -> dict:
    """``scene_params.json`` of one ``sm_XXX`` folder, with an error naming it when it is missing or unreadable."""
    path = params_path(sm_dir)
    if not path.is_file():
        raise AssetError(f"{Path(sm_dir) / 'scene_params.json'}: missing; point at an sm_XXX folder of a baked SMERF scene")
    return _read_json(path)


def load_submodel(sm_dir: str | Path) -> Submodel:
    """Every array of one submodel; anything wrong is an :class:`AssetError` naming the file."""
    sm_dir = Path(sm_dir)
    p = read_params(sm_dir)
    with reading(params_path(sm_dir), AssetError, FIX):
        return _load_submodel(sm_dir, p)


def _load_submodel(sm_dir: Path, p: dict) -> Submodel:
    if not isinstance(p.get("asset_metadata"), list):
        raise AssetError(f"{params_path(sm_dir)}: no asset_metadata list (the file names and shapes of every array); "
                         f"{FIX}")
    if p.get("export_array_format", "png") != "raw.gz":
        raise AssetError(f"{sm_dir}: export_array_format {p.get('export_array_format')!r}; nerfbake reads raw.gz assets")
    if not p.get("export_store_rgb_and_density_separately", False):
        raise AssetError(f"{sm_dir}: legacy merged rgb+density layout is not supported; export with separate rgb/density")
    meta = {m["filename"]: m for m in p["asset_metadata"]}

    def arr(name):
        m = meta.get(name)
        if m is None:
            raise AssetError(f"{sm_dir / 'scene_params.json'}: asset_metadata has no entry for {name}")
        return _read_raw(sm_dir / name, m["shape"])

    nb = p["sparse_grid_resolution"] // p["data_block_size"]
    slices = int(p["num_slices"])

    def atlas(kind):
        return np.ascontiguousarray(np.stack([arr(f"sparse_grid_{kind}_{k:03d}.raw.gz") for k in range(slices)], 0)
                                    .transpose(2, 1, 0, 3))  # [w][v][u] -> [u, v, w]

    planes = {kind: np.stack([arr(f"plane_{kind}_{k}.raw.gz").transpose(1, 0, 2) for k in range(3)])
              for kind in ("rgb", "density", "features")}
    sm = Submodel(sm_dir, p, _grid_from_image(arr("sparse_grid_block_indices.raw.gz"), nb), atlas("rgb"), atlas("density"),
                  atlas("features"), planes["rgb"], planes["density"], planes["features"])
    t = p["triplane_resolution"]
    for name, m in meta.items():
        for kind, store in (("occupancy_grid_", sm.occupancy), ("distance_grid_", sm.distance)):
            if name.startswith(kind):
                factor = int(name[len(kind):].split("_")[0])
                n = -(-t // factor)
                slices_n = m.get("slice_count", 1)
                if slices_n == 1:
                    store[factor] = _grid_from_image(arr(name), n)[..., -1]
                elif m.get("slice_idx", 0) == 0:
                    parts = [arr(name.replace("_000.", f"_{i:03d}.")) for i in range(slices_n)]
                    store[factor] = _grid_from_image(np.concatenate(parts, 0), n)[..., -1]
    if 8 not in sm.occupancy or 8 not in sm.distance:
        raise AssetError(f"{sm_dir}: needs occupancy_grid_8 and distance_grid_8 (the viewer's factor-8 grids)")
    return sm


def load_deferred_mlp(sm_dir: str | Path, params: dict) -> dict[str, np.ndarray]:
    """``ResampleDense_{0,1,2}/{kernel,bias}`` arrays ([N, P, P, P, in, out] / [N, P, P, P, out])."""
    if "deferred_mlp" in params:
        raw = params["deferred_mlp"]
    else:
        path = Path(sm_dir) / "deferred_mlp.json.gz"
        if not path.is_file():
            raise AssetError(f"{path}: missing (scene_params says the deferred MLP is stored separately)")
        raw = _read_json(path)
    where = Path(sm_dir) / "deferred_mlp.json.gz" if "deferred_mlp" not in params else params_path(Path(sm_dir))
    with reading(where, AssetError, FIX):
        out = {k: np.asarray(v["data"], np.float32).reshape(v["shape"]) for k, v in raw.items()}
    for layer in range(3):
        if f"ResampleDense_{layer}/kernel" not in out:
            raise AssetError(f"{where}: deferred MLP lacks ResampleDense_{layer}; the viewer needs exactly 3 grid layers")
    bad = [k for k, v in out.items() if not np.all(np.isfinite(v))]
    if bad:
        raise AssetError(f"{where}: deferred MLP weights {', '.join(bad)} hold NaN or infinite values; {FIX}")
    return out


@dataclass
class SceneAssets:
    """Every submodel of a baked scene, loaded on first use (as the viewer streams them)."""

    root: Path  # the folder holding sm_XXX/
    params: dict  # the first submodel's scene_params
    mlp: dict
    _cache: dict = field(default_factory=dict)
    device_scenes: dict = field(default_factory=dict)  # (params index, device) -> renderer's copy of a submodel

    @classmethod
    def open(cls, path: str | Path) -> "SceneAssets":
        path = Path(path)
        first = path if (path / "scene_params.json").is_file() or (path / "scene_params.json.gz").is_file() else None
        if first is None:
            subs = sorted(path.glob("sm_*"))
            if not subs:
                raise AssetError(f"{path}: no sm_XXX folders and no scene_params.json; not a SMERF asset directory")
            first = subs[0]
        params = read_params(first)
        return cls(first.parent, params, load_deferred_mlp(first, params))

    def submodel(self, params_idx: int) -> Submodel:
        if params_idx not in self._cache:
            sm = self.params["params_to_sm"][params_idx]
            self._cache[params_idx] = load_submodel(self.root / f"sm_{sm:03d}")
        return self._cache[params_idx]
