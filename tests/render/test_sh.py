import math

import numpy as np
import pytest
import scipy.special
import torch

from nerfbake.render.sh import eval_sh_color, sh_basis, sh_num_coeffs


def random_dirs(n, seed=0):
    d = torch.randn(n, 3, generator=torch.Generator().manual_seed(seed), dtype=torch.float64)
    return d / d.norm(dim=-1, keepdim=True)


def closed_form(l, m, dirs):
    """svox's real SH from scipy's complex Y_l^m (with Condon-Shortley phase): sqrt2*Im(Y_l^|m|) for m<0,
    Y_l^0, sqrt2*Re(Y_l^m) for m>0 — no (-1)^m compensation, which gives svox's signs."""
    x, y, z = dirs.numpy().T
    polar = np.arccos(np.clip(z, -1, 1))
    azim = np.arctan2(y, x)
    if hasattr(scipy.special, "sph_harm_y"):
        Y = scipy.special.sph_harm_y(l, abs(m), polar, azim)
    else:  # older scipy: sph_harm(m, l, azimuth, polar)
        Y = scipy.special.sph_harm(abs(m), l, azim, polar)
    if m < 0:
        return math.sqrt(2) * Y.imag
    if m == 0:
        return Y.real
    return math.sqrt(2) * Y.real


def test_basis_equals_closed_forms():
    dirs = random_dirs(500)
    basis = sh_basis(4, dirs).numpy()
    k = 0
    for l in range(5):
        for m in range(-l, l + 1):
            np.testing.assert_allclose(basis[:, k], closed_form(l, m, dirs), atol=1e-10, err_msg=f"l={l} m={m}")
            k += 1


def test_svox_sign_convention():
    d = torch.tensor([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0]], dtype=torch.float64)
    b = sh_basis(1, d)
    assert b[0, 1] < 0 and b[1, 3] < 0  # Y_1 = (-C1 y, C1 z, -C1 x)


def test_orthonormal_by_monte_carlo():
    dirs = random_dirs(400_000, seed=1)
    b = sh_basis(4, dirs)
    gram = (b.T @ b) * (4 * math.pi / len(dirs))
    np.testing.assert_allclose(gram.numpy(), np.eye(25), atol=0.03)


def test_eval_sh_color_layout_and_dc():
    dirs = random_dirs(10)
    coeffs = torch.zeros(10, 3 * 9, dtype=torch.float64)
    # Colour-major layout: R coefficients first. Only DC set: colour is direction-independent.
    coeffs[:, 0], coeffs[:, 9], coeffs[:, 18] = 1.0, -1.0, 0.0
    c = eval_sh_color(coeffs, dirs)
    expect = torch.sigmoid(torch.tensor([1.0, -1.0, 0.0], dtype=torch.float64) * 0.28209479177387814)
    torch.testing.assert_close(c, expect.expand(10, 3))
    with pytest.raises(ValueError):
        eval_sh_color(torch.zeros(10, 20), dirs)
    assert [sh_num_coeffs(d) for d in range(5)] == [1, 4, 9, 16, 25]
