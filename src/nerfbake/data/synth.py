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
}


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
        return self.fov_deg if self.fov_deg is not None else (75.0 if self.scene == "rooms" else 40.0)


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
    yy, xx = np.mgrid[0:size, 0:size]
    for _ in range(700):
        r = size * 0.012 / rng.uniform(0.08, 1.0)  # more small discs than large ones (radius ~ 1/uniform)
        cx, cy = rng.uniform(0, size, 2)
        mask = (xx - cx) ** 2 + (yy - cy) ** 2 < r * r
        img[mask] = rng.uniform(0.03, 0.97, 3)
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


def _rooms_scene(mi, seed: int) -> tuple[dict, dict]:
    T = mi.ScalarTransform4f
    H = 1.5
    meta = {
        "up": [0, 0, 1],
        "rooms": {"A": {"min": [-2.0, -1.0, 0.0], "max": [0.0, 1.0, H]}, "B": {"min": [0.0, -1.0, 0.0], "max": [2.0, 1.0, H]}},
        "doorway": {"x": 0.0, "y": [-0.3, 0.3], "z": [0.0, 1.0]},
        "objects": {"sphere_A": {"center": [-1.3, 0.4, 0.3], "radius": 0.3}, "sphere_B": {"center": [1.2, -0.4, 0.3], "radius": 0.3}},
    }

    def diffuse(rgb):
        return {"type": "twosided", "bsdf": {"type": "diffuse", "reflectance": {"type": "rgb", "value": rgb}}}

    def rect(center, size, normal_axis, bsdf):
        # A rectangle spanning 'size' (2 dims) centred at 'center' with its normal along normal_axis.
        t = T().translate(center)
        if normal_axis == "x":
            t = t.rotate([0, 1, 0], 90)
        elif normal_axis == "y":
            t = t.rotate([1, 0, 0], 90)
        return {"type": "rectangle", "to_world": t.scale([size[0] / 2, size[1] / 2, 1]), "bsdf": bsdf}

    floor = {"type": "twosided", "bsdf": {"type": "diffuse", "reflectance": {"type": "checkerboard",
             "color0": {"type": "rgb", "value": [0.7, 0.7, 0.65]}, "color1": {"type": "rgb", "value": [0.3, 0.25, 0.2]},
             "to_uv": T().scale([8, 4, 1])}}}
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
        "light_A": {"type": "rectangle", "to_world": T().translate([-1, 0, H - 0.01]).rotate([1, 0, 0], 180).scale([0.6, 0.6, 1]),
                    "emitter": {"type": "area", "radiance": {"type": "rgb", "value": [3.0, 2.85, 2.7]}}},
        "light_B": {"type": "rectangle", "to_world": T().translate([1, 0, H - 0.01]).rotate([1, 0, 0], 180).scale([0.6, 0.6, 1]),
                    "emitter": {"type": "area", "radiance": {"type": "rgb", "value": [2.7, 2.7, 3.2]}}},
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
            poses.append(look_at(*room_view(meta, ("A", "B")[i % 2], rng)))
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
        eye[2] = rng.uniform(0.5, 1.0)
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
    build = {"objects": _objects_scene, "textured": _textured_scene, "rooms": _rooms_scene}[cfg.scene]
    scene_dict, meta = build(mi, cfg.seed)
    fov_x = cfg.fov if cfg.width >= cfg.height else math.degrees(2 * math.atan(math.tan(math.radians(cfg.fov) / 2) * cfg.width / cfg.height))
    scene_dict["sensor"] = {
        "type": "perspective", "fov": fov_x, "fov_axis": "x",
        "film": {"type": "hdrfilm", "width": cfg.width, "height": cfg.height, "rfilter": {"type": "gaussian"},
                 "pixel_format": "rgb" if cfg.scene == "rooms" else "rgba"},
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
            if cfg.scene == "rooms":  # indoors: cameras sit inside the scene, so NeRF's object bounds do not apply
                lo = np.min([r["min"] for r in meta["rooms"].values()], 0) - 0.05
                hi = np.max([r["max"] for r in meta["rooms"].values()], 0) + 0.05
                header.update(near=0.05, far=float(np.linalg.norm(hi - lo)), aabb=[lo.tolist(), hi.tolist()])
            (tmp / f"transforms_{split}.json").write_text(json.dumps({**header, "frames": frames}, indent=1))
        meta.update({"scene": cfg.scene, "config": cfg.__dict__, "mitsuba_variant": variant,
                     "description": SCENES[cfg.scene]})
        (tmp / "scene_meta.json").write_text(json.dumps(meta, indent=1))
    return out
