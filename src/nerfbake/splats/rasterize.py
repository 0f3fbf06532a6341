"""The 3DGS rasteriser: :func:`rasterize` (the projection in torch, the per-pixel compositing by the Warp kernels of
``kernels/splat_raster.py``), which scores exported splats and fits them, and :func:`rasterize_reference`, the
same in plain torch, which the kernels are checked against; both differentiable through autograd.

Per Gaussian: the mean into the camera (OpenGL axes: the camera looks down -Z, image rows go down), the 3D
covariance R S S^T R^T projected with the perspective Jacobian (EWA splatting) plus 0.3 px^2 on the diagonal (the
reference's low-pass; the web viewers' is a quarter of it), the colour ``max(SH(d) . k + 0.5, 0)`` for the direction
from the camera to the mean. Per pixel: ``alpha = min(0.99, opacity * exp(-0.5 d^T Sigma^-1 d))`` (pixel centres at
+0.5), alphas under 1/255 skipped, front-to-back compositing by the means' depth, stopping before the Gaussian that
would take the transmittance under 1e-4 (as the reference code does), the background behind. Those are the
:data:`REFERENCE` rules; every function here also draws under the web viewers' (:data:`WEB`: see
``kernels/splat_raster.py``). Pixels are processed in 16 x 16 tiles, each against the Gaussians whose 3-sigma box
touches it.
"""
from __future__ import annotations

import torch

from nerfbake.data.cameras import Camera
from nerfbake.kernels.splat_raster import REFERENCE, TILE, SplatRules, composite
from nerfbake.render.rotations import quaternion_matrix
from nerfbake.render.sh import sh_basis
from nerfbake.splats.gaussians import FIELDS

NEAR = 0.01


def project(means, log_scales, quats, camera: Camera, low_pass: float = REFERENCE.low_pass):
    """Screen-space splats: centres (N, 2) in pixels, inverse 2D covariances (N, 2, 2) (``low_pass`` px^2 added to
    the covariance's diagonal), depths (N,), 3-sigma radii (N,) in pixels; ``visible`` (N,) bool for the ones in
    front of the near plane."""
    c2w = torch.as_tensor(camera.c2w, dtype=means.dtype, device=means.device)
    rot, origin = c2w[:3, :3], c2w[:3, 3]
    p = (means - origin) @ rot  # camera coordinates (x right, y up, -z forward)
    depth = -p[:, 2]
    visible = depth > NEAR
    d = depth.clamp_min(NEAR)
    u = camera.cx + camera.fx * p[:, 0] / d
    v = camera.cy - camera.fy * p[:, 1] / d
    s = torch.exp(log_scales)
    m = quaternion_matrix(quats) * s[:, None, :]  # R S
    cov_world = m @ m.transpose(1, 2)
    cov_cam = rot.T @ cov_world @ rot
    # The Jacobian is taken where the mean's direction is clamped to 1.3x the field of view, as the reference code
    # does: a Gaussian far off to the side (near the camera plane) would otherwise blow up to cover the image.
    lim_x, lim_y = 1.3 * camera.width / (2 * camera.fx), 1.3 * camera.height / (2 * camera.fy)
    jx = (p[:, 0] / d).clamp(-lim_x, lim_x) * d
    jy = (p[:, 1] / d).clamp(-lim_y, lim_y) * d
    zeros = torch.zeros_like(d)
    jac = torch.stack([camera.fx / d, zeros, camera.fx * jx / d ** 2,
                       zeros, -camera.fy / d, -camera.fy * jy / d ** 2], -1).reshape(-1, 2, 3)
    cov2 = jac @ cov_cam @ jac.transpose(1, 2) + low_pass * torch.eye(2, dtype=means.dtype, device=means.device)
    a, b, c = cov2[:, 0, 0], cov2[:, 0, 1], cov2[:, 1, 1]
    det = (a * c - b * b).clamp_min(1e-12)
    inv = torch.stack([c / det, -b / det, -b / det, a / det], -1).reshape(-1, 2, 2)
    mid = 0.5 * (a + c)
    radius = 3.0 * torch.sqrt(mid + torch.sqrt((mid * mid - det).clamp_min(0.0)))
    return torch.stack([u, v], -1), inv, depth, radius, visible


def splat_colors(means, sh, origin, max_color: float = float("inf")) -> torch.Tensor:
    """(N, 3) colour of each Gaussian seen from ``origin`` (3,): SH(d) . k + 0.5 clamped to [0, max_color]."""
    dirs = torch.nn.functional.normalize(means - origin, dim=-1)
    degree = int(round(sh.shape[-1] ** 0.5)) - 1
    return ((sh * sh_basis(degree, dirs)[:, None, :]).sum(-1) + 0.5).clamp(0.0, max_color)


def screen_splats(means, log_scales, quats, opacity_logits, sh, camera: Camera, rules: SplatRules = REFERENCE):
    """The Gaussians that touch the image, projected and sorted front to back: centres (K, 2), inverse covariances
    (K, 2, 2), colours (K, 3), opacities (K,) and 3-sigma radii (K,); differentiable in every input."""
    W, H = camera.width, camera.height
    with torch.no_grad():  # which Gaussians touch the image: only those go through the differentiable path
        centre, _, depth, radius, visible = project(means, log_scales, quats, camera, rules.low_pass)
        seen = visible & (centre[:, 0] + radius >= 0) & (centre[:, 1] + radius >= 0) & (centre[:, 0] - radius < W) \
            & (centre[:, 1] - radius < H)
        keep = torch.nonzero(seen).squeeze(1)
        keep = keep[torch.argsort(depth[keep])]
    means, log_scales, quats, opacity_logits, sh = (t[keep] for t in (means, log_scales, quats, opacity_logits, sh))
    centre, inv_cov, _, radius, _ = project(means, log_scales, quats, camera, rules.low_pass)
    origin = torch.as_tensor(camera.c2w[:3, 3], dtype=means.dtype, device=means.device)
    color = splat_colors(means, sh, origin, rules.max_color)
    return centre, inv_cov, color, torch.sigmoid(opacity_logits), radius.detach()


def rasterize(means, log_scales, quats, opacity_logits, sh, camera: Camera, background=(1.0, 1.0, 1.0),
              rules: SplatRules = REFERENCE) -> torch.Tensor:
    """(H, W, 3) float32 image of the Gaussians (tensors as :class:`~nerfbake.splats.gaussians.Gaussians`) from
    ``camera`` under ``rules``, composited by the Warp kernels; see the module docstring."""
    centre, inv_cov, color, opacity, radius = screen_splats(means, log_scales, quats, opacity_logits, sh, camera, rules)
    conic = torch.stack([inv_cov[:, 0, 0], inv_cov[:, 0, 1], inv_cov[:, 1, 1]], -1)
    return composite(centre, conic, opacity, color, radius, camera.width, camera.height, background, rules)


def rasterize_reference(means, log_scales, quats, opacity_logits, sh, camera: Camera,
                        background=(1.0, 1.0, 1.0), rules: SplatRules = REFERENCE) -> torch.Tensor:
    """:func:`rasterize` in plain torch, in the inputs' dtype (float64 for gradcheck)."""
    dev, dt = means.device, means.dtype
    W, H = camera.width, camera.height
    centre, inv_cov, color, opacity, radius = screen_splats(means, log_scales, quats, opacity_logits, sh, camera, rules)
    lo = (centre - radius[:, None]).detach()
    hi = (centre + radius[:, None]).detach()
    bg = torch.as_tensor(background, dtype=dt, device=dev)
    rows = []
    for ty in range(0, H, TILE):
        tiles = []
        for tx in range(0, W, TILE):
            w, h = min(TILE, W - tx), min(TILE, H - ty)
            sel = torch.nonzero((lo[:, 0] < tx + w) & (hi[:, 0] >= tx) & (lo[:, 1] < ty + h) & (hi[:, 1] >= ty)).squeeze(1)
            if sel.numel() == 0:
                tiles.append(bg.expand(h, w, 3))
                continue
            ys, xs = torch.meshgrid(torch.arange(ty, ty + h, dtype=dt, device=dev) + 0.5,
                                    torch.arange(tx, tx + w, dtype=dt, device=dev) + 0.5, indexing="ij")
            pix = torch.stack([xs, ys], -1).reshape(-1, 1, 2)
            delta = pix - centre[sel][None]  # (P, K, 2)
            ic = inv_cov[sel]
            power = -0.5 * (ic[None, :, 0, 0] * delta[..., 0] ** 2 + 2 * ic[None, :, 0, 1] * delta[..., 0] * delta[..., 1]
                            + ic[None, :, 1, 1] * delta[..., 1] ** 2)
            alpha = (opacity[sel][None] * torch.exp(power.clamp(max=0.0))).clamp(max=rules.max_alpha)
            drawn = (alpha >= rules.min_alpha) & (power >= -rules.cutoff)
            alpha = torch.where(drawn, alpha, torch.zeros_like(alpha))
            after = torch.cumprod(1 - alpha, 1)  # transmittance behind each Gaussian
            trans = torch.cat([torch.ones_like(alpha[:, :1]), after[:, :-1]], 1)
            weight = torch.where(after >= rules.min_transmittance, alpha * trans, torch.zeros_like(alpha))
            rgb = weight @ color[sel] + (1 - weight.sum(1, keepdim=True)) * bg
            tiles.append(rgb.reshape(h, w, 3))
        rows.append(torch.cat(tiles, 1))
    return torch.cat(rows, 0)


def render_gaussians(g, camera: Camera, background=(1.0, 1.0, 1.0), rules: SplatRules = REFERENCE) -> torch.Tensor:
    """(H, W, 3) float32 image of :class:`~nerfbake.splats.gaussians.Gaussians` ``g`` under ``rules`` (no
    gradients)."""
    with torch.no_grad():
        return rasterize(*(torch.as_tensor(getattr(g, k), dtype=torch.float32) for k in FIELDS), camera, background,
                         rules)
