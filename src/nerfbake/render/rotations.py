"""Unit quaternions (w first, as COLMAP and the 3DGS files store them) and rotation matrices, for numpy arrays and
torch tensors alike (the arithmetic is the same; only the stacking differs). Torch is not imported here: the data
readers use this without it, and a tensor argument means torch is loaded already."""
from __future__ import annotations

import sys

import numpy as np


def quaternion_matrix(q):
    """Rotation matrices (..., 3, 3) of quaternions (..., 4), w first; normalised here."""
    lib = np if isinstance(q, np.ndarray) else sys.modules["torch"]
    q = q / (q * q).sum(-1, keepdims=True) ** 0.5
    w, x, y, z = (q[..., i] for i in range(4))
    rows = [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
            2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
            2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]
    return lib.stack(rows, -1).reshape(*q.shape[:-1], 3, 3)


def matrix_quaternion(r: np.ndarray) -> np.ndarray:
    """Unit quaternions (..., 4), w first and w >= 0, of rotation matrices (..., 3, 3), by Shepperd's method: from
    the largest of 4w^2, 4x^2, 4y^2, 4z^2, so it stays exact at half turns."""
    r = np.asarray(r, np.float64)
    flat = r.reshape(-1, 3, 3)
    out = np.zeros((flat.shape[0], 4))
    for n, m in enumerate(flat):
        trace = np.trace(m)
        if trace >= np.diag(m).max():
            s = 2.0 * np.sqrt(1.0 + trace)
            q = [s / 4, (m[2, 1] - m[1, 2]) / s, (m[0, 2] - m[2, 0]) / s, (m[1, 0] - m[0, 1]) / s]
        else:
            i = int(np.argmax(np.diag(m)))
            j, k = (i + 1) % 3, (i + 2) % 3
            s = 2.0 * np.sqrt(1.0 + m[i, i] - m[j, j] - m[k, k])
            q = [0.0] * 4
            q[0], q[1 + i], q[1 + j], q[1 + k] = (m[k, j] - m[j, k]) / s, s / 4, (m[j, i] + m[i, j]) / s, (m[k, i] + m[i, k]) / s
        out[n] = q if q[0] >= 0 else [-v for v in q]
    return out.reshape(*r.shape[:-2], 4)
