"""SE(3) helpers on batches of 4x4 float64 poses (numpy only).

Perturbations follow gtsam's Pose3 retraction so that our analytic Jacobians plug straight into
gtsam factors: T' = T @ Exp(xi), xi = (omega, nu), rotation first, applied on the right.
"""

from __future__ import annotations

import numpy as np


def skew(v: np.ndarray) -> np.ndarray:
    """(..., 3) -> (..., 3, 3) cross-product matrices: skew(a) @ b == cross(a, b)."""
    v = np.asarray(v, dtype=np.float64)
    out = np.zeros(v.shape[:-1] + (3, 3))
    out[..., 0, 1] = -v[..., 2]
    out[..., 0, 2] = v[..., 1]
    out[..., 1, 0] = v[..., 2]
    out[..., 1, 2] = -v[..., 0]
    out[..., 2, 0] = -v[..., 1]
    out[..., 2, 1] = v[..., 0]
    return out


def so3_exp(omega: np.ndarray) -> np.ndarray:
    """(..., 3) rotation vectors -> (..., 3, 3) rotation matrices (Rodrigues, stable near zero)."""
    omega = np.asarray(omega, dtype=np.float64)
    theta = np.linalg.norm(omega, axis=-1)[..., None, None]
    K = skew(omega)
    small = theta < 1e-8
    t = np.where(small, 1.0, theta)
    a = np.where(small, 1.0 - theta**2 / 6.0, np.sin(t) / t)
    b = np.where(small, 0.5 - theta**2 / 24.0, (1.0 - np.cos(t)) / t**2)
    return np.eye(3) + a * K + b * (K @ K)


def so3_log(R: np.ndarray) -> np.ndarray:
    """(..., 3, 3) rotations -> (..., 3) rotation vectors (angle in [0, pi])."""
    R = np.asarray(R, dtype=np.float64)
    cos = np.clip((np.trace(R, axis1=-2, axis2=-1) - 1.0) / 2.0, -1.0, 1.0)
    theta = np.arccos(cos)
    w = np.stack([R[..., 2, 1] - R[..., 1, 2], R[..., 0, 2] - R[..., 2, 0], R[..., 1, 0] - R[..., 0, 1]], -1)
    s = np.sin(theta)
    small = s < 1e-6
    scale = np.where(small, 0.5 + theta**2 / 12.0, theta / (2.0 * np.where(small, 1.0, s)))
    out = w * scale[..., None]
    near_pi = small & (theta > 1.0)
    if np.any(near_pi):  # axis from the symmetric part: R = 2 a a^T - I at theta = pi
        Rp = R[near_pi]
        B = (Rp + np.eye(3)) / 2.0
        i = np.argmax(np.diagonal(B, axis1=-2, axis2=-1), axis=-1)
        a = B[np.arange(len(Rp)), :, i]
        a /= np.linalg.norm(a, axis=-1, keepdims=True)
        out[near_pi] = a * theta[near_pi][..., None]
    return out


def invert(T: np.ndarray) -> np.ndarray:
    """(..., 4, 4) rigid transforms -> their inverses (R^T, -R^T t)."""
    T = np.asarray(T, dtype=np.float64)
    R = T[..., :3, :3]
    t = T[..., :3, 3]
    out = np.zeros_like(T)
    Rt = np.swapaxes(R, -1, -2)
    out[..., :3, :3] = Rt
    out[..., :3, 3] = -np.einsum("...ij,...j->...i", Rt, t)
    out[..., 3, 3] = 1.0
    return out


def transform(T: np.ndarray, X: np.ndarray) -> np.ndarray:
    """Apply (..., 4, 4) transforms to (..., 3) points (broadcasting)."""
    return np.einsum("...ij,...j->...i", T[..., :3, :3], X) + T[..., :3, 3]


def retract(T: np.ndarray, xi: np.ndarray) -> np.ndarray:
    """T @ Exp(xi), xi = (omega, nu) (..., 6): gtsam's Pose3 retraction to first order."""
    T = np.asarray(T, dtype=np.float64)
    xi = np.asarray(xi, dtype=np.float64)
    D = np.zeros(xi.shape[:-1] + (4, 4))
    D[..., :3, :3] = so3_exp(xi[..., :3])
    D[..., :3, 3] = xi[..., 3:]
    D[..., 3, 3] = 1.0
    return T @ D


def make_T(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """(..., 3, 3) and (..., 3) -> (..., 4, 4)."""
    R = np.asarray(R, dtype=np.float64)
    out = np.zeros(R.shape[:-2] + (4, 4))
    out[..., :3, :3] = R
    out[..., :3, 3] = t
    out[..., 3, 3] = 1.0
    return out


def similarity_T_cw(T_cw: np.ndarray, R: np.ndarray, t: np.ndarray, scale: float | np.ndarray) -> np.ndarray:
    """World-to-camera pose after the world moves by x -> scale * R x + t (the camera keeps its shape,
    so the camera-frame translation scales too). Batched over leading axes: (..., 4, 4), (..., 3, 3),
    (..., 3), scalar or (...)."""
    R_cw = T_cw[..., :3, :3] @ np.swapaxes(R, -1, -2)
    scale = np.asarray(scale, np.float64)[..., None]
    return make_T(R_cw, scale * T_cw[..., :3, 3] - np.einsum("...ij,...j->...i", R_cw, t))


def project_points(K: np.ndarray, T_wc: np.ndarray, X_w: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Pinhole projection of world points: returns (..., 2) pixels and (...,) camera depth z."""
    X_c = transform(invert(T_wc), X_w)
    z = X_c[..., 2]
    zs = np.where(np.abs(z) < 1e-12, 1e-12, z)
    uv = np.stack([K[0, 0] * X_c[..., 0] / zs + K[0, 2], K[1, 1] * X_c[..., 1] / zs + K[1, 2]], -1)
    return uv, z


def rotation_angle_deg(R_a: np.ndarray, R_b: np.ndarray) -> np.ndarray:
    """Angle of R_a^T R_b in degrees."""
    return np.degrees(np.linalg.norm(so3_log(np.swapaxes(R_a, -1, -2) @ R_b), axis=-1))


def bearings(x: np.ndarray) -> np.ndarray:
    """Unit rays (N, 3) of normalised image coordinates (N, 2)."""
    b = np.column_stack([x, np.ones(len(x))])
    return b / np.linalg.norm(b, axis=1, keepdims=True)


def kabsch_rotation(a: np.ndarray, b: np.ndarray, weights: np.ndarray | None = None) -> np.ndarray:
    """The rotation R minimising the (weighted) sum of |b_i - R a_i|^2 over rows of (N, 3) vectors."""
    M = (b if weights is None else b * weights[:, None]).T @ a
    U, _, Vt = np.linalg.svd(M)
    return U @ np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt))]) @ Vt


def rotation_alignment(R_from: np.ndarray, R_to: np.ndarray) -> np.ndarray:
    """The rotation G with R_to[i] ~ G R_from[i] over (N, 3, 3) rotations, in the least squares (the
    chordal L2 mean of R_to R_from^T): Kabsch over the rotations' columns."""
    return kabsch_rotation(
        np.swapaxes(R_from, -1, -2).reshape(-1, 3), np.swapaxes(R_to, -1, -2).reshape(-1, 3)
    )


def ray_angles_deg(a: np.ndarray, b: np.ndarray, R: np.ndarray) -> np.ndarray:
    """(N,) angle (deg) between each unit ray b_i and R a_i."""
    return np.degrees(np.arccos(np.clip(np.sum(b * (a @ R.T), axis=1), -1.0, 1.0)))


def rotation_between_rays(
    b1: np.ndarray, b2: np.ndarray, iterations: int = 3
) -> tuple[np.ndarray, np.ndarray]:
    """Rotation R_21 (b2 ~ R_21 b1) of a camera turning in place, and each ray pair's residual angle (deg).

    Kabsch on unit rays, refitted on the pairs within three times the median residual, so the
    matches that move with parallax (or are wrong) do not pull the rotation. For a camera that also
    translated, the residuals are the parallax left after the best rotation: a lower bound.
    """
    keep = np.ones(len(b1), bool)
    R = np.eye(3)
    err = ray_angles_deg(b1, b2, R)
    for _ in range(iterations):
        if keep.sum() < 3:
            break
        R = kabsch_rotation(b1[keep], b2[keep])
        err = ray_angles_deg(b1, b2, R)
        keep = err <= 3.0 * max(float(np.median(err)), 1e-6)
    return R, err
