"""What a tree shows beyond its box: an environment map baked from the teacher.

A PlenOctree covers one box. Photos of an unbounded room or garden show far more: drawn as a constant colour,
the room around bonsai cost the octree route half its PSNR. Seen from near the cameras, what lies beyond the box
changes little with the viewpoint, so one colour per direction (an equirectangular map, ``render/envmap.py``)
stands in for it. Each texel is the teacher's render along its direction from the cameras' mean position,
starting where that ray leaves the box, so nothing inside the box (which the tree holds) is counted twice. A
teacher with a learned directional background (object captures on opaque photos) gives the map directly.
"""
from __future__ import annotations

import numpy as np
import torch

from nerfbake.data.cameras import Camera
from nerfbake.progress import progress_bar
from nerfbake.render.envmap import equirect_directions
from nerfbake.teacher.sampling import ray_box
from nerfbake.teacher.protocol import Teacher


def needs_environment(teacher: Teacher) -> bool:
    """True for teachers that see past their box: unbounded (contracted) scenes and learned backgrounds."""
    return bool(teacher.box.contracted) or teacher.background is not None


@torch.no_grad()
def bake_environment(teacher: Teacher, box_min, box_max, cameras: list[Camera], height: int, background=(1.0, 1.0, 1.0),
                     chunk: int = 1 << 14) -> torch.Tensor:
    """(height, 2 height, 3) colours in [0, 1] beyond the box [box_min, box_max] (world units)."""
    dev = next(teacher.parameters()).device
    dirs = equirect_directions(height, 2 * height).reshape(-1, 3)
    if teacher.background is not None and not teacher.box.contracted:
        return torch.cat([teacher.background(dirs[s: s + chunk].to(dev)).float().cpu()
                          for s in range(0, dirs.shape[0], chunk)]).reshape(height, 2 * height, 3)
    centre = torch.from_numpy(np.mean([c.c2w[:3, 3] for c in cameras], axis=0)).float()
    lo, hi = torch.as_tensor(box_min, dtype=torch.float32), torch.as_tensor(box_max, dtype=torch.float32)
    origins = centre.expand_as(dirs)
    t_near, t_far = ray_box(origins, dirs, lo, hi)
    start = torch.where(t_far >= t_near, t_far.clamp_min(0.0), torch.zeros_like(t_far))
    origins = origins + start[:, None] * dirs
    bg = torch.tensor(background, dtype=torch.float32, device=dev)
    out = torch.empty(dirs.shape[0], 3)
    with progress_bar("environment map", total=dirs.shape[0], unit="ray") as advance:
        for s in range(0, dirs.shape[0], chunk):
            o, d = origins[s: s + chunk].to(dev), dirs[s: s + chunk].to(dev)
            out[s: s + chunk] = teacher.render_rays(o, d, bg)["rgb"].float().clamp(0, 1).cpu()
            advance(o.shape[0])
    return out.reshape(height, 2 * height, 3)
