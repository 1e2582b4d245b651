"""Axis errors use the camera orientations' alignment, exact even for a short straight path."""

from __future__ import annotations

import numpy as np

from papl_mapper.eval.evaluate import orientation_alignment
from papl_mapper.geometry.se3 import so3_exp


def test_orientation_alignment_recovers_the_rotation():
    rng = np.random.default_rng(0)
    R = so3_exp(np.array([0.3, -0.2, 0.5]))  # ref world <- est world
    T_est = np.repeat(np.eye(4)[None], 20, axis=0)
    T_est[:, :3, :3] = so3_exp(rng.normal(0, 0.2, (20, 3)))
    T_est[:, 0, 3] = np.linspace(0, 1, 20)  # a straight path: positions cannot fix the roll about x
    T_ref = T_est.copy()
    T_ref[:, :3, :3] = R @ T_est[:, :3, :3]
    T_ref[:, :3, :3] = T_ref[:, :3, :3] @ so3_exp(rng.normal(0, 0.002, (20, 3)))  # small noise
    R_hat = orientation_alignment(T_est, T_ref)
    err = np.degrees(np.arccos(np.clip((np.trace(R_hat.T @ R) - 1) / 2, -1, 1)))
    assert err < 0.1
    assert np.isclose(np.linalg.det(R_hat), 1.0)
