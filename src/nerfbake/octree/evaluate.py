"""``nerfbake octree eval``: held-out quality and frame time of a tree, timed as the paper does (every test view
rendered repeatedly after a warm-up pass, mean ms per frame at the dataset's resolution)."""
from __future__ import annotations

import time
from dataclasses import replace
from pathlib import Path

import numpy as np
import torch

from nerfbake.data.formats import load_dataset
from nerfbake.eval.metrics import psnr
from nerfbake.eval.views import evaluate_views, pick_views
from nerfbake.octree.io import load_tree
from nerfbake.octree.render import RenderOptions, render_camera
from nerfbake.octree.tree import Octree
from nerfbake.train.loop import default_device, git_revision, write_json_atomic


def _sync(device) -> None:
    if torch.device(device).type == "cuda":
        torch.cuda.synchronize(device)


def time_frames(tree, cameras, opts: RenderOptions, repeats: int = 3) -> float:
    """Mean seconds per frame over ``repeats`` passes through ``cameras`` after one untimed warm-up pass."""
    for cam in cameras:
        render_camera(tree, cam, opts)
    _sync(tree.device)
    start = time.perf_counter()
    for _ in range(repeats):
        for cam in cameras:
            render_camera(tree, cam, opts)
    _sync(tree.device)
    return (time.perf_counter() - start) / (repeats * len(cameras))


class ViewLoss:
    """Mean PSNR of trees on a few evenly spread views of ``split`` (photos loaded once), rendered as ``octree eval``
    renders them; calling it gives a tree's loss in dB against ``reference``, the first tree's PSNR. Compression
    scores its candidates with it on training views, fine-tuning its epochs on validation views.

    With ``quality_floor_db`` (compression), a call also charges the error a tree adds to the first tree's own
    renders as the drop it would cost a tree of that PSNR, and returns the larger loss. Against the photos alone a
    poor tree hides its added error: a 13 dB octree of a real room lost only 0.2 dB with 4 colours for its whole
    diffuse band, and the hues visibly shifted."""

    def __init__(self, tree: Octree, ds, views: int, split: str = "train", quality_floor_db: float | None = None):
        self.opts = RenderOptions(background=tuple(ds.background or (1.0, 1.0, 1.0)))
        picked = pick_views(ds.split(split), views)
        self.frames = [ds.frames[i].camera for i in picked]
        self.images = [ds.image(i)[..., :3] for i in picked]
        if not self.frames:
            raise ValueError(f"{ds.root}: the {split!r} split has no views to score trees on")
        self.quality_floor_db = quality_floor_db
        self.first_renders = self.renders(tree)
        self.reference = self.psnr_of(self.first_renders)

    def renders(self, tree: Octree) -> list:
        return [render_camera(tree, cam, self.opts)["rgb"] for cam in self.frames]

    def psnr_of(self, renders: list) -> float:
        return float(np.mean([float(psnr(r, img)[0]) for r, img in zip(renders, self.images)]))

    def psnr(self, tree: Octree) -> float:
        return self.psnr_of(self.renders(tree))

    def __call__(self, tree: Octree) -> float:
        renders = self.renders(tree)
        drop = self.reference - self.psnr_of(renders)
        if self.quality_floor_db is None:
            return drop
        added = float(np.mean([float(((r - f) ** 2).mean()) for r, f in zip(renders, self.first_renders)]))
        return max(drop, float(10 * np.log10(1 + added / 10 ** (-self.quality_floor_db / 10))))


def evaluate_tree(tree_path: str | Path, data: str | Path, split: str = "test", max_views: int | None = None,
                  downscale: float = 1.0, repeats: int = 3, opts: RenderOptions | None = None, write: bool = True,
                  normalize: str = "auto") -> dict:
    """Quality of a tree on ``split`` (PSNR, SSIM, LPIPS per image and mean) and its mean ms per frame, rendered
    with ``opts`` against the dataset's background; images and ``results_<split>.json`` go beside the tree unless
    ``write`` is False."""
    tree_path = Path(tree_path)
    device = default_device()
    tree = load_tree(tree_path, device)
    ds = load_dataset(data, downscale=downscale, normalize=normalize)
    out_dir = tree_path.parent / f"{tree_path.stem}_eval"

    bg = tuple(ds.background or (1.0, 1.0, 1.0))
    opts = replace(opts or RenderOptions(), background=bg)
    result = evaluate_views(lambda cam, _bg: render_camera(tree, cam, opts)["rgb"], ds, split, max_views,
                            out_dir / split if write else None, desc="octree eval")
    cams = [ds.frames[i].camera for i in pick_views(ds.split(split), max_views)]
    sec = time_frames(tree, cams, opts, repeats)
    result.update({
        "ms_per_frame": 1000.0 * sec, "fps": 1.0 / sec, "resolution": [cams[0].width, cams[0].height],
        "num_leaves": tree.num_leaves, "file_bytes": tree_path.stat().st_size,
        "device": str(device) if str(device) != "cpu" else f"cpu ({torch.get_num_threads()} threads)",
        "tree": str(tree_path), "data": str(data), "git": git_revision(),
        "timing": f"{repeats} passes over the views after one warm-up pass",
    })
    result["per_image"] = [{k: (float(v) if isinstance(v, (float, np.floating)) else v) for k, v in m.items()} for m in result["per_image"]]
    if write:
        write_json_atomic(out_dir / f"results_{split}.json", result)
    return result
