"""``export``: a nerfbake scene as 3D Gaussian splats for other viewers."""
from __future__ import annotations

from dataclasses import dataclass

from nerfbake.commands.spec import JSON, NORMALIZATIONS, OVERWRITE, Command, option


@dataclass(kw_only=True)
class Export(Command):
    name = "export"
    help = "write a tree or a teacher as 3D Gaussian splats (.ply in the 3DGS layout, or .splat) for splat viewers"
    tree: str | None = option(None, "a PlenOctree .npz: one Gaussian per leaf", group="source")
    teacher: str | None = option(None, "a teacher run folder (a tree is built from it first, --grid)", group="source")
    out: str = option(help="the file to write (and OUT.json beside it: counts and the frame)")
    format: str = option("ply", "ply: the 3DGS reference layout; splat: the compact 32-byte web layout",
                         choices=("ply", "splat"))
    max_splats: int | None = option(None, "keep the N most opaque splats")
    sh_degree: int | None = option(None, "SH degree of the splats' colour, 0..3 (default: the tree's, at most 3)")
    data: str | None = option(None, "the dataset the scene came from: OUT.json then records the transform back to its "
                              "photos' frame (a teacher's own dataset by default)")
    normalize: str = option("auto", "the --normalize the teacher was trained with (with --tree --data)",
                            choices=NORMALIZATIONS)
    grid: int = option(256, "with --teacher: the dense grid side of the tree built first")
    eval_views: int = option(0, "score the splats on this many test views of --data (the torch reference "
                             "rasteriser; PSNR/SSIM/LPIPS go into OUT.json)")
    downscale: float = option(1.0, "image downscale of the --eval-views and --fit-steps images (a teacher's own by "
                              "default)")
    fit_steps: int = option(0, "fit the Gaussians to the teacher's renders of training views (or, with --tree, the "
                            "training photos of --data) for this many steps of one 128x128 crop each")
    fit_views: int = option(20, "training views to fit to (evenly spread)")
    viewer_rules: str = option("web", "the drawing rules the fit and the evaluation follow: web (gsplat.js and the "
                               "other antimatter15/splat descendants: a quarter of the reference's low-pass, a cut at "
                               "2.83 sigma, no alpha cap, 8-bit colours) or reference (the 3DGS CUDA rasteriser)",
                               choices=("web", "reference"))
    overwrite: bool = option(False, OVERWRITE)
    json: bool = option(False, JSON)

    def run(self) -> dict:
        from nerfbake.splats.export import export_splats

        return export_splats(self.out, self.format, self.tree, self.teacher, self.sh_degree, self.max_splats,
                             self.data, self.normalize, self.grid, self.overwrite, self.eval_views, self.downscale,
                             self.fit_steps, self.fit_views, self.viewer_rules)

    def text(self, r: dict) -> str:
        scores = ""
        if "eval" in r:
            e = r["eval"]
            scores = (f"; {e['split']} ({e['num_views']} views): PSNR {e['psnr']:.2f}  SSIM {e['ssim']:.4f}  "
                      f"LPIPS-{e['lpips_net']} {e['lpips_' + e['lpips_net']]:.4f}")
        return (f"wrote {r['file']}: {r['num_splats']:,} splats (SH degree {r['sh_degree']}), "
                f"{r['file_bytes'] / 1e6:.1f} MB{scores}; frame: {r['frame']} (see {r['file']}.json)")
