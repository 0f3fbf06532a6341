"""Octree compression: file size, ratio and held-out PSNR loss of the default (bits chosen by measured error,
``--target-db``) and of each fixed allocation, all against the uncompressed tree on the same test views.

    python benchmarks/octree_compress.py --tree RUN/octree/tree_opt.npz --data DIR [--eval-views 10]
        [--downscale F] [--normalize M] [--fixed "16;16,8,6,4;16,10,8,6"] [--codebooks kmeans,median]
    -> one JSON object on stdout; the compressed trees go to --out (default outputs/octree_compress/)

Rows: ``default`` (what ``octree compress --data`` writes), each ``--fixed`` band allocation with each codebook,
and ``authors`` (one 16-bit median-cut codebook per basis, always split: the PlenOctrees script).
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

from nerfbake.data.formats import load_dataset
from nerfbake.octree.compress import TARGET_DB, compress_tree
from nerfbake.octree.evaluate import ViewLoss
from nerfbake.octree.io import load_tree, volrend_problems
from nerfbake.train.loop import git_revision


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--tree", required=True, help="the optimised (uncompressed) tree")
    ap.add_argument("--data", required=True, help="the scene it was built from")
    ap.add_argument("--out", default="outputs/octree_compress")
    ap.add_argument("--eval-views", type=int, default=10, help="evenly spaced test views (0: all)")
    ap.add_argument("--downscale", type=float, default=1.0)
    ap.add_argument("--normalize", default="auto")
    ap.add_argument("--target-db", type=float, default=TARGET_DB)
    ap.add_argument("--fixed", default="16;16,8,6,4;16,10,8,6", help="fixed band allocations, ';'-separated")
    ap.add_argument("--codebooks", default="kmeans,median")
    ap.add_argument("--sigma-thresh", type=float, default=2.0)
    args = ap.parse_args()
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    ds = load_dataset(args.data, downscale=args.downscale, normalize=args.normalize)
    held_out = ViewLoss(load_tree(args.tree), ds, args.eval_views, split="test")
    raw_bytes = Path(args.tree).stat().st_size
    rows = [("default", dict(data=args.data, target_db=args.target_db, downscale=args.downscale, normalize=args.normalize))]
    for fixed in filter(None, args.fixed.split(";")):
        for cb in args.codebooks.split(","):
            rows.append((f"{fixed} {cb}", dict(band_bits=tuple(int(b) for b in fixed.split(",")), codebook=cb)))
    rows.append(("authors", dict(band_bits=(16,), codebook="median", min_extent=0.0)))
    results = []
    for name, kw in rows:
        path = out / (name.replace(" ", "_").replace(",", "-") + ".npz")
        start = time.time()
        s = compress_tree(args.tree, path, sigma_thresh=args.sigma_thresh, **kw)
        results.append({
            "name": name, "band_bits": s["band_bits"], "sigma_thresh": s["sigma_thresh"], "codebook": s["codebook"],
            "file_bytes": s["file_bytes"], "ratio": raw_bytes / s["file_bytes"],
            "test_loss_db": held_out(load_tree(path)),
            "train_loss_db": s.get("measured_loss_db"), "seconds": time.time() - start,
            "volrend_ok": volrend_problems(path) == [],
        })
        print(json.dumps(results[-1]), flush=True, file=sys.stderr)
    print(json.dumps({"tree": args.tree, "data": args.data, "raw_bytes": raw_bytes, "test_views": len(held_out.frames),
                      "raw_test_psnr": held_out.reference, "target_db": args.target_db, "git": git_revision(),
                      "results": results}, indent=1))


if __name__ == "__main__":
    main()
