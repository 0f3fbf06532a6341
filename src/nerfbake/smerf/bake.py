"""``nerfbake bake``: a student -> an asset directory in the official SMERF viewer's layout (one ``sm_XXX/``
folder per alive submodel). The steps follow the authors' baker (``shared/reference/smerf_anchors.md`` section 3):

1. alive voxels at the triplane resolution: render the training cameras within 1.5 cell widths of the submodel's
   centre (SMERF appendix C.2; its own cameras alone left a K = 2 bake 6.3 dB under its student) on the teacher's
   intervals with the final alpha-culling threshold; every sample whose weight and whose alpha at the viewer's step
   size exceed it marks the 8 voxels around it (each camera's teacher intervals are rendered once for all the
   submodels near it);
2. 3x3x3 median filter (majority of 27);
3. max-filter pyramid -> occupancy grids at factors 2..128, bit-packed 2x2x2 per byte, and distance grids;
4. 8^3 macroblocks of the sparse grid that hold an alive voxel, packed into a 3-D atlas of 9^3 blocks (one-voxel
   apron) with a uint8 block-index grid (255 = empty), each atlas side <= 2048;
5. uint8 quantisation with the documented ranges; plane texels the viewer can never read (outside every occupied
   factor-4 column, dilated by one texel) set to byte 0, as the authors' baker does;
6. ``scene_params.json`` (+ .gz), ``deferred_mlp.json.gz``, ``test_frames.json`` (the test views whose camera the
   submodel holds), arrays as ``raw.gz`` in reversed axis order; beside the folders ``bake.json`` and a
   ``test_frames.json`` with every test view in the dataset's order (the walk across submodels).

Everything is written to a temporary sibling folder and renamed into place at the end: no half-written output.
"""
from __future__ import annotations

import gzip
import json
import os
import shutil
import time
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F

from nerfbake.atomic import DIR_MODE, check_output_folder, remove_stale_temps, replace_folder, temp_name
from nerfbake.data.formats import load_dataset
from nerfbake.data.rays import camera_rays, pixel_grid
from nerfbake.errors import NerfbakeError
from nerfbake.progress import console, progress_bar
from nerfbake.render.quantize import RANGE_DENSITY, RANGE_FEATURES, to_bytes
from nerfbake.smerf.assets import VIEWER_FROM_TRAIN
from nerfbake.smerf.baked_render import ViewerCamera
from nerfbake.smerf.deferred_mlp import deferred_mlp_text
from nerfbake.smerf.distill import teacher_background
from nerfbake.smerf.run import load_student
from nerfbake.smerf.validate import ATLAS_BLOCK, MAX_ATLAS_SIDE, OCCUPANCY_FACTORS, distance_grid
from nerfbake.teacher.protocol import Teacher
from nerfbake.teacher.run import load_teacher
from nerfbake.train.loop import DataParallel

BLOCK = 8
MAX_BLOCKS_PER_AXIS = MAX_ATLAS_SIDE // ATLAS_BLOCK  # 227, also below the 255 "empty" marker


class BakeError(NerfbakeError):
    """Baking cannot proceed (nothing occupied, an unwritable or non-empty output); names the cause and the fix."""


# ---- geometry --------------------------------------------------------------------------------------------------
ALIVE_BUDGET_BYTES = 1 << 29  # the alive grids (a bool a voxel, one grid a submodel) one pass over the cameras fills


@torch.no_grad()
def alive_voxels(student, teacher: Teacher, cameras, submodels: dict[int, np.ndarray], threshold: float, background,
                 stride: int = 2, chunk: int = 1 << 13, progress=None) -> dict[int, torch.Tensor]:
    """Per submodel of ``submodels`` ({params index: (N,) bool, the ``cameras`` that bake it}): (T, T, T) bool over
    contracted space (viewer axes), the voxels next to a sample the submodel really shows.

    The teacher renders each camera once for every submodel that uses it: its intervals do not depend on the
    submodel, and its march is most of a bake's time (the house's indoor grid teacher: ~5 of a submodel's 6 min)."""
    t = student.cfg.triplane_resolution
    alive = {p: torch.zeros(t ** 3, dtype=torch.bool) for p in submodels}
    corners = torch.tensor([[(c >> 2) & 1, (c >> 1) & 1, c & 1] for c in range(8)])
    dev = student.sparse.device
    bg = torch.tensor(background, device=dev)
    for i, cam in enumerate(cameras):
        users = [p for p, near in submodels.items() if near[i]]
        if not users:
            continue
        pix = pixel_grid(cam.width, cam.height)[::stride, ::stride].reshape(-1, 2)
        rays = camera_rays(cam, pix)
        for a in range(0, pix.shape[0], chunk):
            o, d = rays["origins"][a:a + chunk].to(dev), rays["directions"][a:a + chunk].to(dev)
            tout = teacher.render_rays(o, d, bg.expand(o.shape[0], 3))
            for p in users:
                pidx = torch.full((o.shape[0],), p, dtype=torch.long, device=dev)
                out = student.render(o, d, pidx, tout["t0"], tout["t1"], tout["ray_idx"], cull_alpha=threshold)
                alpha_rt = 1.0 - torch.exp(-out["density"] * student.realtime_step(out["stretch"]))
                keep = (out["w"] > threshold) & (alpha_rt > threshold)
                if not keep.any():
                    continue
                g = ((out["z"][keep].cpu() + 2) / 4 * t - 0.5).floor().long()
                idx = (g[:, None, :] + corners[None]).clamp(0, t - 1).reshape(-1, 3)
                alive[p][(idx[:, 0] * t + idx[:, 1]) * t + idx[:, 2]] = True
        if progress is not None:
            progress()
    return {p: grid.view(t, t, t) for p, grid in alive.items()}


def median_filter_3(grid: torch.Tensor) -> torch.Tensor:
    """3x3x3 median of a boolean grid = at least 14 of the 27 neighbours set (outside counts as empty)."""
    count = F.avg_pool3d(grid[None, None].float(), 3, stride=1, padding=1, count_include_pad=True)[0, 0] * 27
    return count > 13.5


def max_pool(grid: torch.Tensor, factor: int) -> torch.Tensor:
    """Boolean occupancy (D, H, W) pooled by ``factor`` (a cell is occupied if any of its cells is), as the viewer's
    coarser occupancy levels are."""
    if factor == 1:
        return grid
    return F.max_pool3d(grid[None, None].float(), factor, stride=factor, ceil_mode=True)[0, 0] > 0


def pack_bits(fine: torch.Tensor) -> np.ndarray:
    """(2n)^3 bool -> n^3 uint8, bit 2^(c + 2b + 4a) for the sub-cell (a, b, c) along axes (0, 1, 2)."""
    n = fine.shape[0] // 2
    f = fine.reshape(n, 2, n, 2, n, 2).to(torch.int32)
    out = torch.zeros(n, n, n, dtype=torch.int32)
    for a in range(2):
        for b in range(2):
            for c in range(2):
                out += f[:, a, :, b, :, c] << (c + 2 * b + 4 * a)
    return out.to(torch.uint8).numpy()


def plane_texels_in_use(occupied4: torch.Tensor, t: int) -> np.ndarray:
    """(3, T, T) bool: plane texels the viewer can read. It only samples inside occupied factor-4 cells (the
    bit-packed occupancy it tests), so a texel matters if a column of such cells projects onto it, or onto a
    bilinear neighbour. Everything else is baked to byte 0, which gzip squeezes away."""
    masks = []
    for k in range(3):
        m = occupied4.any(dim=k).float()[None, None]
        m = F.interpolate(m, scale_factor=t // occupied4.shape[0], mode="nearest")
        masks.append(F.max_pool2d(m, 3, stride=1, padding=1)[0, 0] > 0)
    return torch.stack(masks).numpy()


def atlas_shape(num_blocks: int) -> tuple[int, int, int]:
    """Blocks per atlas axis (width, height, depth): least volume holding ``num_blocks``, each side <= 227,
    depth the smallest."""
    if num_blocks > MAX_BLOCKS_PER_AXIS ** 3:
        raise BakeError(f"{num_blocks} alive blocks do not fit a {MAX_ATLAS_SIDE}^3 atlas; lower the sparse resolution")
    best = None
    for ax in range(1, MAX_BLOCKS_PER_AXIS + 1):
        for ay in range(1, ax + 1):
            az = -(-num_blocks // (ax * ay))
            if az > ay:
                continue
            vol = ax * ay * az
            if best is None or vol < best[0]:
                best = (vol, (ax, ay, az))
            if az == 1:
                break
    return best[1]


# ---- file writing ------------------------------------------------------------------------------------------------
class AssetWriter:
    """Writes ``raw.gz`` arrays with the viewer's axis order and collects ``asset_metadata``."""

    def __init__(self, folder: Path):
        self.folder, self.meta = folder, []
        folder.mkdir(parents=True)

    def write(self, name: str, image: np.ndarray, slice_idx: int = 0, slice_count: int = 1) -> None:
        image = np.ascontiguousarray(image, dtype=np.uint8)
        (self.folder / name).write_bytes(gzip.compress(image.tobytes(), compresslevel=6, mtime=0))
        self.meta.append({"dtype": "uint8", "shape": list(image.shape), "format": "raw.gz", "filename": name,
                          "slice_idx": slice_idx, "slice_count": slice_count})

    def grid(self, name: str, grid: np.ndarray, sliced: bool, numbered: bool = True) -> None:
        """[u, v, w(, C)] grid -> image rows w * n + v, columns u, in ``name_000.raw.gz`` (8 files along w when
        ``sliced``), or in ``name.raw.gz`` when not ``numbered``."""
        if grid.ndim == 3:
            grid = grid[..., None]
        n = grid.shape[0]
        img = grid.transpose(2, 1, 0, 3).reshape(n * n, n, grid.shape[-1])
        parts = np.split(img, 8) if sliced else [img]
        for i, part in enumerate(parts):
            self.write(f"{name}_{i:03d}.raw.gz" if numbered else f"{name}.raw.gz", part, i, len(parts))

    def plane(self, name: str, plane: np.ndarray) -> None:
        self.write(name, plane.transpose(1, 0, 2))


def quantize_channels(values: torch.Tensor) -> np.ndarray:
    """(..., 8) pre-activation channels -> uint8 with the density range for channel 0, features for the rest."""
    out = np.empty(values.shape, np.uint8)
    out[..., :1] = to_bytes(values[..., :1], RANGE_DENSITY)
    out[..., 1:] = to_bytes(values[..., 1:], RANGE_FEATURES)
    return out


def pack_atlas(sparse: torch.Tensor, blocks: torch.Tensor) -> tuple[np.ndarray, np.ndarray, dict]:
    """(S, S, S, 8) uint8 sparse grid + (nB, nB, nB) alive blocks -> atlas (AW, AH, AD, 8), block indices, sizes."""
    s = sparse.shape[0]
    nb = blocks.shape[0]
    alive = torch.nonzero(blocks).numpy()
    ax, ay, az = atlas_shape(len(alive))
    atlas = np.zeros((ax * ATLAS_BLOCK, ay * ATLAS_BLOCK, az * ATLAS_BLOCK, sparse.shape[-1]), np.uint8)
    index = np.full((nb, nb, nb, 3), 255, np.uint8)
    arr = sparse.numpy() if isinstance(sparse, torch.Tensor) else sparse
    local = np.arange(ATLAS_BLOCK)
    for b, (bu, bv, bw) in enumerate(alive):
        slot = np.unravel_index(b, (ax, ay, az))
        index[bu, bv, bw] = slot
        iu, iv, iw = (np.minimum(c * BLOCK + local, s - 1) for c in (bu, bv, bw))
        atlas[slot[0] * 9:(slot[0] + 1) * 9, slot[1] * 9:(slot[1] + 1) * 9, slot[2] * 9:(slot[2] + 1) * 9] = \
            arr[np.ix_(iu, iv, iw)]
    return atlas, index, {"atlas_width": ax * 9, "atlas_height": ay * 9, "atlas_depth": az * 9,
                          "num_alive_blocks": len(alive)}


# ---- cameras ----------------------------------------------------------------------------------------------------
def viewer_camera(camera, partition, near: float = 0.02, far: float = 100.0):
    """A dataset camera as the viewer's three.js camera: centre and rotation in the viewer frame (partition cube,
    axes (-x, z, y)), projection from the intrinsics (pixel centres at +0.5)."""
    w, h = camera.width, camera.height
    proj = np.array([[2 * camera.fx / w, 0, 1 - 2 * camera.cx / w, 0],
                     [0, 2 * camera.fy / h, 2 * camera.cy / h - 1, 0],
                     [0, 0, (far + near) / (near - far), 2 * far * near / (near - far)],
                     [0, 0, -1, 0]])
    position = VIEWER_FROM_TRAIN @ partition.normalize(camera.origin)
    rotation = VIEWER_FROM_TRAIN @ camera.c2w[:3, :3]
    return ViewerCamera(position, rotation, proj, w, h)


TEST_FRAMES = "test_frames.json"  # in each sm_XXX/ its own test views; beside the folders all of them, in order


def test_frames_json(cameras) -> dict:
    """``test_frames.json`` content: column-major 4x4 matrices (three.js ``fromArray``)."""
    frames = []
    for cam in cameras:
        rot = np.eye(4)
        rot[:3, :3] = cam.rotation
        frames.append({"position": cam.position.tolist(), "rotation": rot.T.reshape(-1).tolist(),
                       "projection": cam.projection.T.reshape(-1).tolist()})
    return {"test_frames": frames}


# ---- one submodel -----------------------------------------------------------------------------------------------
def scene_params(student, params_idx: int, atlas: dict) -> dict:
    """The ``scene_params.json`` of submodel ``params_idx``: resolutions, value ranges, the export flags the
    official viewer reads, the atlas layout and the submodel's place in the partition."""
    part, cfg = student.partition, student.cfg
    t, s = cfg.triplane_resolution, cfg.sparse_resolution
    return {
        "triplane_resolution": t, "sparse_grid_resolution": s, "range_features": list(RANGE_FEATURES),
        "range_density": list(RANGE_DENSITY), "merge_features_combine_op": "coarse_sum",
        "deferred_rendering_mode": "snerg", "submodel_idx": part.params_to_sm[params_idx],
        "export_apply_zdiff_to_slices": False, "export_array_format": "raw.gz",
        "export_slice_occupancy_and_distance_grids": True, "export_pad_occupancy_and_distance_grids": False,
        "export_store_deferred_mlp_separately": True, "export_store_rgb_and_density_separately": True,
        "triplane_voxel_size": 4 / t, "sparse_grid_voxel_size": 4 / s, "submodel_voxel_size": 2 / part.k,
        "submodel_idx_override": None, "submodels_on_host": [part.params_to_sm[params_idx]],
        "submodel_scale": part.submodel_scale, "voxel_size_to_use": min(4 / t, 4 / s), "resolution_to_use": max(t, s),
        "num_submodels": part.k ** 3, "num_local_submodels": part.num_alive, "num_submodel_mlp_kernels": 1,
        "num_submodel_hash_encoding_kernels": part.num_alive, "sm_to_params": list(part.sm_to_params),
        "params_to_sm": part.params_to_sm, "default_exposure": None, "exposure_range": None, "data_block_size": BLOCK,
        "atlas_width": atlas["atlas_width"], "atlas_height": atlas["atlas_height"], "atlas_depth": atlas["atlas_depth"],
        "num_slices": atlas["atlas_depth"], "slice_depth": 1, "activation": "elu", "feature_gating": True,
    }


def write_submodel(folder: Path, student, params_idx: int, alive: torch.Tensor, mlp_json: dict, frames: dict) -> dict:
    """Bake one submodel's grids from its alive voxels into ``folder``; returns its statistics."""
    cfg = student.cfg
    t, s = cfg.triplane_resolution, cfg.sparse_resolution
    if t % 128:
        raise BakeError(f"triplane resolution {t} must be a multiple of 128 (the 128x occupancy grid)")
    if s % BLOCK or (t * BLOCK) % s:
        raise BakeError(f"sparse resolution {s} must be a multiple of {BLOCK} dividing {t * BLOCK}")
    w = AssetWriter(folder)
    # geometry: occupancy pyramid and distance grids (factors relative to the triplane resolution)
    levels = {1: alive}
    for f in (2,) + OCCUPANCY_FACTORS:
        levels[f] = max_pool(levels[f // 2], 2)
    for f in OCCUPANCY_FACTORS:
        n = t // f
        sliced = n > 256
        w.grid(f"occupancy_grid_{f}", pack_bits(levels[f // 2]), sliced)
        w.grid(f"distance_grid_{f}", distance_grid(levels[f].cpu().numpy()), sliced)
    # sparse grid: 8^3 blocks holding an alive voxel
    blocks = max_pool(alive, BLOCK * t // s)
    sparse = student.sparse.detach().cpu().view(-1, s, s, s, 8)[params_idx]
    atlas, index, sizes = pack_atlas(torch.from_numpy(quantize_channels(sparse)), blocks)
    w.grid("sparse_grid_block_indices", index, False, numbered=False)
    for kind, chans in (("rgb", [1, 2, 3]), ("density", [0, 7]), ("features", [4, 5, 6])):
        for k in range(atlas.shape[2]):
            w.write(f"sparse_grid_{kind}_{k:03d}.raw.gz", atlas[:, :, k][..., chans].transpose(1, 0, 2), k, atlas.shape[2])
    planes = quantize_channels(student.planes.detach().cpu().view(-1, 3, t, t, 8)[params_idx])
    planes[~plane_texels_in_use(levels[4], t)] = 0  # dead texels -> the range minimum, as the authors' baker
    for k in range(3):
        w.plane(f"plane_rgb_{k}.raw.gz", planes[k][..., 1:4])
        w.plane(f"plane_density_{k}.raw.gz", planes[k][..., :1])
        w.plane(f"plane_features_{k}.raw.gz", planes[k][..., 4:8])
    params = scene_params(student, params_idx, sizes)
    params["asset_metadata"] = w.meta
    text = json.dumps(params)
    (folder / "scene_params.json").write_text(text)
    (folder / "scene_params.json.gz").write_bytes(gzip.compress(text.encode(), mtime=0))
    (folder / "deferred_mlp.json.gz").write_bytes(gzip.compress(deferred_mlp_text(mlp_json).encode(), mtime=0))
    (folder / TEST_FRAMES).write_text(json.dumps(frames))
    return {"alive_voxels": int(alive.sum()), "alive_blocks": sizes["num_alive_blocks"],
            "atlas": [sizes["atlas_width"], sizes["atlas_height"], sizes["atlas_depth"]]}


def bake_student(student_dir: str | Path, out: str | Path, stride: int = 2, overwrite: bool = False,
                 camera_radius: float = 1.5) -> dict:
    """Bake every alive submodel of a student into ``out/sm_XXX``; returns statistics (also ``out/bake.json``).
    A submodel's alive voxels come from the training cameras within ``camera_radius`` cell widths of its centre
    (:meth:`Partition.baking_cameras`; 0: its own cameras only).

    Under ``torchrun`` the submodels are dealt out over the ranks (submodel p on rank p mod N), all writing into
    one temporary folder beside ``out`` that rank 0 completes and renames once every rank is done."""
    out = Path(out)
    dp = DataParallel()
    if dp.is_main:
        check_output_folder(out, overwrite, "bake")
    t_start = time.time()
    student, cfg, meta = load_student(student_dir)
    student.to(dp.device)
    teacher, tcfg, tmeta, _ = load_teacher(Path(meta["teacher"]))
    ds = load_dataset(meta["data"], downscale=meta.get("downscale", 1.0), normalize=meta.get("normalize", "auto"))
    part = student.partition
    train_cams = [ds.frames[i].camera for i in ds.split("train")]
    origins = np.stack([c.origin for c in train_cams])
    home = part.assign(origins)
    test_cams = [ds.frames[i].camera for i in ds.split("test")]
    test_home = part.assign(np.stack([c.origin for c in test_cams])) if test_cams else np.zeros(0, int)
    test_views = [viewer_camera(c, part) for c in test_cams]
    threshold = cfg.cull_alpha[1]
    bg = teacher_background(ds)
    mlp_json = student.mlp.export()
    out.parent.mkdir(parents=True, exist_ok=True)
    if dp.is_main:  # what a killed bake into the same folder left behind (not a running one's)
        remove_stale_temps(out)
    if dp.world == 1:
        tmp = temp_name(out, keep_suffix=False)
        tmp.mkdir(mode=DIR_MODE)
        os.chmod(tmp, DIR_MODE)
    else:  # one name every rank can find
        tmp = out.parent / f".{out.name}.baking"
        if dp.is_main:
            shutil.rmtree(tmp, ignore_errors=True)
            tmp.mkdir(mode=DIR_MODE)
            os.chmod(tmp, DIR_MODE)
        dp.barrier()
    stats = {"submodels": {}}
    try:
        mine = list(range(dp.rank, part.num_alive, dp.world))
        for p in mine:
            if not any(home == p):
                raise BakeError(f"submodel {p} has no training cameras; the partition and the dataset disagree")
        per_pass = max(1, ALIVE_BUDGET_BYTES // student.cfg.triplane_resolution ** 3)
        for first in range(0, len(mine), per_pass):
            near = {p: part.baking_cameras(origins, p, camera_radius) for p in mine[first:first + per_pass]}
            names = [f"sm_{part.params_to_sm[p]:03d}" for p in near]
            label = names[0] if len(names) == 1 else f"{names[0]}..{names[-1]} ({len(names)} submodels)"
            with progress_bar(f"bake {label}: alive voxels", int(np.any(list(near.values()), axis=0).sum()),
                              unit="view") as adv:
                alive_of = alive_voxels(student, teacher, train_cams, near, threshold, bg, stride, progress=adv)
            for p, name in zip(near, names):
                alive = median_filter_3(alive_of.pop(p))
                if not alive.any():
                    raise BakeError(f"submodel {p}: no voxel passes the alpha/weight threshold {threshold}; the "
                                    "student renders nothing from its cameras (distil longer or check the teacher)")
                frames = test_frames_json([v for v, h in zip(test_views, test_home) if h == p])
                stats["submodels"][name] = write_submodel(tmp / name, student, p, alive, mlp_json, frames)
                console.print(f"{name}: {stats['submodels'][name]}")
        if dp.world > 1:
            (tmp / f".stats.{dp.rank}.json").write_text(json.dumps(stats["submodels"]))
            dp.barrier()
        if dp.is_main:
            for r in range(1, dp.world):
                part_stats = tmp / f".stats.{r}.json"
                stats["submodels"].update(json.loads(part_stats.read_text()))
            for f in tmp.glob(".stats.*.json"):
                f.unlink()
            stats["submodels"] = dict(sorted(stats["submodels"].items()))
            stats.update({"seconds": time.time() - t_start, "student": str(Path(student_dir).resolve()),
                          "num_submodels": part.num_alive, "partition": part.to_json(), "data": meta["data"],
                          "downscale": meta.get("downscale", 1.0),
                          "normalize": meta.get("normalize", "auto"), "threshold": threshold, "ray_stride": stride,
                          "camera_radius": camera_radius,
                          "ranks": dp.world})
            (tmp / "bake.json").write_text(json.dumps(stats, indent=2))
            # every test camera in the dataset's order (each sm_XXX/ holds only its own): the walk across submodels
            # that `nerfbake view --benchmark --walkthrough test` flies
            (tmp / TEST_FRAMES).write_text(json.dumps(test_frames_json(test_views)))
            replace_folder(tmp, out)
        dp.barrier()
    except BaseException:
        if dp.is_main:
            shutil.rmtree(tmp, ignore_errors=True)
        raise
    return json.loads((out / "bake.json").read_text()) if dp.world > 1 else stats
