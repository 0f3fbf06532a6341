"""Check a baked SMERF asset directory against the official viewer's format rules (``shared/reference/
smerf_anchors.md`` section 1): every ``scene_params.json`` key, file name, dtype and size, and the block/atlas
invariants. Returns readable problems; an empty list means the official viewer can load the directory."""
from __future__ import annotations

import gzip
import json
import math
from pathlib import Path

import numpy as np

REQUIRED_KEYS = (
    "triplane_resolution", "sparse_grid_resolution", "triplane_voxel_size", "sparse_grid_voxel_size", "voxel_size_to_use",
    "resolution_to_use", "data_block_size", "atlas_width", "atlas_height", "atlas_depth", "num_slices", "slice_depth",
    "range_features", "range_density", "merge_features_combine_op", "deferred_rendering_mode", "activation",
    "feature_gating", "export_array_format", "export_slice_occupancy_and_distance_grids",
    "export_pad_occupancy_and_distance_grids", "export_store_deferred_mlp_separately",
    "export_store_rgb_and_density_separately", "export_apply_zdiff_to_slices", "submodel_idx", "submodel_voxel_size",
    "submodel_scale", "num_submodels", "num_local_submodels", "sm_to_params", "params_to_sm", "submodels_on_host",
    "submodel_idx_override", "num_submodel_mlp_kernels", "num_submodel_hash_encoding_kernels", "default_exposure",
    "exposure_range", "asset_metadata",
)
OCCUPANCY_FACTORS = (4, 8, 16, 32, 64, 128)
ATLAS_BLOCK = 9
MAX_ATLAS_SIDE = 2048


def _close(a, b) -> bool:
    return math.isclose(float(a), float(b), rel_tol=1e-6, abs_tol=1e-9)


def submodel_problems(sm_dir: str | Path) -> list[str]:
    """Reasons the official viewer would fail on one ``sm_XXX`` folder (missing keys, files of the wrong size or
    shape); empty when it loads."""
    sm_dir = Path(sm_dir)
    out: list[str] = []
    path = sm_dir / "scene_params.json"
    try:
        p = json.loads(path.read_text())
    except (OSError, json.JSONDecodeError) as exc:
        return [f"{path}: unreadable ({exc})"]
    missing = [k for k in REQUIRED_KEYS if k not in p]
    if missing:
        out.append(f"{path}: missing keys {', '.join(missing)}")
        if any(k in missing for k in ("triplane_resolution", "sparse_grid_resolution", "asset_metadata", "data_block_size")):
            return out
    t, s, b = p["triplane_resolution"], p["sparse_grid_resolution"], p["data_block_size"]
    for key, want in (("triplane_voxel_size", 4 / t), ("sparse_grid_voxel_size", 4 / s),
                      ("voxel_size_to_use", min(4 / t, 4 / s)), ("resolution_to_use", max(t, s))):
        if key in p and not _close(p[key], want):
            out.append(f"{path}: {key} = {p[key]}, expected {want}")
    if p.get("export_array_format") != "raw.gz":
        out.append(f"{path}: export_array_format {p.get('export_array_format')!r}; the viewer setup uses raw.gz")
    if p.get("export_apply_zdiff_to_slices"):
        out.append(f"{path}: export_apply_zdiff_to_slices is set; the viewer cannot undo it")
    if not p.get("export_store_rgb_and_density_separately"):
        out.append(f"{path}: export_store_rgb_and_density_separately must be true (separate rgb/density/features)")
    aw, ah, ad = p.get("atlas_width", 0), p.get("atlas_height", 0), p.get("atlas_depth", 0)
    for name, v in (("atlas_width", aw), ("atlas_height", ah), ("atlas_depth", ad)):
        if v <= 0 or v % ATLAS_BLOCK or v > MAX_ATLAS_SIDE:
            out.append(f"{path}: {name} {v} must be a positive multiple of {ATLAS_BLOCK} and at most {MAX_ATLAS_SIDE}")
    if p.get("num_slices") != ad or p.get("slice_depth") != 1:
        out.append(f"{path}: num_slices must equal atlas_depth ({ad}) with slice_depth 1")
    k = round(2 / p.get("submodel_voxel_size", 2))
    if p.get("num_submodels") != k ** 3 or len(p.get("sm_to_params", [])) != k ** 3:
        out.append(f"{path}: num_submodels / sm_to_params must cover the {k}^3 grid")
    alive = [i for i, v in enumerate(p.get("sm_to_params", [])) if v >= 0]
    if [p["sm_to_params"][i] for i in alive] != list(range(len(alive))) or p.get("params_to_sm") != alive:
        out.append(f"{path}: sm_to_params and params_to_sm are not inverse maps")
    if p.get("num_local_submodels") != len(alive):
        out.append(f"{path}: num_local_submodels {p.get('num_local_submodels')} != {len(alive)} alive submodels")
    if f"sm_{p.get('submodel_idx', -1):03d}" != sm_dir.name:
        out.append(f"{path}: submodel_idx {p.get('submodel_idx')} does not match the folder name {sm_dir.name}")
    for key in ("range_features", "range_density"):
        r = p.get(key, [0, 0])
        if len(r) != 2 or not r[0] < r[1]:
            out.append(f"{path}: {key} must be [min, max] with min < max")

    nb = s // b
    expected = {"sparse_grid_block_indices.raw.gz": [nb * nb, nb, 3]}
    for kind, c in (("rgb", 3), ("density", 2), ("features", 3)):
        for i in range(ad):
            expected[f"sparse_grid_{kind}_{i:03d}.raw.gz"] = [ah, aw, c]
    for kind, c in (("rgb", 3), ("density", 1), ("features", 4)):
        for i in range(3):
            expected[f"plane_{kind}_{i}.raw.gz"] = [t, t, c]
    for f in OCCUPANCY_FACTORS:
        n = -(-t // f)
        sliced = p.get("export_slice_occupancy_and_distance_grids", True) and n > 256
        c = 4 if p.get("export_pad_occupancy_and_distance_grids") else 1
        for kind in ("occupancy_grid", "distance_grid"):
            if sliced:
                for i in range(8):
                    expected[f"{kind}_{f}_{i:03d}.raw.gz"] = [n * n // 8, n, c]
            else:
                expected[f"{kind}_{f}_000.raw.gz"] = [n * n, n, c]
    meta = {m.get("filename"): m for m in p.get("asset_metadata", [])}
    arrays: dict[str, np.ndarray] = {}
    for name, shape in expected.items():
        m = meta.get(name)
        if m is None:
            out.append(f"{path}: asset_metadata lacks {name}")
            continue
        if list(m.get("shape", [])) != shape or m.get("dtype") != "uint8" or m.get("format") != "raw.gz":
            out.append(f"{path}: {name} metadata {m.get('shape')} {m.get('dtype')} {m.get('format')}, expected {shape} uint8 raw.gz")
        f = sm_dir / name
        if not f.is_file():
            out.append(f"{f}: missing")
            continue
        try:
            raw = gzip.decompress(f.read_bytes())
        except (OSError, EOFError) as exc:
            out.append(f"{f}: not gzip ({exc})")
            continue
        if len(raw) != int(np.prod(shape)):
            out.append(f"{f}: {len(raw)} bytes, expected {int(np.prod(shape))}")
            continue
        arrays[name] = np.frombuffer(raw, np.uint8).reshape(shape)
    extra = sorted(set(meta) - set(expected))
    if extra:
        out.append(f"{path}: asset_metadata lists unexpected files {', '.join(extra)}")

    idx = arrays.get("sparse_grid_block_indices.raw.gz")
    if idx is not None and aw and ah and ad:
        flat = idx.reshape(-1, 3).astype(int)
        empty = (flat == 255).all(1)
        if ((flat == 255).any(1) & ~empty).any():
            out.append(f"{sm_dir}: block indices mix 255 (empty) with real coordinates in one entry")
        live = flat[~empty]
        if (live >= np.array([aw, ah, ad]) // ATLAS_BLOCK).any():
            out.append(f"{sm_dir}: a block index points outside the {aw}x{ah}x{ad} atlas")
        if len(np.unique(live, axis=0)) != len(live):
            out.append(f"{sm_dir}: two blocks share one atlas slot")
    for f in OCCUPANCY_FACTORS:
        occ, dist = arrays.get(f"occupancy_grid_{f}_000.raw.gz"), arrays.get(f"distance_grid_{f}_000.raw.gz")
        if occ is None or dist is None or occ.shape != dist.shape or occ.shape[0] != occ.shape[1] ** 2:
            continue  # missing, misshapen (named above) or sliced into files
        n = occ.shape[1]
        occupied = occ[..., -1].reshape(n, n, n) > 0
        if not occupied.any():
            continue  # nothing to jump into: any byte is safe (the export caps these cells at min(255, n), not n - 1)
        if (dist.reshape(n, n, n, -1) > distance_grid(occupied)[..., None]).any():
            out.append(f"{sm_dir}: distance_grid_{f} lets the viewer jump into occupied cells of occupancy_grid_{f} "
                       "(each byte may be at most the Chebyshev distance to an occupied cell minus 1); re-bake it")

    mlp_path = sm_dir / "deferred_mlp.json.gz"
    if p.get("export_store_deferred_mlp_separately"):
        try:
            mlp = json.loads(gzip.decompress(mlp_path.read_bytes()))
        except (OSError, EOFError, json.JSONDecodeError) as exc:
            out.append(f"{mlp_path}: unreadable ({exc})")
            mlp = {}
    else:
        mlp = p.get("deferred_mlp", {})
    width_in = 41 if p.get("merge_features_combine_op") == "coarse_sum" else 34
    for layer in range(3):
        kern, bias = mlp.get(f"ResampleDense_{layer}/kernel"), mlp.get(f"ResampleDense_{layer}/bias")
        if kern is None or bias is None:
            out.append(f"{mlp_path}: missing ResampleDense_{layer} (the viewer needs exactly 3 grid layers)")
            continue
        ks, bs = kern["shape"], bias["shape"]
        if len(ks) != 6 or ks[0] != p.get("num_local_submodels") or not ks[1] == ks[2] == ks[3] or bs != ks[:4] + ks[5:]:
            out.append(f"{mlp_path}: ResampleDense_{layer} shapes {ks} / {bs} are not [N, P, P, P, in, out] / [N, P, P, P, out]")
        elif layer == 0 and ks[4] != width_in:
            out.append(f"{mlp_path}: layer 0 takes {ks[4]} inputs, the viewer feeds {width_in}")
        elif len(kern["data"]) != int(np.prod(ks)) or len(bias["data"]) != int(np.prod(bs)):
            out.append(f"{mlp_path}: ResampleDense_{layer} data length does not match its shape")
    frames = sm_dir / "test_frames.json"
    try:
        tf = json.loads(frames.read_text())["test_frames"]
        if any(len(f["position"]) != 3 or len(f["rotation"]) != 16 or len(f["projection"]) != 16 for f in tf):
            out.append(f"{frames}: each frame needs position[3], rotation[16], projection[16]")
    except (OSError, KeyError, TypeError, json.JSONDecodeError) as exc:
        out.append(f"{frames}: unreadable ({exc})")
    return out


def distance_grid(occupied: np.ndarray) -> np.ndarray:
    """Per cell of an (n, n, n) occupancy, how many whole cells a ray may jump from anywhere inside it without
    entering an occupied one: the Chebyshev distance to the nearest occupied cell minus 1 (0 on occupied cells and
    their 26 neighbours), capped at min(255, n) - 1. The viewer jumps ``byte`` cells at once, so a cell next to an
    occupied one must hold 0: a point on its far side may be a hair from the occupied cell (the authors' grids hold
    exactly this; storing the distance itself let rays jump through thin surfaces, 0.7 dB of lego's bake loss).
    Grown one ring at a time by a separable 3-box dilation; numpy, so the validator can recompute it."""
    occ = np.asarray(occupied, bool)
    cap = min(255, occ.shape[0]) - 1
    dist = np.full(occ.shape, cap, np.uint8)
    dist[occ] = 0
    cur = occ
    for ring in range(1, cap + 1):
        if cur.all():
            break
        grown = cur.copy()
        for axis in range(3):
            lower = tuple(slice(0, -1) if a == axis else slice(None) for a in range(3))
            upper = tuple(slice(1, None) if a == axis else slice(None) for a in range(3))
            step = grown.copy()
            step[lower] |= grown[upper]
            step[upper] |= grown[lower]
            grown = step
        dist[grown & ~cur] = ring - 1
        cur = grown
    return dist


def asset_problems(root: str | Path) -> list[str]:
    """Problems of every ``sm_XXX`` folder under ``root`` (or of ``root`` itself if it is one)."""
    root = Path(root)
    subs = [root] if (root / "scene_params.json").is_file() else sorted(root.glob("sm_*"))
    if not subs:
        return [f"{root}: no sm_XXX folders"]
    return [msg for sm in subs for msg in submodel_problems(sm)]
