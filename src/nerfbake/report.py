"""``nerfbake report RUN``: a Markdown page for a pipeline run in the form of the papers' tables (quality, frame
time, memory, disk per method), with plots a reader would rather look at than read: quality against frame time
and against disk size, the same test view from every method beside the ground truth, and the training curves."""
from __future__ import annotations

from pathlib import Path

import imageio.v3 as iio
import numpy as np

from nerfbake import atomic
from nerfbake.data.formats import load_dataset
from nerfbake.eval.views import to_png
from nerfbake.train.loop import training_curve

MB = 1e6


def save_figure(fig, path: Path) -> None:
    with atomic.atomic_file(path) as tmp:
        fig.savefig(tmp, format=Path(path).suffix.lstrip("."))


def _plt():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def scatter(rows: list[dict], x_key: str, x_label: str, path: Path, scale: float = 1.0) -> None:
    plt = _plt()
    fig, ax = plt.subplots(figsize=(5.5, 3.6), dpi=110)
    for r, marker in zip(rows, "osD^vP*X<>"):
        ax.scatter([r[x_key] * scale], [r["psnr"]], s=45, marker=marker, label=r["method"])
    ax.legend(fontsize=7, loc="best")
    ax.set_xscale("log")
    ax.set_xlabel(x_label)
    ax.set_ylabel("test PSNR (dB)")
    ax.grid(alpha=0.3, which="both")
    fig.tight_layout()
    save_figure(fig, path)
    plt.close(fig)


def strip(rows: list[dict], data: str | None, path: Path) -> str | None:
    """One test view rendered by every method, next to the ground truth; returns the view's name."""
    folders = [Path(r["images"]) for r in rows if r.get("images") and Path(r["images"]).is_dir()]
    if not folders:
        return None
    common = set(p.name for p in folders[0].glob("*.png"))
    for f in folders[1:]:
        common &= set(p.name for p in f.glob("*.png"))
    if not common:
        return None
    name = sorted(common, key=lambda n: (len(n), n))[0]
    panels = [(r["method"], iio.imread(Path(r["images"]) / name)[..., :3]) for r in rows if r.get("images")
              and (Path(r["images"]) / name).is_file()]
    if data:
        ds = load_dataset(data)
        for i in ds.split("test"):
            if Path(ds.frames[i].name).stem == Path(name).stem:
                gt = ds.image(i)
                if gt.shape[-1] == 4:
                    bg = np.asarray(ds.background or (1.0, 1.0, 1.0))
                    gt = gt[..., :3] * gt[..., 3:] + bg * (1 - gt[..., 3:])
                panels.insert(0, ("ground truth", to_png(gt[..., :3])))
                break
    plt = _plt()
    fig, axes = plt.subplots(1, len(panels), figsize=(2.2 * len(panels), 2.5), dpi=110)
    for ax, (title, img) in zip(np.atleast_1d(axes), panels):
        ax.imshow(img)
        ax.set_title(title, fontsize=8)
        ax.axis("off")
    fig.tight_layout()
    save_figure(fig, path)
    plt.close(fig)
    return Path(name).stem


def training_curves(run: Path, path: Path) -> bool:
    curves = []
    for label, log, key in (("teacher (train PSNR)", run / "teacher" / "metrics.jsonl", "psnr"),
                            ("SMERF student (PSNR vs teacher)", run / "smerf" / "student" / "metrics.jsonl", "psnr_vs_teacher")):
        pts = [(p["step"], p[key]) for p in training_curve(log.parent, key)]
        if pts:
            curves.append((label, np.array(pts)))
    if not curves:
        return False
    plt = _plt()
    fig, axes = plt.subplots(1, len(curves), figsize=(5 * len(curves), 3.2), dpi=110)
    for ax, (label, pts) in zip(np.atleast_1d(axes), curves):
        ax.plot(pts[:, 0], pts[:, 1])
        ax.set_title(label, fontsize=9)
        ax.set_xlabel("step")
        ax.set_ylabel("PSNR (dB)")
        ax.grid(alpha=0.3)
    fig.tight_layout()
    save_figure(fig, path)
    plt.close(fig)
    return True


def view_commands(run: Path, results: dict) -> list[str]:
    out = []
    for rel in ("octree/tree_c.npz", "octree/tree_opt.npz", "smerf/assets"):
        if (run / rel).exists():
            out.append(f"nerfbake view {run / rel}")
    return out


def write_report(run: str | Path, results: dict) -> Path:
    """``RUN/report.md`` plus ``RUN/report/*.png`` (and ``results.json``) from a run's collected ``results``
    (``pipeline.collect_results``); returns the Markdown path."""
    run = Path(run)
    atomic.write_json(run / "results.json", results)
    rows = results["methods"]
    fig_dir = run / "report"
    fig_dir.mkdir(exist_ok=True)
    cfg = results.get("config", {})
    lines = [f"# nerfbake report: {run.name}", "",
             f"Data `{cfg.get('data')}`, preset `{cfg.get('preset')}`, K = {cfg.get('k')}, "
             f"{rows[0]['num_views'] if rows else 0} test views, git `{results.get('git')}`.", ""]
    if cfg.get("downscale_why"):
        lines += [f"Images: {cfg['downscale_why']}.", ""]
    skipped = {}
    for name, rec in results.get("stages", {}).items():
        if rec.get("skipped"):
            skipped.setdefault(rec["skipped"], []).append(name)
    for reason, names in skipped.items():
        lines += [f"Skipped ({', '.join(names)}): {reason}.", ""]
    if rows:
        net = rows[0].get("lpips_net", "vgg")
        lines += [f"| method | PSNR ↑ | SSIM ↑ | LPIPS ({net}) ↓ | FPS | ms/frame | memory MB | disk MB |",
                  "|---|---:|---:|---:|---:|---:|---:|---:|"]
        for r in rows:
            lines.append(f"| {r['method']} | {r['psnr']:.2f} | {r['ssim']:.4f} | {r['lpips']:.4f} | "
                         f"{1000 / r['ms_per_frame']:.2f} | {r['ms_per_frame']:.1f} | {r['memory_bytes'] / MB:.1f} | "
                         f"{r['disk_bytes'] / MB:.2f} |")
        lines += ["", "FPS and ms/frame: the Python renderers on this machine at the dataset's resolution (the "
                  "teacher and the student march their fields; the octree and baked SMERF use the Warp kernels). Memory: "
                  "what a renderer holds (teacher weights, float32 octree leaves, the largest SMERF submodel); disk: "
                  "the checkpoint or exported files.", ""]
        scatter(rows, "ms_per_frame", "ms per frame (log)", fig_dir / "quality_vs_time.png")
        scatter(rows, "disk_bytes", "disk MB (log)", fig_dir / "quality_vs_disk.png", 1 / MB)
        lines += ["![quality vs frame time](report/quality_vs_time.png) ![quality vs disk](report/quality_vs_disk.png)", ""]
        view = strip(rows, cfg.get("data"), fig_dir / "strip.png")
        if view:
            lines += [f"Test view `{view}`, ground truth first:", "", "![same view by each method](report/strip.png)", ""]
    if training_curves(run, fig_dir / "training.png"):
        lines += ["Training curves:", "", "![training curves](report/training.png)", ""]
    stages = results.get("stages", {})
    if stages:
        seconds = {k: "skipped" if v.get("skipped") else f"{v['seconds']:.0f}" for k, v in stages.items()}
        lines += ["| stage | seconds |", "|---|---:|"] + [f"| {k} | {v} |" for k, v in seconds.items()] + [""]
    cmds = view_commands(run, results)
    if cmds:
        lines += ["Open the results in a browser:", "", "```bash", *cmds, "```", ""]
    lines += ["All figures: `results.json`."]
    return atomic.write_text(run / "report.md", "\n".join(lines) + "\n")
