"""The plain-float rotation helpers of `dpmhw.transforms` (used per tracker sample, where numpy's
per-call cost dominates) against numpy's products and the numpy rotation maps."""

from __future__ import annotations

import numpy as np
import pytest

from dpmhw.transforms import (
    angle_of_floats,
    matmul_bt_floats,
    matmul_floats,
    matrix_to_rotvec,
)


def test_plain_float_products_and_angle_are_numpys():
    rng = np.random.default_rng(3)
    for _ in range(20):
        a, b = rng.normal(size=(3, 3)), rng.normal(size=(3, 3))
        fa, fb = tuple(a.reshape(9).tolist()), tuple(b.reshape(9).tolist())
        assert np.allclose(np.reshape(matmul_floats(fa, fb), (3, 3)), a @ b, rtol=1e-14, atol=1e-14)
        assert np.allclose(np.reshape(matmul_bt_floats(fa, fb), (3, 3)), a @ b.T, rtol=1e-14, atol=1e-14)
    for angle in (0.0, 1e-9, 0.3, np.pi - 1e-7):
        c, s = np.cos(angle), np.sin(angle)
        turn = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])  # about z, not through the module
        expected = float(np.linalg.norm(matrix_to_rotvec(turn)))
        assert angle_of_floats(tuple(turn.reshape(9).tolist())) == pytest.approx(expected, abs=1e-15)
