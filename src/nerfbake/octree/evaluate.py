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
    scores its candidates with it on training views, fine-tuning its epochs on validation views."""

    def __init__(self, tree: Octree, ds, views: int, split: str = "train"):
        self.opts = RenderOptions(background=tuple(ds.background or (1.0, 1.0, 1.0)))
        picked = pick_views(ds.split(split), views)
        self.frames = [ds.frames[i].camera for i in picked]
        self.images = [ds.image(i)[..., :3] for i in picked]
        if not self.frames:
            raise ValueError(f"{ds.root}: the {split!r} split has no views to score trees on")
        self.reference = self.psnr(tree)

    def psnr(self, tree: Octree) -> float:
        return float(np.mean([float(psnr(render_camera(tree, cam, self.opts)["rgb"], img)[0])
                              for cam, img in zip(self.frames, self.images)]))

    def __call__(self, tree: Octree) -> float:
        return self.reference - self.psnr(tree)


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
