"""How visible are the partition's seams? SMERF renders each camera with one submodel, the one whose cell holds it
(eq. 6), so a camera crossing a cell boundary switches submodels in one frame. The consistency loss (eq. 14) is
there to make that switch invisible. Measured here: a camera near a boundary, rendered by its home submodel and by
the neighbour across the boundary. The partition is seamless there when the two pictures differ by less than the
student's own error to the teacher.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from nerfbake.atomic import write_image
from nerfbake.eval.metrics import psnr
from nerfbake.eval.views import to_png
from nerfbake.smerf.bake import viewer_camera
from nerfbake.smerf.baked_render import render_baked
from nerfbake.smerf.distill import render_student_camera, teacher_background
from nerfbake.smerf.partition import Partition
from nerfbake.teacher.evaluate import render_camera
from nerfbake.teacher.protocol import Teacher


def boundary_cameras(partition: Partition, origins: np.ndarray, count: int) -> list[dict]:
    """The ``count`` cameras nearest the cell of an alive neighbour of their home submodel, one pair each:
    ``{camera, home, neighbour, gap_cell_widths}``; the gap is the inf-norm distance to the neighbour's cell in
    cell widths (0 on the shared face). Cameras outside the partition cube (which no submodel renders) are skipped."""
    cube = partition.normalize(origins)
    homes = partition.assign(origins)
    half = 1.0 / partition.k
    pairs = []
    for i, (p, home) in enumerate(zip(cube, homes.tolist())):
        if np.abs(p).max() > 1.0:
            continue
        gaps = [(float(np.maximum(np.abs(p - partition.cell_centre(partition.params_to_sm[nb])) - half, 0).max()), nb)
                for nb in partition.neighbours(home)]
        if gaps:
            gap, nb = min(gaps)
            pairs.append({"camera": i, "home": home, "neighbour": nb, "gap_cell_widths": gap / (2 * half)})
    return sorted(pairs, key=lambda q: q["gap_cell_widths"])[:count]


def compare_across_boundary(student, teacher: Teacher, ds, split: str, pairs: list[dict], scene=None,
                            image_dir: Path | None = None) -> list[dict]:
    """PSNR between every two of teacher, home submodel, neighbour and ground truth for each of ``pairs`` (indices
    into ``split``), for the student on the teacher's intervals and, given baked ``scene`` assets, for the viewer's
    picture. ``seamless``: home vs neighbour is closer than home vs teacher. Optional PNG rows (teacher | home |
    neighbour [| baked home | baked neighbour]) go to ``image_dir``."""

    def db(a, b) -> float:
        return round(float(psnr(a, b)), 2)

    bg = teacher_background(ds)
    indices = ds.split(split)
    out = []
    for q in pairs:
        index = indices[q["camera"]]
        cam, gt = ds.frames[index].camera, ds.image(index)
        ref = render_camera(teacher, cam, bg)["rgb"]
        home = render_student_camera(student, teacher, cam, bg, params_idx=q["home"])
        nb = render_student_camera(student, teacher, cam, bg, params_idx=q["neighbour"])
        rec = {**q, "name": ds.frames[index].name,
               "student": {"home_vs_neighbour": db(home, nb), "home_vs_teacher": db(home, ref),
                           "neighbour_vs_teacher": db(nb, ref), "home_vs_gt": db(home, gt), "neighbour_vs_gt": db(nb, gt)}}
        rec["seamless"] = rec["student"]["home_vs_neighbour"] > rec["student"]["home_vs_teacher"]
        row = [ref, home, nb]
        if scene is not None:
            vcam = viewer_camera(cam, student.partition)
            b_home, b_nb = (render_baked(scene, vcam, params_idx=q[k]) for k in ("home", "neighbour"))
            rec["baked"] = {"home_vs_neighbour": db(b_home, b_nb), "home_vs_teacher": db(b_home, ref),
                            "neighbour_vs_teacher": db(b_nb, ref)}
            row += [b_home, b_nb]
        if image_dir is not None:
            name = f"boundary_k{student.partition.k}_{Path(rec['name']).name}.png"
            write_image(image_dir / name, to_png(np.concatenate(row, 1)))
        out.append(rec)
    return out
