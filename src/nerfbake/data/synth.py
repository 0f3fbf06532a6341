"""Ground-truth synthetic scenes rendered with Mitsuba 3, written as Blender-format datasets.

Scenes are deterministic by seed and Z-up like the NeRF-synthetic scenes:

* ``objects`` — object-centric, RGBA: a glossy red sphere, a rough-metal sphere and a diffuse cube on a
  pedestal, lit by an environment map with a sun, so highlights move with the viewpoint. Cameras on the
  upper hemisphere looking at the origin.
* ``textured`` — the ``objects`` layout with unique (non-repeating "dead leaves") textures on every object and
  only broad highlights, so every view has distinctive, 3D-consistent features: what structure from motion
  (``nerfbake process``) needs. The plain scene's polar checkerboard repeats every 60°, its spheres are
  featureless or mirror-like.
* ``rooms`` — indoor, opaque: two rooms joined by a doorway, each with its own ceiling light and objects,
  cameras inside both rooms (what SMERF's camera partitioning is for).
* ``house`` — the large indoor scene: two storeys of 6 x 4 units, five rooms off a corridor downstairs and two
  bedrooms upstairs, joined by doors and an open stairwell in the slab, each room with its own light, colours and
  object; cameras in all seven rooms. Cameras on two storeys span the partition cube's height too, so K = 3 gives
  more alive submodels than the 3 x 3 a single floor could.

``scene_meta.json`` beside the transforms records what is where (object centres, radii, room boxes), so
tests can check the geometry of the generated views.
"""
from __future__ import annotations

import json
import math
from dataclasses import dataclass
from pathlib import Path

import imageio.v3 as iio
import numpy as np

from nerfbake.atomic import atomic_folder, check_output_folder

SCENES = {
    "objects": "object-centric RGBA scene: glossy + rough-metal spheres and a cube under an environment light",
    "textured": "the objects scene with non-repeating noise textures (feature-rich, for structure from motion)",
    "rooms": "two connected rooms with cameras inside both (indoor, opaque, for partitioning)",
    "house": "seven rooms on two storeys, doors, a corridor and a stairwell; cameras in every room (large, for K = 3)",
}
INDOOR = ("rooms", "house")  # cameras inside the scene: opaque RGB, a wide lens, no object bounds


@dataclass
class SynthConfig:
    scene: str = "objects"
    width: int = 200
    height: int = 200
    views: int = 60  # training views; val and test get a quarter each (at least 4)
    spp: int = 64
    seed: int = 0
    fov_deg: float | None = None  # across the longer image side; None: 40 for the object scenes, 75 indoors

    @property
    def held_out_views(self) -> int:
        """Views in each of the val and test splits: a quarter of the training views, at least 4."""
        return max(4, self.views // 4)

    @property
    def fov(self) -> float:
        """Indoors a 40-degree camera 1 to 1.5 units from a wall sees little but the wall."""
        return self.fov_deg if self.fov_deg is not None else (75.0 if self.scene in INDOOR else 40.0)


def set_variant() -> str:
    """Pick Mitsuba's LLVM variant (needs libllvm) or fall back to the scalar one."""
    import mitsuba as mi

    for variant in ("llvm_ad_rgb", "scalar_rgb"):
        try:
            mi.set_variant(variant)
            return variant
        except (ImportError, AttributeError, RuntimeError):
            continue
    raise RuntimeError("mitsuba has neither the llvm_ad_rgb nor the scalar_rgb variant; reinstall mitsuba")


def look_at(eye, target, up=(0.0, 0.0, 1.0)) -> np.ndarray:
    """OpenGL c2w for a camera at ``eye`` looking at ``target``."""
    eye, target, up = (np.asarray(v, dtype=np.float64) for v in (eye, target, up))
    back = eye - target
    back /= np.linalg.norm(back)
    right = np.cross(up, back)
    if np.linalg.norm(right) < 1e-8:
        right = np.cross([0.0, 1.0, 0.0], back)
    right /= np.linalg.norm(right)
    cam_up = np.cross(back, right)
    m = np.eye(4)
    m[:3, 0], m[:3, 1], m[:3, 2], m[:3, 3] = right, cam_up, back, eye
    return m


def _sky(seed: int) -> np.ndarray:
    """Equirectangular environment (Mitsuba's Y-up): sky gradient, grey ground, one bright sun."""
    h, w = 64, 128
    theta = (np.arange(h) + 0.5) / h * math.pi  # from +Y (up)
    phi = (np.arange(w) + 0.5) / w * 2 * math.pi
    th, ph = np.meshgrid(theta, phi, indexing="ij")
    up = np.cos(th)
    sky = np.where(up[..., None] > 0, np.array([0.45, 0.6, 0.9]) * (0.6 + 0.4 * up[..., None]) + 0.2,
                   np.array([0.35, 0.32, 0.3]))
    rng = np.random.default_rng(seed)
    sun_th, sun_ph = math.radians(40), rng.uniform(0, 2 * math.pi)
    d = np.stack([np.sin(th) * np.cos(ph), np.cos(th), np.sin(th) * np.sin(ph)], -1)
    s = np.array([math.sin(sun_th) * math.cos(sun_ph), math.cos(sun_th), math.sin(sun_th) * math.sin(sun_ph)])
    sky = sky + 60.0 * (d @ s > math.cos(math.radians(4)))[..., None]
    return sky.astype(np.float32)


def _objects_scene(mi, seed: int) -> tuple[dict, dict]:
    T = mi.ScalarTransform4f
    meta = {
        "up": [0, 0, 1],
        "objects": {
            "glossy_sphere": {"center": [0.0, 0.0, 0.35], "radius": 0.35, "color": "red"},
            "metal_sphere": {"center": [0.55, -0.45, 0.25], "radius": 0.25},
            "cube": {"center": [-0.5, 0.45, 0.2], "half_size": 0.2},
            "pedestal": {"center": [0.0, 0.0, 0.0], "radius": 1.0},
        },
        "camera_target": [0.0, 0.0, 0.25],
    }
    o = meta["objects"]
    scene = {
        "type": "scene",
        "integrator": {"type": "path", "max_depth": 6, "hide_emitters": True},
        "env": {"type": "envmap", "bitmap": mi.Bitmap(_sky(seed)), "scale": 1.0,
                "to_world": T().rotate([1, 0, 0], 90)},
        "glossy_sphere": {"type": "sphere", "center": o["glossy_sphere"]["center"], "radius": o["glossy_sphere"]["radius"],
                          "bsdf": {"type": "roughplastic", "alpha": 0.05,
                                   "diffuse_reflectance": {"type": "rgb", "value": [0.75, 0.08, 0.06]}}},
        "metal_sphere": {"type": "sphere", "center": o["metal_sphere"]["center"], "radius": o["metal_sphere"]["radius"],
                         "bsdf": {"type": "roughconductor", "material": "Al", "alpha": 0.2}},
        "cube": {"type": "cube", "to_world": T().translate(o["cube"]["center"]).rotate([0, 0, 1], 30).scale(0.2),
                 "bsdf": {"type": "diffuse", "reflectance": {"type": "checkerboard",
                          "color0": {"type": "rgb", "value": [0.9, 0.8, 0.2]},
                          "color1": {"type": "rgb", "value": [0.1, 0.3, 0.7]},
                          "to_uv": mi.ScalarTransform4f().scale([4, 4, 1])}}},
        "pedestal": {"type": "disk", "to_world": T().scale([1.0, 1.0, 1.0]),
                     "bsdf": {"type": "twosided", "bsdf": {"type": "diffuse", "reflectance": {"type": "checkerboard",
                              "color0": {"type": "rgb", "value": [0.8, 0.8, 0.8]},
                              "color1": {"type": "rgb", "value": [0.25, 0.25, 0.25]},
                              "to_uv": mi.ScalarTransform4f().scale([6, 6, 1])}}}},
    }
    return scene, meta


def _noise_texture(seed: int, size: int = 512) -> np.ndarray:
    """A "dead leaves" texture: overlapping random discs of many sizes and colours. High contrast, corners at
    every scale and no repetition, so every patch is distinctive."""
    rng = np.random.default_rng(seed)
    img = np.full((size, size, 3), 0.5, np.float32)
    for _ in range(700):
        r = size * 0.012 / rng.uniform(0.08, 1.0)  # more small discs than large ones (radius ~ 1/uniform)
        cx, cy = rng.uniform(0, size, 2)
        x0, x1 = max(0, int(cx - r)), min(size, int(cx + r) + 2)  # the disc's bounding square
        y0, y1 = max(0, int(cy - r)), min(size, int(cy + r) + 2)
        yy, xx = np.mgrid[y0:y1, x0:x1]
        mask = (xx - cx) ** 2 + (yy - cy) ** 2 < r * r
        img[y0:y1, x0:x1][mask] = rng.uniform(0.03, 0.97, 3)
    return img


FLOOR_RADIUS = 2.5


def _textured_scene(mi, seed: int) -> tuple[dict, dict]:
    scene, meta = _objects_scene(mi, seed)

    def tex(k):
        return {"type": "bitmap", "bitmap": mi.Bitmap(_noise_texture(seed * 7 + k)), "filter_type": "bilinear"}

    # A wide textured floor: features across the whole frame pin down rotations (a small object alone leaves a
    # rotation/translation ambiguity of about a degree).
    scene["pedestal"]["bsdf"]["bsdf"]["reflectance"] = tex(1)
    scene["pedestal"]["to_world"] = mi.ScalarTransform4f().scale([FLOOR_RADIUS, FLOOR_RADIUS, 1.0])
    meta["objects"]["pedestal"]["radius"] = FLOOR_RADIUS
    scene["cube"]["bsdf"]["reflectance"] = tex(2)
    # Broad highlights only: sharp reflections of the textured pedestal would be features that move with the view.
    scene["glossy_sphere"]["bsdf"].update(alpha=0.3, diffuse_reflectance=tex(3))
    scene["metal_sphere"]["bsdf"] = {"type": "roughplastic", "alpha": 0.3, "diffuse_reflectance": tex(4)}
    return scene, meta


def _diffuse(rgb) -> dict:
    return {"type": "twosided", "bsdf": {"type": "diffuse", "reflectance": {"type": "rgb", "value": rgb}}}


def _rect(mi, center, size, normal_axis, bsdf) -> dict:
    """A rectangle spanning ``size`` (its two in-plane sides: (y, z) for a normal along x, (x, z) along y, (x, y)
    along z) centred at ``center``."""
    t = mi.ScalarTransform4f().translate(center)
    if normal_axis == "x":
        t = t.rotate([0, 1, 0], 90)
    elif normal_axis == "y":
        t = t.rotate([1, 0, 0], 90)
    return {"type": "rectangle", "to_world": t.scale([size[0] / 2, size[1] / 2, 1]), "bsdf": bsdf}


def _checker(mi, rgb0, rgb1, repeats) -> dict:
    return {"type": "twosided", "bsdf": {"type": "diffuse", "reflectance": {
        "type": "checkerboard", "color0": {"type": "rgb", "value": rgb0}, "color1": {"type": "rgb", "value": rgb1},
        "to_uv": mi.ScalarTransform4f().scale([repeats[0], repeats[1], 1])}}}


def _ceiling_light(mi, x, y, z, half, radiance) -> dict:
    return {"type": "rectangle", "to_world": mi.ScalarTransform4f().translate([x, y, z - 0.01]).rotate([1, 0, 0], 180)
            .scale([half, half, 1]), "emitter": {"type": "area", "radiance": {"type": "rgb", "value": radiance}}}


def _wall(mi, axis: str, coord: float, span, heights, doors, rgb) -> dict[str, dict]:
    """A wall in the plane ``axis = coord`` over ``span`` (along y for an x wall, x for a y wall) between
    ``heights`` (z0, z1), cut by ``doors`` ((centre, width) along the span, 1 unit high from z0): the pieces
    between the doors and a lintel over each."""
    (a, b), (z0, z1), bsdf = span, heights, _diffuse(rgb)
    cuts = [a] + [v for c, w in sorted(doors) for v in (c - w / 2, c + w / 2)] + [b]
    pieces = {}

    def piece(lo, hi, zlo, zhi, name):
        mid = [(lo + hi) / 2, (zlo + zhi) / 2]
        center = [coord, mid[0], mid[1]] if axis == "x" else [mid[0], coord, mid[1]]
        size = [zhi - zlo, hi - lo] if axis == "x" else [hi - lo, zhi - zlo]
        pieces[name] = _rect(mi, center, size, axis, bsdf)

    for i in range(0, len(cuts), 2):
        if cuts[i + 1] - cuts[i] > 1e-6:
            piece(cuts[i], cuts[i + 1], z0, z1, f"piece{i // 2}")
    for j, (c, w) in enumerate(doors):
        piece(c - w / 2, c + w / 2, z0 + 1.0, z1, f"lintel{j}")
    return pieces


def _house_scene(mi, seed: int) -> tuple[dict, dict]:
    H = 1.5  # storey height; the slab between the storeys is at z = H
    rooms = {  # the walk of the held-out cameras goes through them in this order
        "hall": ([-3.0, -0.5, 0.0], [3.0, 0.5, H]), "kitchen": ([-3.0, 0.5, 0.0], [0.0, 2.0, H]),
        "living": ([0.0, 0.5, 0.0], [3.0, 2.0, H]), "bath": ([0.0, -2.0, 0.0], [3.0, -0.5, H]),
        "study": ([-3.0, -2.0, 0.0], [0.0, -0.5, H]), "bed_west": ([-3.0, -2.0, H], [0.0, 2.0, 2 * H]),
        "bed_east": ([0.0, -2.0, H], [3.0, 2.0, 2 * H])}
    objects = {  # name: (kind, centre, size, bsdf)
        "hall_cube": ("cube", [-2.2, 0.0, 0.15], 0.15, _diffuse([0.2, 0.3, 0.7])),
        "kitchen_sphere": ("sphere", [-2.2, 1.5, 0.3], 0.3, {"type": "roughplastic", "alpha": 0.1, "diffuse_reflectance":
                                                             {"type": "rgb", "value": [0.8, 0.6, 0.1]}}),
        "living_cube": ("cube", [2.2, 1.4, 0.25], 0.25, _diffuse([0.6, 0.15, 0.2])),
        "bath_sphere": ("sphere", [2.3, -1.5, 0.3], 0.3, {"type": "roughconductor", "material": "Al", "alpha": 0.2}),
        "study_cube": ("cube", [-1.0, -1.5, 0.3], 0.3, _diffuse([0.15, 0.5, 0.3])),
        "bed_west_cube": ("cube", [-2.3, 1.2, H + 0.2], 0.2, _diffuse([0.7, 0.7, 0.2])),
        "bed_east_sphere": ("sphere", [1.2, -1.3, H + 0.35], 0.35, {"type": "roughplastic", "alpha": 0.05,
                                                                    "diffuse_reflectance": {"type": "rgb", "value": [0.1, 0.2, 0.6]}}),
    }
    hole = ([2.0, -0.5], [3.0, 0.5])  # the stairwell: an open square in the slab over the hall's east end
    meta = {"up": [0, 0, 1], "rooms": {n: {"min": lo, "max": hi} for n, (lo, hi) in rooms.items()},
            "stairwell": {"min": hole[0], "max": hole[1], "z": H},
            "objects": {n: {"center": c, "radius": r * (math.sqrt(3) if k == "cube" else 1.0)}
                        for n, (k, c, r, _) in objects.items()}}
    scene = {"type": "scene", "integrator": {"type": "path", "max_depth": 5},
             "floor": _rect(mi, [0, 0, 0], [6, 4], "z", _checker(mi, [0.7, 0.7, 0.65], [0.3, 0.25, 0.2], (12, 8))),
             "roof": _rect(mi, [0, 0, 2 * H], [6, 4], "z", _diffuse([0.85, 0.85, 0.8]))}
    # The slab: a ceiling below and a floor above, each four rectangles around the stairwell.
    (hx0, hy0), (hx1, hy1) = hole
    for side, (x0, x1, y0, y1) in {"w": (-3, hx0, -2, 2), "e": (hx1, 3, -2, 2), "s": (hx0, hx1, -2, hy0),
                                   "n": (hx0, hx1, hy1, 2)}.items():
        if x1 - x0 > 1e-6 and y1 - y0 > 1e-6:
            centre, size = [(x0 + x1) / 2, (y0 + y1) / 2], [x1 - x0, y1 - y0]
            scene[f"ceiling_{side}"] = _rect(mi, [*centre, H - 0.002], size, "z", _diffuse([0.8, 0.8, 0.78]))
            scene[f"upper_floor_{side}"] = _rect(mi, [*centre, H + 0.002], size, "z",
                                                 _checker(mi, [0.55, 0.35, 0.2], [0.4, 0.25, 0.15], (size[0] * 3, size[1] * 3)))
    walls = [  # axis, coordinate, span, heights, doors, colour
        ("x", -3.0, (-2, 2), (0, H), [], [0.3, 0.45, 0.75]), ("x", 3.0, (-2, 2), (0, H), [], [0.8, 0.55, 0.3]),
        ("y", -2.0, (-3, 3), (0, H), [], [0.55, 0.7, 0.85]), ("y", 2.0, (-3, 3), (0, H), [], [0.35, 0.6, 0.45]),
        ("y", 0.5, (-3, 3), (0, H), [(-1.5, 0.6), (1.5, 0.6)], [0.85, 0.75, 0.5]),
        ("y", -0.5, (-3, 3), (0, H), [(-1.5, 0.6), (1.5, 0.6)], [0.75, 0.4, 0.45]),
        ("x", 0.0, (0.5, 2), (0, H), [(1.25, 0.5)], [0.85, 0.85, 0.8]), ("x", 0.0, (-2, -0.5), (0, H), [], [0.6, 0.5, 0.7]),
        ("x", -3.0, (-2, 2), (H, 2 * H), [], [0.7, 0.75, 0.5]), ("x", 3.0, (-2, 2), (H, 2 * H), [], [0.45, 0.3, 0.6]),
        ("y", -2.0, (-3, 3), (H, 2 * H), [], [0.9, 0.6, 0.55]), ("y", 2.0, (-3, 3), (H, 2 * H), [], [0.4, 0.65, 0.7]),
        ("x", 0.0, (-2, 2), (H, 2 * H), [(0.0, 0.6)], [0.8, 0.8, 0.6])]
    for i, (axis, coord, span, heights, doors, rgb) in enumerate(walls):
        for name, shape in _wall(mi, axis, coord, span, heights, doors, rgb).items():
            scene[f"wall{i}_{name}"] = shape
    tints = [[3.0, 2.85, 2.7], [2.7, 2.7, 3.2], [3.1, 2.9, 2.5]]
    for i, (name, (lo, hi)) in enumerate(rooms.items()):
        x, y = (lo[0] + hi[0]) / 2, (lo[1] + hi[1]) / 2
        if name == "hall":
            x = -0.5  # not over the stairwell
        scene[f"light_{name}"] = _ceiling_light(mi, x, y, hi[2], 0.3 if name == "hall" else 0.45, tints[i % 3])
    for name, (kind, centre, size, bsdf) in objects.items():
        scene[name] = ({"type": "sphere", "center": centre, "radius": size, "bsdf": bsdf} if kind == "sphere" else
                       {"type": "cube", "to_world": mi.ScalarTransform4f().translate(centre).rotate([0, 0, 1], 25)
                        .scale(size), "bsdf": bsdf})
    return scene, meta


def _rooms_scene(mi, seed: int) -> tuple[dict, dict]:
    T = mi.ScalarTransform4f
    H = 1.5
    meta = {
        "up": [0, 0, 1],
        "rooms": {"A": {"min": [-2.0, -1.0, 0.0], "max": [0.0, 1.0, H]}, "B": {"min": [0.0, -1.0, 0.0], "max": [2.0, 1.0, H]}},
        "doorway": {"x": 0.0, "y": [-0.3, 0.3], "z": [0.0, 1.0]},
        "objects": {"sphere_A": {"center": [-1.3, 0.4, 0.3], "radius": 0.3}, "sphere_B": {"center": [1.2, -0.4, 0.3], "radius": 0.3}},
    }

    def rect(center, size, normal_axis, bsdf):
        return _rect(mi, center, size, normal_axis, bsdf)

    diffuse = _diffuse
    floor = _checker(mi, [0.7, 0.7, 0.65], [0.3, 0.25, 0.2], (8, 4))
    scene = {
        "type": "scene",
        "integrator": {"type": "path", "max_depth": 5},
        "floor": rect([0, 0, 0], [4, 2], "z", floor),
        "ceiling": rect([0, 0, H], [4, 2], "z", diffuse([0.8, 0.8, 0.8])),
        "wall_west": rect([-2, 0, H / 2], [H, 2], "x", diffuse([0.3, 0.45, 0.75])),
        "wall_east": rect([2, 0, H / 2], [H, 2], "x", diffuse([0.8, 0.55, 0.3])),
        "wall_south_A": rect([-1, -1, H / 2], [2, H], "y", diffuse([0.55, 0.7, 0.85])),
        "wall_north_A": rect([-1, 1, H / 2], [2, H], "y", diffuse([0.35, 0.6, 0.45])),
        "wall_south_B": rect([1, -1, H / 2], [2, H], "y", diffuse([0.85, 0.75, 0.5])),
        "wall_north_B": rect([1, 1, H / 2], [2, H], "y", diffuse([0.75, 0.4, 0.45])),
        # Shared wall at x = 0 with a doorway y in [-0.3, 0.3], z in [0, 1].
        "divider_left": rect([0, -0.65, H / 2], [H, 0.7], "x", diffuse([0.85, 0.85, 0.8])),
        "divider_right": rect([0, 0.65, H / 2], [H, 0.7], "x", diffuse([0.85, 0.85, 0.8])),
        "divider_top": rect([0, 0, 1.25], [0.5, 0.6], "x", diffuse([0.85, 0.85, 0.8])),
        "light_A": _ceiling_light(mi, -1, 0, H, 0.6, [3.0, 2.85, 2.7]),
        "light_B": _ceiling_light(mi, 1, 0, H, 0.6, [2.7, 2.7, 3.2]),
        "sphere_A": {"type": "sphere", "center": meta["objects"]["sphere_A"]["center"], "radius": 0.3,
                     "bsdf": {"type": "roughplastic", "alpha": 0.08, "diffuse_reflectance": {"type": "rgb", "value": [0.1, 0.5, 0.15]}}},
        "sphere_B": {"type": "sphere", "center": meta["objects"]["sphere_B"]["center"], "radius": 0.3,
                     "bsdf": {"type": "roughconductor", "material": "Cu", "alpha": 0.15}},
        "box_B": {"type": "cube", "to_world": T().translate([1.4, 0.55, 0.2]).rotate([0, 0, 1], 20).scale(0.2),
                  "bsdf": diffuse([0.6, 0.2, 0.6])},
    }
    return scene, meta


def camera_poses(cfg: SynthConfig, meta: dict, count: int, rng: np.random.Generator, kind: str) -> list[np.ndarray]:
    """Poses for one split; train views are random, val/test follow an orbit or a walk through both rooms."""
    poses = []
    for i in range(count):
        if cfg.scene in ("objects", "textured"):
            if kind == "train":
                az, el = rng.uniform(0, 2 * math.pi), rng.uniform(math.radians(10), math.radians(70))
            else:
                az, el = 2 * math.pi * (i + 0.5) / count, math.radians(30 + 15 * math.sin(3 * i))
            r = 4.0
            eye = [r * math.cos(el) * math.cos(az), r * math.cos(el) * math.sin(az), r * math.sin(el)]
            poses.append(look_at(eye, meta["camera_target"]))
        else:
            rooms = list(meta["rooms"])  # a walk through the rooms in their order, room after room
            poses.append(look_at(*room_view(meta, rooms[i % len(rooms)], rng)))
    return poses


def room_view(meta: dict, room: str, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """(eye, target) of one view inside ``room``: the eye at least 0.45 from the walls and 0.2 clear of every
    object's surface, looking within ~57 degrees of the room's centre, a little downwards. (A camera inside a
    sphere sees black; one facing a plain wall from close by sees one flat colour, which says nothing of depth.)"""
    box = meta["rooms"][room]
    lo, hi = np.array(box["min"]) + 0.45, np.array(box["max"]) - 0.45
    centre = (np.array(box["min"]) + np.array(box["max"])) / 2
    while True:
        eye = rng.uniform(lo, hi)
        eye[2] = box["min"][2] + rng.uniform(0.5, 1.0)  # eye height above the room's floor
        if all(np.linalg.norm(eye - np.array(o["center"])) > o["radius"] + 0.2 for o in meta["objects"].values()):
            break
    yaw = math.atan2(centre[1] - eye[1], centre[0] - eye[0]) + rng.uniform(-1.0, 1.0)
    return eye, eye + np.array([math.cos(yaw), math.sin(yaw), rng.uniform(-0.35, 0.1)])


def _to_srgb8(linear: np.ndarray) -> np.ndarray:
    x = np.clip(linear, 0.0, 1.0)
    srgb = np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.power(x, 1 / 2.4) - 0.055)
    return np.round(srgb * 255).astype(np.uint8)


def render_dataset(cfg: SynthConfig, out: Path, progress=None, overwrite: bool = False) -> Path:
    """Render ``cfg.scene`` into a Blender-format dataset at ``out`` (written to a temporary folder, then swapped
    in); a non-empty ``out`` is refused unless ``overwrite``."""
    import mitsuba as mi

    if cfg.scene not in SCENES:
        raise ValueError(f"unknown synthetic scene {cfg.scene!r}; choose from {', '.join(SCENES)} (nerfbake synth --list)")
    if min(cfg.width, cfg.height, cfg.views, cfg.spp) <= 0:
        raise ValueError("width, height, views and spp must be positive")
    variant = set_variant()
    build = {"objects": _objects_scene, "textured": _textured_scene, "rooms": _rooms_scene, "house": _house_scene}[cfg.scene]
    scene_dict, meta = build(mi, cfg.seed)
    fov_x = cfg.fov if cfg.width >= cfg.height else math.degrees(2 * math.atan(math.tan(math.radians(cfg.fov) / 2) * cfg.width / cfg.height))
    scene_dict["sensor"] = {
        "type": "perspective", "fov": fov_x, "fov_axis": "x",
        "film": {"type": "hdrfilm", "width": cfg.width, "height": cfg.height, "rfilter": {"type": "gaussian"},
                 "pixel_format": "rgb" if cfg.scene in INDOOR else "rgba"},
        "sampler": {"type": "independent", "sample_count": cfg.spp},
    }
    scene = mi.load_dict(scene_dict)
    sensor = scene.sensors()[0]
    params = mi.traverse(sensor)
    rng = np.random.default_rng(cfg.seed)
    held = cfg.held_out_views
    splits = {"train": cfg.views, "val": held, "test": held}
    out = Path(out)
    check_output_folder(out, overwrite, "dataset")
    total = sum(splits.values())
    done = 0
    flip = np.diag([-1.0, 1.0, -1.0, 1.0])  # OpenGL camera axes -> Mitsuba's (looks down +Z, +X left)
    with atomic_folder(out, overwrite, "dataset") as tmp:
        for split, count in splits.items():
            (tmp / split).mkdir()
            frames = []
            for i, c2w in enumerate(camera_poses(cfg, meta, count, rng, split)):
                params["to_world"] = mi.ScalarTransform4f(mi.ScalarMatrix4f((c2w @ flip).tolist()))
                params.update()
                img = np.array(mi.render(scene, sensor=sensor, spp=cfg.spp, seed=cfg.seed * 100003 + done))
                if img.shape[-1] == 4:
                    alpha = np.clip(img[..., 3:], 0, 1)
                    rgb = np.where(alpha > 1e-4, img[..., :3] / np.maximum(alpha, 1e-4), 0.0)  # straight alpha
                    png = np.concatenate([_to_srgb8(rgb), np.round(alpha * 255).astype(np.uint8)], -1)
                else:
                    png = _to_srgb8(img[..., :3])
                iio.imwrite(tmp / split / f"r_{i}.png", png)
                frames.append({"file_path": f"./{split}/r_{i}", "transform_matrix": c2w.tolist()})
                done += 1
                if progress is not None:
                    progress(done, total)
            header = {"camera_angle_x": math.radians(fov_x)}
            if cfg.scene in INDOOR:  # indoors: cameras sit inside the scene, so NeRF's object bounds do not apply
                lo = np.min([r["min"] for r in meta["rooms"].values()], 0) - 0.05
                hi = np.max([r["max"] for r in meta["rooms"].values()], 0) + 0.05
                header.update(near=0.05, far=float(np.linalg.norm(hi - lo)), aabb=[lo.tolist(), hi.tolist()])
            (tmp / f"transforms_{split}.json").write_text(json.dumps({**header, "frames": frames}, indent=1))
        meta.update({"scene": cfg.scene, "config": cfg.__dict__, "mitsuba_variant": variant,
                     "description": SCENES[cfg.scene]})
        (tmp / "scene_meta.json").write_text(json.dumps(meta, indent=1))
    return out
