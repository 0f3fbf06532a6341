"""Exported splats scored on held-out views by two independent renderers: gsplat.js (npm, a published web splat
viewer, in headless chromium) reading the written file, and our Warp rasteriser (under the 3DGS reference's
compositing rules, ``warp``, and as a web viewer draws the file, ``warp_web_rules``: 8-bit colours, opacities and
rotations, the web compositing); with the teacher's or the tree's figure on the same views beside them when a run's
results.json is given.

    python benchmarks/splat_export.py --splats F.ply|F.splat --data DATASET [--views 5] [--results RUN/results.json]
        [--images outputs/splat_eval]
    -> one JSON object on stdout: per renderer PSNR / SSIM / LPIPS, the file's size and splat count (from its
       side-car F.json), and each reference method's PSNR and the gap to it

The dataset must be loaded as the splats' source was (``--normalize``, ``--downscale`` as for the export; the
side-car records the normalisation that was used).
"""
from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np

from nerfbake.data.formats import load_dataset
from nerfbake.eval.metrics import psnr
from nerfbake.eval.views import evaluate_views, pick_views
from nerfbake.kernels.splat_raster import REFERENCE, WEB
from nerfbake.splats.io import read_splats, web_quantized
from nerfbake.splats.rasterize import render_gaussians
from nerfbake.splats.web_viewer import render_cameras_with_gsplat


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--splats", required=True)
    ap.add_argument("--data", required=True)
    ap.add_argument("--views", type=int, default=5, help="evenly spaced test views")
    ap.add_argument("--normalize", default="auto")
    ap.add_argument("--downscale", type=float, default=1.0)
    ap.add_argument("--results", help="a pipeline run's results.json: its methods' PSNR on the same views")
    ap.add_argument("--images", help="write both renderers' pictures under this folder")
    args = ap.parse_args()
    ds = load_dataset(args.data, downscale=args.downscale, normalize=args.normalize)
    g = read_splats(args.splats)
    # gsplat.js draws every view in one page load, in the order evaluate_views asks for them (the same pick_views)
    cameras = [ds.frames[i].camera for i in pick_views(ds.split("test"), args.views)]
    start = time.perf_counter()
    background = tuple(ds.background or (1.0, 1.0, 1.0))
    theirs = render_cameras_with_gsplat(args.splats, cameras, background)
    drawn = iter(theirs)
    gsplat_seconds = (time.perf_counter() - start) / max(1, len(cameras))
    held = web_quantized(g)  # what gsplat.js holds once it has loaded the file
    renderers = {
        "gsplat.js": lambda cam, bg: next(drawn),
        "warp": lambda cam, bg: render_gaussians(g, cam, bg, REFERENCE).clamp(0, 1).numpy(),
        "warp_web_rules": lambda cam, bg: render_gaussians(held, cam, bg, WEB).clamp(0, 1).numpy(),
    }
    report = {"splats": args.splats, "data": args.data, "num_splats": len(g),
              "file_bytes": Path(args.splats).stat().st_size}
    side_car = Path(f"{args.splats}.json")
    if side_car.is_file():
        record = json.loads(side_car.read_text())
        report["export"] = {k: record[k] for k in ("source", "sh_degree", "fit", "seconds") if k in record}
    for name, render in renderers.items():
        r = evaluate_views(render, ds, "test", args.views, desc=name,
                           image_dir=Path(args.images) / name if args.images else None)
        report[name] = {k: r[k] for k in ("psnr", "ssim", f"lpips_{r['lpips_net']}", "num_views", "seconds_per_view")}
        report[name]["per_image_psnr"] = [m["psnr"] for m in r["per_image"]]
    for name in ("warp", "warp_web_rules"):  # how close each of ours comes to gsplat.js's picture
        report[name]["psnr_to_gsplat_js"] = float(np.mean([psnr(t, renderers[name](c, background))
                                                           for c, t in zip(cameras, theirs)]))
    report["gsplat.js"]["seconds_per_view"] = gsplat_seconds  # the page load shared out, not the cached lookup
    if args.results:
        for m in json.loads(Path(args.results).read_text())["methods"]:
            report.setdefault("references", {})[m["method"]] = {
                "psnr": m["psnr"], "num_views": m.get("num_views"),
                "gsplat_js_minus_this_db": report["gsplat.js"]["psnr"] - m["psnr"]}
    print(json.dumps(report, indent=2))


if __name__ == "__main__":
    main()
