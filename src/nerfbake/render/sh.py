"""Real spherical harmonics to degree 4 in the svox/volrend sign convention.

The basis is the real form of the Condon-Shortley complex SH *without* the (-1)^m compensation, ordered
m = -l..l within each degree l: Y_1 = (-C1*y, C1*z, -C1*x). PlenOctree files store, per leaf,
``[R_0..R_{B-1}, G_0..G_{B-1}, B_0..B_{B-1}, sigma]`` and colour = sigmoid(sum_k Y_k(d) * c_k).
"""
from __future__ import annotations

import torch

C0 = 0.28209479177387814
C1 = 0.4886025119029199
C2 = (1.0925484305920792, -1.0925484305920792, 0.31539156525252005, -1.0925484305920792, 0.5462742152960396)
C3 = (-0.5900435899266435, 2.890611442640554, -0.4570457994644658, 0.3731763325901154,
      -0.4570457994644658, 1.445305721320277, -0.5900435899266435)
C4 = (2.5033429417967046, -1.7701307697799304, 0.9461746957575601, -0.6690465435572892, 0.10578554691520431,
      -0.6690465435572892, 0.47308734787878004, -1.7701307697799304, 0.6258357354491761)

MAX_DEGREE = 4


def sh_num_coeffs(degree: int) -> int:
    """Number of basis functions up to and including ``degree`` ((degree+1)^2)."""
    if not 0 <= degree <= MAX_DEGREE:
        raise ValueError(f"SH degree must be in 0..{MAX_DEGREE}, got {degree}")
    return (degree + 1) ** 2


def sh_basis(degree: int, dirs: torch.Tensor) -> torch.Tensor:
    """Basis values (..., (degree+1)^2) at unit directions ``dirs`` (..., 3)."""
    sh_num_coeffs(degree)
    x, y, z = dirs.unbind(-1)
    out = [torch.full_like(x, C0)]
    if degree >= 1:
        out += [-C1 * y, C1 * z, -C1 * x]
    if degree >= 2:
        xx, yy, zz = x * x, y * y, z * z
        xy, yz, xz = x * y, y * z, x * z
        out += [C2[0] * xy, C2[1] * yz, C2[2] * (2.0 * zz - xx - yy), C2[3] * xz, C2[4] * (xx - yy)]
    if degree >= 3:
        out += [
            C3[0] * y * (3 * xx - yy),
            C3[1] * xy * z,
            C3[2] * y * (4 * zz - xx - yy),
            C3[3] * z * (2 * zz - 3 * xx - 3 * yy),
            C3[4] * x * (4 * zz - xx - yy),
            C3[5] * z * (xx - yy),
            C3[6] * x * (xx - 3 * yy),
        ]
    if degree >= 4:
        out += [
            C4[0] * xy * (xx - yy),
            C4[1] * yz * (3 * xx - yy),
            C4[2] * xy * (7 * zz - 1),
            C4[3] * yz * (7 * zz - 3),
            C4[4] * (zz * (35 * zz - 30) + 3),
            C4[5] * xz * (7 * zz - 3),
            C4[6] * (xx - yy) * (7 * zz - 1),
            C4[7] * xz * (xx - 3 * yy),
            C4[8] * (xx * (xx - 3 * yy) - yy * (3 * xx - yy)),
        ]
    return torch.stack(out, dim=-1)


def eval_sh_color(coeffs: torch.Tensor, dirs: torch.Tensor, degree: int | None = None) -> torch.Tensor:
    """Colour sigmoid(sum_k Y_k(d) c_k) from coefficients (..., 3*B) in the colour-major svox layout."""
    num_basis = coeffs.shape[-1] // 3
    if degree is None:
        degree = int(round(num_basis**0.5)) - 1
    if 3 * sh_num_coeffs(degree) != coeffs.shape[-1]:
        raise ValueError(f"expected {3 * sh_num_coeffs(degree)} SH coefficients for degree {degree}, got {coeffs.shape[-1]}")
    basis = sh_basis(degree, dirs)
    c = coeffs.reshape(*coeffs.shape[:-1], 3, num_basis)
    return torch.sigmoid((c * basis[..., None, :]).sum(-1))
