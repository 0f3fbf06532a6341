"""Quaternion <-> matrix: one function for numpy and torch, and the inverse exact at half turns (where the naive
formula divides by zero)."""
import numpy as np
import torch

from nerfbake.render.rotations import matrix_quaternion, quaternion_matrix


def test_quaternions_and_matrices_round_trip_in_numpy_and_torch():
    q = np.random.default_rng(0).normal(size=(50, 4))
    r = quaternion_matrix(q)
    np.testing.assert_allclose(r @ np.swapaxes(r, 1, 2), np.broadcast_to(np.eye(3), r.shape), atol=1e-12)
    np.testing.assert_allclose(np.linalg.det(r), 1.0, atol=1e-12)
    np.testing.assert_allclose(quaternion_matrix(torch.tensor(q)).numpy(), r, atol=1e-12)
    unit = q / np.linalg.norm(q, axis=1, keepdims=True)
    np.testing.assert_allclose(matrix_quaternion(r), unit * np.sign(unit[:, :1]), atol=1e-12)
    # a quarter turn about z takes x to y
    np.testing.assert_allclose(quaternion_matrix(np.array([np.cos(np.pi / 4), 0, 0, np.sin(np.pi / 4)])) @ [1, 0, 0],
                               [0, 1, 0], atol=1e-12)


def test_half_turns_come_back_exactly():
    for axis in range(3):
        m = -np.eye(3)
        m[axis, axis] = 1.0
        q = matrix_quaternion(m)
        assert abs(abs(q[1 + axis]) - 1.0) < 1e-12
        np.testing.assert_allclose(quaternion_matrix(q), m, atol=1e-12)
