"""Viewer speed against a frozen baseline: the same assets, camera and size in the same headless chromium, drawn by
the viewer files frozen in ``benchmarks/viewer_baseline/static`` (the shaders of commit bf9e9f5, before issue 23)
and by the current viewer; rounds alternate baseline/current so that drift on a busy machine hits both alike.

    python benchmarks/viewer_speed.py --assets DIR_OR_TREE.npz [--size 512,512] [--view 0] [--frames 6]
        [--rounds 2] [--frame-mult 1] [--query "quality=high"] [--gpu] [--phone] [--out outputs/viewer_speed]
    -> one JSON object on stdout: baseline_ms, current_ms, speedup, psnr_current_vs_baseline (dB), and both
       screenshots (PNG) under --out; with --phone, those figures for the phone's resting and moving frame sizes
       under quality=phone in phone emulation, and the GPU bytes of the scene's textures

SMERF asset folders are timed at a ``test_frames.json`` view; octree trees at the viewer's first orbit benchmark
view (2.2 radii from the tree's centre). Times are the mean ms per draw after the warm-up frames, with
``finish()`` after each frame, as ``nerfbake view --benchmark`` measures them.
"""
from __future__ import annotations

import argparse
import json
import statistics
import sys
from pathlib import Path

import numpy as np
from PIL import Image

from nerfbake.viewer.browser import PHONE_EMULATION, ViewerPage
from nerfbake.viewer.server import STATIC

BASELINE = Path(__file__).resolve().parent / "viewer_baseline" / "static"
BASELINE_COMMIT = "bf9e9f5"

# Both viewers expose window.nerfbake.app; this draws view i of the scene's benchmark views off screen.
RENDER_VIEW = """async ([i, w, h]) => {
  const app = window.nerfbake.app;
  const cam = app.benchmarkViews(w, h)[i];
  return app.renderOffscreen(cam, w, h);
}"""


def psnr(a: np.ndarray, b: np.ndarray) -> float:
    mse = float(np.mean((a.astype(np.float64) - b.astype(np.float64)) ** 2))
    return float("inf") if mse == 0 else 10 * np.log10(255.0**2 / mse)


PHONE_MOVING_PIXELS = 300 * 450  # main.js QUALITY.phone: the most pixels drawn while the camera moves


def phone_sizes() -> dict[str, tuple[int, int]]:
    """The two frame sizes quality=phone draws on the emulated phone: the full viewport once the camera rests, and
    the reduced size main.js picks while it moves."""
    w, h = PHONE_EMULATION["viewport"]["width"], PHONE_EMULATION["viewport"]["height"]
    f = max(1.0, (w * h / PHONE_MOVING_PIXELS) ** 0.5)
    return {"resting": (w, h), "moving": (max(1, round(w / f)), max(1, round(h / f)))}


def measure(static: Path, args, size) -> tuple[list[float], np.ndarray, str, int]:
    """Frame times (ms, one per repeat) from one page load, its screenshot, the GL renderer string and the GPU bytes
    of the scene's textures."""
    w, h = size
    device = PHONE_EMULATION if args.phone else None
    page_size = phone_sizes()["resting"] if args.phone else (256, 256)
    with ViewerPage(args.assets, query=args.query, size=page_size, software_gl=not args.gpu, static=static,
                    device=device) as page:
        b64 = page.evaluate(RENDER_VIEW, [args.view, w, h])
        image = page._image(b64, w, h)
        times = []
        for _ in range(args.repeats):
            r = page.benchmark(w, h, args.frame_mult, args.frames, args.warmup, max_views=args.view + 1)
            times.append(r["views"][args.view]["ms_per_frame"])
        if page.errors:
            raise RuntimeError(f"console errors with {static}: {page.errors}")
        return times, image, r["renderer"], page.state().get("gpuBytes")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--assets", required=True, help="a SMERF asset folder or a PlenOctree .npz")
    ap.add_argument("--size", default="512,512", help="W,H of the timed frames")
    ap.add_argument("--view", type=int, default=0, help="which benchmark view")
    ap.add_argument("--frames", type=int, default=6, help="timed frames per measurement")
    ap.add_argument("--warmup", type=int, default=2)
    ap.add_argument("--repeats", type=int, default=1, help="measurements per page load")
    ap.add_argument("--rounds", type=int, default=2, help="page loads per viewer, alternating")
    ap.add_argument("--frame-mult", type=int, default=1)
    ap.add_argument("--query", default="", help="extra viewer URL parameters, e.g. quality=phone")
    ap.add_argument("--gpu", action="store_true", help="the machine's GPU instead of SwiftShader")
    ap.add_argument("--phone", action="store_true",
                    help="phone emulation (390x844, scale 3, touch) with quality=phone: times the resting and the "
                         "moving frame size and reports the textures' GPU bytes (--size is ignored)")
    ap.add_argument("--baseline", default=str(BASELINE), help="the frozen viewer files")
    ap.add_argument("--out", default="outputs/viewer_speed")
    args = ap.parse_args()
    out = Path(args.out)
    if args.phone:
        args.query = "&".join(q for q in ("quality=phone", args.query) if q)
        report = {}
        for name, size in phone_sizes().items():
            report[name] = compare(args, size, out / name)
        print(json.dumps({"assets": str(args.assets), "device": PHONE_EMULATION, "query": args.query, **report}, indent=2))
        return
    size = tuple(int(v) for v in args.size.split(","))
    print(json.dumps({"assets": str(args.assets), "query": args.query, **compare(args, size, out)}, indent=2))


def compare(args, size, out: Path) -> dict:
    """Alternating rounds of baseline and current at one size; their median ms, speed-up and pictures."""
    out.mkdir(parents=True, exist_ok=True)
    runs = {"baseline": [], "current": []}
    images, renderer, gpu_bytes = {}, None, {}
    for r in range(args.rounds):
        for name, static in (("baseline", Path(args.baseline)), ("current", STATIC)):
            times, images[name], renderer, gpu_bytes[name] = measure(static, args, size)
            runs[name] += times
            print(f"round {r + 1}/{args.rounds} {name}: {', '.join(f'{t:.1f}' for t in times)} ms", file=sys.stderr)
    for name, img in images.items():
        Image.fromarray(img).save(out / f"{name}.png")
    base, cur = statistics.median(runs["baseline"]), statistics.median(runs["current"])
    return {
        "width": size[0], "height": size[1], "view": args.view,
        "renderer": renderer, "baseline_commit": BASELINE_COMMIT,
        "baseline_ms": base, "current_ms": cur, "speedup": base / cur,
        "baseline_runs_ms": runs["baseline"], "current_runs_ms": runs["current"],
        "psnr_current_vs_baseline": psnr(images["current"], images["baseline"]),
        "gpu_bytes": gpu_bytes,
        "screenshots": {k: str(out / f"{k}.png") for k in images},
    }


if __name__ == "__main__":
    main()
