"""``octree build | optimize | compress | eval | info | render``."""
from __future__ import annotations

from dataclasses import dataclass, replace

from nerfbake.atomic import check_output_file
from nerfbake.commands.spec import (JSON, NORMALIZATIONS, OVERWRITE, PRESETS, TREE_NORMALIZE_HELP, Command,
                                    config_overrides, option)
from nerfbake.commands.teacher import scores_line

STEP_SIZE = "tree units past each leaf exit (1e-4 default)"


@dataclass(kw_only=True)
class OctreeBuild(Command):
    name = "octree build"
    help = "extract a tree from a trained teacher"
    teacher: str = option(help="teacher run folder")
    out: str = option(help="tree .npz to write")
    overwrite: bool = option(False, OVERWRITE)
    preset: str = option("cpu-small", choices=PRESETS)
    overrides: dict = config_overrides("nerfbake.octree.build:BuildConfig", "grid", "weight_thresh", "samples_per_leaf",
                                       "ray_stride", "autoscale", "box_scale", "env_map_height")
    json: bool = option(False, JSON)

    def run(self) -> dict:
        from nerfbake.octree.build import build_octree, build_preset

        self.config = replace(build_preset(self.preset), **self.overrides)
        self.config.depth  # validates --grid before any work
        check_output_file(self.out, self.overwrite)
        return build_octree(self.teacher, self.out, self.config)

    def text(self, s: dict) -> str:
        return (f"wrote {s['tree']}: {s['num_leaves']:,} leaves ({s['kept_voxels']:,} kept voxels at {self.config.grid}^3), "
                f"{s['file_bytes'] / 1e6:.1f} MB in {s['seconds']:.0f} s; covers {s['region']}")


@dataclass(kw_only=True)
class OctreeOptimize(Command):
    name = "octree optimize"
    help = "fine-tune a tree on the training images (analytic gradients, SGD)"
    tree: str = option()
    data: str = option()
    out: str = option()
    overwrite: bool = option(False, OVERWRITE)
    preset: str = option("cpu-small", choices=PRESETS)
    overrides: dict = config_overrides("nerfbake.octree.optimize:OptimizeConfig", "epochs", "lr", "val_every",
                                       "downscale", "normalize", "continue_on_decrease")
    json: bool = option(False, JSON)

    def run(self) -> dict:
        from nerfbake.octree.optimize import optimize_preset, optimize_tree

        cfg = replace(optimize_preset(self.preset), **self.overrides)
        check_output_file(self.out, self.overwrite)
        return optimize_tree(self.tree, self.data, self.out, cfg)

    def text(self, s: dict) -> str:
        return f"wrote {s['tree']}: best validation PSNR {s['best_val_psnr']:.2f} dB at epoch {s['best_epoch']}"


@dataclass(kw_only=True)
class OctreeCompress(Command):
    name = "octree compress"
    help = "quantise SH into codebooks + DEFLATE (web trees), bits chosen by measured loss"
    tree: str = option()
    out: str = option()
    overwrite: bool = option(False, OVERWRITE)
    bits: int = option(16, "codebook size 2^bits (volrend needs 16)")
    retain: int = option(0, "keep the first R SH bases unquantised")
    sigma_thresh: float = option(2.0, "drop leaves with sigma at or below this")
    min_extent: float = option(2.0 ** -9, "do not split codebook cells narrower than this (0 = the authors' "
                               "always-split median cut)")
    data: str | None = option(None, "the scene the tree was built from: bits per SH band and the density threshold are "
                              "then chosen by measured error on its training views (--target-db)")
    target_db: float = option(0.5, "the most PSNR the compressed tree may lose against the uncompressed one (with --data)")
    views: int = option(4, "training views the loss is measured on")
    downscale: float = option(1.0, "image downscale for the measurement (the tree's)")
    normalize: str | None = option(None, TREE_NORMALIZE_HELP, choices=NORMALIZATIONS)
    band_bits: str | None = option(None, "fixed codebook bits per SH band instead, e.g. 16,8,6,4 (the choice without "
                                   "--data; capped by --bits; '16' with --codebook median --min-extent 0 = the authors' "
                                   "quantiser)")
    codebook: str = option("kmeans", "median cut refined by k-means (default) or median cut alone",
                           choices=("kmeans", "median"))
    sh_degree: int | None = option(None, "keep SH bands up to this degree (smaller files; default: all)")
    json: bool = option(False, JSON)

    def run(self) -> dict:
        from nerfbake.octree.compress import compress_tree

        band = {"band_bits": [int(b) for b in self.band_bits.split(",")]} if self.band_bits else {}
        check_output_file(self.out, self.overwrite)
        return compress_tree(self.tree, self.out, bits=self.bits, retain=self.retain, sigma_thresh=self.sigma_thresh,
                             sh_degree=self.sh_degree, min_extent=self.min_extent, data=self.data,
                             target_db=self.target_db, downscale=self.downscale, normalize=self.normalize or "auto",
                             views=self.views, codebook=self.codebook, **band)

    def text(self, s: dict) -> str:
        how = (f"measured loss {s['measured_loss_db']:.2f} dB on {s['measured_on']} (target {self.target_db})"
               if s["allocation"] == "measured" else s["allocation"])
        return (f"wrote {s['tree']}: {s['file_bytes'] / 1e6:.2f} MB ({s['ratio']:.1f}x smaller); bits per basis "
                f"{','.join(map(str, s['band_bits']))}, sigma > {s['sigma_thresh']:g}; {how}")


@dataclass(kw_only=True)
class OctreeEval(Command):
    name = "octree eval"
    help = "test-split PSNR/SSIM/LPIPS and ms/frame"
    tree: str = option()
    data: str = option()
    split: str = option("test")
    max_views: int | None = option(None)
    downscale: float = option(1.0)
    normalize: str = option("auto", TREE_NORMALIZE_HELP, choices=NORMALIZATIONS)
    repeats: int = option(3, "timed passes over the views after a warm-up pass")
    step_size: float | None = option(None, STEP_SIZE)
    no_images: bool = option(False, "score without writing the renders")
    json: bool = option(False, JSON)

    def run(self) -> dict:
        from nerfbake.octree.evaluate import evaluate_tree
        from nerfbake.octree.render import RenderOptions

        return evaluate_tree(self.tree, self.data, self.split, self.max_views, self.downscale, self.repeats,
                             RenderOptions.from_text(self.step_size), write=not self.no_images, normalize=self.normalize)

    def text(self, r: dict) -> str:
        return (f"{r['split']}: {scores_line(r)}  {r['ms_per_frame']:.1f} ms/frame ({r['fps']:.1f} FPS, {r['device']})")


@dataclass(kw_only=True)
class OctreeInfo(Command):
    name = "octree info"
    help = "summarise a tree file (and check it against volrend's loader rules)"
    tree: str = option(positional=True)
    json: bool = option(False, JSON)

    def run(self) -> dict:
        from nerfbake.octree.io import tree_info

        return tree_info(self.tree)

    def text(self, info: dict) -> str:
        return "\n".join(f"{k:22s} {v}" for k, v in info.items())


@dataclass(kw_only=True)
class OctreeRender(Command):
    name = "octree render"
    help = "render camera poses from a transforms-style JSON"
    tree: str = option()
    pose_file: str = option()
    out: str = option()
    overwrite: bool = option(False, OVERWRITE)
    sh_range: str | None = option(None, "SH components lo,hi (half-open) to sum, e.g. 0,1 for the diffuse part")
    slice: str | None = option(None, "slicing box xmin,ymin,zmin,xmax,ymax,zmax in tree coordinates")
    step_size: float | None = option(None, STEP_SIZE)
    depth: bool = option(False, "also write expected depth as NNNN_depth.npy")

    def run(self) -> str:
        from nerfbake.octree.render import RenderOptions, render_pose_file

        opts = RenderOptions.from_text(self.step_size, self.sh_range, self.slice)
        written = render_pose_file(self.tree, self.pose_file, self.out, opts, self.overwrite, self.depth)
        return f"wrote {len(written)} images to {self.out}"


