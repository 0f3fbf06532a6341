"""Render a baked SMERF scene as the official web viewer does: pick the submodel from the camera position, march
every pixel with the Warp kernel, then run the deferred MLP whose weights are trilinearly interpolated from the
camera position once per frame. Cameras are three.js cameras in the viewer frame (``test_frames.json``)."""
from __future__ import annotations

import json
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from nerfbake.atomic import check_output_folder
from nerfbake.eval.views import render_views_to_folder
from nerfbake.kernels.smerf_march import march_baked, to_warp_scene
from nerfbake.smerf.assets import VIEWER_FROM_TRAIN, AssetError, SceneAssets
from nerfbake.smerf.deferred_mlp import deferred_inputs


@dataclass
class ViewerCamera:
    """A three.js camera: centre, rotation (3x3, camera looks down -z, +y up) and projection (4x4)."""

    position: np.ndarray
    rotation: np.ndarray
    projection: np.ndarray
    width: int
    height: int

    @classmethod
    def perspective(cls, position, rotation, vfov_deg: float, width: int, height: int, near: float = 0.2, far: float = 100.0):
        f = 1.0 / math.tan(math.radians(vfov_deg) / 2)
        proj = np.array([[f * height / width, 0, 0, 0], [0, f, 0, 0],
                         [0, 0, (far + near) / (near - far), 2 * far * near / (near - far)], [0, 0, -1, 0]])
        return cls(np.asarray(position, float), np.asarray(rotation, float), proj, width, height)


def read_test_frames(path: str | Path, width: int, height: int) -> list[ViewerCamera]:
    """``test_frames.json`` (column-major three.js matrices) -> cameras at the given image size."""
    path = Path(path)
    try:
        frames = json.loads(path.read_text())["test_frames"]
    except (OSError, KeyError, json.JSONDecodeError) as exc:
        raise AssetError(f"{path}: not a test_frames.json ({exc})") from None
    return [ViewerCamera(np.asarray(f["position"], float), np.asarray(f["rotation"], float).reshape(4, 4).T[:3, :3],
                         np.asarray(f["projection"], float).reshape(4, 4).T, width, height) for f in frames]


def submodel_for_position(params: dict, position: np.ndarray) -> int:
    """Params index of the submodel whose cell (inf-norm, K^3 grid over [-1, 1]^3 in the training frame) holds
    the camera; dead cells (no parameters) fall back to submodel 0 as the viewer's lookup would fail."""
    if params.get("num_local_submodels", 1) <= 1:
        return 0
    k = int(round(2.0 / params["submodel_voxel_size"]))
    p = VIEWER_FROM_TRAIN @ np.asarray(position, float)
    ijk = np.clip(np.floor((p + 1) / 2 * k), 0, k - 1).astype(int)
    sm = (ijk[0] * k + ijk[1]) * k + ijk[2]
    idx = params["sm_to_params"][sm]
    return idx if idx >= 0 else 0


def submodel_center(params: dict, params_idx: int) -> np.ndarray:
    """Centre of a submodel's cell in the viewer frame."""
    if params.get("num_local_submodels", 1) <= 1:
        return np.zeros(3)
    k = int(round(2.0 / params["submodel_voxel_size"]))
    sm = params["params_to_sm"][params_idx]
    ijk = np.array([sm // (k * k), (sm // k) % k, sm % k], float)
    return VIEWER_FROM_TRAIN @ ((ijk + 0.5) * params["submodel_voxel_size"] - 1.0)


def viewer_rays(cam: ViewerCamera, center: np.ndarray, scale: float) -> tuple[torch.Tensor, torch.Tensor]:
    """Per pixel (rows top to bottom), the ray origin and unnormalised direction to the near plane, both in the
    submodel frame: the viewer's full-screen quad interpolates exactly these."""
    cols = (np.arange(cam.width) + 0.5) / cam.width * 2 - 1
    rows = 1 - (np.arange(cam.height) + 0.5) / cam.height * 2
    ndc = np.stack(np.meshgrid(cols, rows), -1).reshape(-1, 2)
    clip = np.concatenate([ndc, -np.ones((ndc.shape[0], 1)), np.ones((ndc.shape[0], 1))], 1)
    q = clip @ np.linalg.inv(cam.projection).T
    q = q[:, :3] / q[:, 3:]
    dirs = scale * q @ cam.rotation.T
    origin = scale * (cam.position - center)
    return (torch.from_numpy(np.broadcast_to(origin, dirs.shape).astype(np.float32).copy()),
            torch.from_numpy(dirs.astype(np.float32)))


def deferred_mlp_weights(mlp: dict, params: dict, params_idx: int, position: np.ndarray) -> list[tuple[np.ndarray, np.ndarray]]:
    """Kernels and biases of the 3 layers, trilinearly interpolated on the P^3 lattice at the camera position
    (lattice axes in the training frame, arrays indexed [submodel, z, y, x])."""
    k = round(params.get("num_submodels", 1) ** (1 / 3))
    p_viewer = (np.asarray(position, float) - submodel_center(params, params_idx)) * k
    p = VIEWER_FROM_TRAIN @ p_viewer  # training frame, [-1, 1] across the submodel's cell
    out = []
    for layer in range(3):
        kern = mlp[f"ResampleDense_{layer}/kernel"][params_idx]
        bias = mlp[f"ResampleDense_{layer}/bias"][params_idx]
        g = kern.shape[0]
        x = (p + 1) / 2 * g - 0.5
        lo = np.floor(x)
        f = x - lo
        kw = np.zeros(kern.shape[3:])
        bw = np.zeros(bias.shape[3:])
        for corner in range(8):
            off = np.array([(corner >> 2) & 1, (corner >> 1) & 1, corner & 1])
            idx = np.clip(lo + off, 0, g - 1).astype(int)
            w = np.prod(np.where(off == 1, f, 1 - f))
            kw += w * kern[idx[2], idx[1], idx[0]]
            bw += w * bias[idx[2], idx[1], idx[0]]
        out.append((kw, bw))
    return out


def deferred_shade(acc: dict, view_dirs: torch.Tensor, weights, params: dict, background=(0.5, 0.5, 0.5),
                   exposure: float | None = None) -> torch.Tensor:
    """Final colour per pixel from accumulated diffuse colour/features (SNeRG mode: diffuse + MLP output)."""
    if params.get("deferred_rendering_mode", "snerg") != "snerg":
        raise AssetError(f"deferred_rendering_mode {params.get('deferred_rendering_mode')!r} is not supported (snerg only)")
    v = torch.from_numpy((view_dirs.numpy() @ VIEWER_FROM_TRAIN.T).astype(np.float32))
    x = deferred_inputs(acc, v, background, params.get("merge_features_combine_op", "coarse_sum"),
                        params.get("default_exposure") or exposure)
    act = torch.nn.functional.elu if params.get("activation", "elu") == "elu" else torch.relu
    for layer, (kern, bias) in enumerate(weights):
        x = x @ torch.from_numpy(kern[: x.shape[1]].astype(np.float32)) + torch.from_numpy(bias.astype(np.float32))
        x = act(x) if layer < 2 else torch.sigmoid(x)
    return acc["color"] + x


def render_baked(scene: SceneAssets, cam: ViewerCamera, step_mult: int = 1, visibility_delay: float = 0.99,
                 background=(0.5, 0.5, 0.5), device: str = "cpu", params_idx: int | None = None) -> np.ndarray:
    """(H, W, 3) float image in [0, 1] (before the viewer's 8-bit rounding). ``step_mult`` is the viewer's
    ``stepMult``: a whole number that divides the step and multiplies the step budget (0.5 would leave no steps).
    The submodel is the camera's own unless ``params_idx`` names another (what a viewer shows while the camera's
    submodel is still streaming in; how far apart two submodels' pictures of one view are)."""
    if step_mult < 1 or int(step_mult) != step_mult:
        raise ValueError(f"step_mult={step_mult}: the viewer's stepMult is a whole number >= 1 (2 halves the step)")

    si = submodel_for_position(scene.params, cam.position) if params_idx is None else int(params_idx)
    if not 0 <= si < len(scene.params["params_to_sm"]):
        raise ValueError(f"params_idx={si}: {scene.root} has submodels 0..{len(scene.params['params_to_sm']) - 1}")
    sm = scene.submodel(si)
    scale = float(sm.params["submodel_scale"])
    origins, dirs = viewer_rays(cam, submodel_center(sm.params, si), scale)
    key = (si, device)
    if key not in scene.device_scenes:  # upload once per submodel and device, not every frame
        scene.device_scenes[key] = to_warp_scene(sm, device)
    acc = march_baked(scene.device_scenes[key], origins.to(device), dirs.to(device), step_mult, visibility_delay)
    acc = {k: v.cpu() for k, v in acc.items()}
    weights = deferred_mlp_weights(scene.mlp, sm.params, si, cam.position)
    rgb = deferred_shade(acc, dirs, weights, sm.params, background)
    return rgb.clamp(0, 1).reshape(cam.height, cam.width, 3).numpy()


def render_frames_to_folder(assets, out, frames=None, width: int = 800, height: int = 500, step_mult: int = 1,
                            overwrite: bool = False) -> list[Path]:
    """``nerfbake smerf render``: one PNG per camera of a ``test_frames.json`` (default: the first submodel's) in
    ``out``, drawn as the official viewer's shader draws them; ``out`` appears only once every view is written."""
    check_output_folder(out, overwrite, "render")
    scene = SceneAssets.open(assets)
    frames = frames or scene.root / f"sm_{scene.params['params_to_sm'][0]:03d}" / "test_frames.json"
    cams = read_test_frames(frames, width, height)
    return render_views_to_folder(lambda cam: render_baked(scene, cam, step_mult=step_mult), cams, out, overwrite,
                                  desc="smerf render")
