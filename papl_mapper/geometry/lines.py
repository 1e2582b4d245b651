"""3D lines: Pluecker coordinates, the orthonormal (U, W) and the anchored three-parameter forms.

A Pluecker line is L = (n, v) (..., 6): n = P x v is the moment (normal of the plane through the line
and the origin), v the direction. Every function is vectorised over leading dimensions. Jacobians use
gtsam's right perturbations (pose: T @ Exp(omega, nu); rotation: U @ Exp(delta)) so that the backend
can hand them to gtsam unchanged; each one is checked against finite differences in the tests.

Anchored representation (paper eq. "three-parameter"): a structural line is its principal axis direction
v (unit, shared by every line of the axis) plus r, the inverse depth of the segment midpoint in the line's
reference keyframe: P_c = b / r with b = K^-1 (u, v, 1) the bearing of the midpoint of the segment as
OBSERVED in that keyframe, so r = 1/z. Taking the bearing from the observation (not from the 3D
endpoints) matters: the observed midpoint lies on the image of the true line, so its ray meets the
true line and the three parameters can reach it; a bearing through a noisy 3D midpoint generally misses
it. What a Map stores: `ref_keyframe_id` and `inverse_depth` r; b is re-derived from the line's
observation in the reference keyframe (`anchor_from_observation`). During one optimisation b is constant.

That paper form gives a line ONE degree of freedom (its depth along the fixed ray): the line can never
leave the plane through the reference camera, the ray and v, so the noise of the one reference observation
is never averaged out. `anchored_offset_plucker` adds s, a sideways shift of the anchor across the line in
the reference image (2 per line + 2 per axis, the minimal count for lines parallel to a known direction).
"""

from __future__ import annotations

import numpy as np

from papl_mapper.geometry.se3 import invert, skew, so3_exp, transform

_E1 = np.array([1.0, 0.0, 0.0])
_E2 = np.array([0.0, 1.0, 0.0])


# ---- Pluecker ---------------------------------------------------------------------------------


def plucker_from_endpoints(P1: np.ndarray, P2: np.ndarray) -> np.ndarray:
    """(..., 3) endpoints -> (..., 6) Pluecker (P1 x P2, P2 - P1)."""
    P1 = np.asarray(P1, dtype=np.float64)
    P2 = np.asarray(P2, dtype=np.float64)
    return np.concatenate([np.cross(P1, P2), P2 - P1], axis=-1)


def plucker_from_point_dir(P: np.ndarray, d: np.ndarray) -> np.ndarray:
    """(..., 3) point on the line and direction -> (..., 6) Pluecker (P x d, d)."""
    P = np.asarray(P, dtype=np.float64)
    d = np.asarray(d, dtype=np.float64)
    return np.concatenate([np.cross(P, d), d], axis=-1)


def plucker_from_homogeneous_points(X1: np.ndarray, X2: np.ndarray) -> np.ndarray:
    """(..., 4) homogeneous points (possibly at infinity) -> (..., 6) Pluecker, up to scale."""
    x1, w1 = X1[..., :3], X1[..., 3:]
    x2, w2 = X2[..., :3], X2[..., 3:]
    return np.concatenate([np.cross(x1, x2), w1 * x2 - w2 * x1], axis=-1)


def line_point_dir(L: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(..., 6) -> the point of the line closest to the origin (..., 3) and the unit direction (..., 3)."""
    n, v = L[..., :3], L[..., 3:]
    vv = np.sum(v * v, axis=-1, keepdims=True)
    P0 = np.cross(v, n) / vv
    return P0, v / np.sqrt(vv)


def normalize_plucker(L: np.ndarray) -> np.ndarray:
    """Scale so that |v| = 1 (then |n| is the distance of the line from the origin)."""
    return L / np.linalg.norm(L[..., 3:], axis=-1, keepdims=True)


def plucker_to_camera(
    L_w: np.ndarray, T_wc: np.ndarray, jacobians: bool = False
) -> np.ndarray | tuple[np.ndarray, np.ndarray, np.ndarray]:
    """World line to camera frame: n_c = R^T (n_w - t x v_w), v_c = R^T v_w with T_wc = (R, t).

    With `jacobians`, also d L_c / d xi (..., 6, 6) for T_wc @ Exp(xi) and d L_c / d L_w (..., 6, 6).
    """
    R = T_wc[..., :3, :3]
    t = T_wc[..., :3, 3]
    Rt = np.swapaxes(R, -1, -2)
    n_w, v_w = L_w[..., :3], L_w[..., 3:]
    n_c = np.einsum("...ij,...j->...i", Rt, n_w - np.cross(t, v_w))
    v_c = np.einsum("...ij,...j->...i", Rt, v_w)
    L_c = np.concatenate([n_c, v_c], axis=-1)
    if not jacobians:
        return L_c
    shape = L_c.shape[:-1]
    J_xi = np.zeros(shape + (6, 6))
    J_xi[..., :3, :3] = skew(n_c)
    J_xi[..., :3, 3:] = skew(v_c)
    J_xi[..., 3:, :3] = skew(v_c)
    J_L = np.zeros(shape + (6, 6))
    J_L[..., :3, :3] = Rt
    J_L[..., :3, 3:] = -Rt @ skew(t)
    J_L[..., 3:, 3:] = Rt
    return L_c, J_xi, J_L


def plucker_to_world(L_c: np.ndarray, T_wc: np.ndarray) -> np.ndarray:
    """Camera line to world frame (inverse of `plucker_to_camera`)."""
    return plucker_to_camera(L_c, invert(T_wc))


# ---- projection and reprojection error -----------------------------------------------------


def line_intrinsics(K: np.ndarray) -> np.ndarray:
    """The paper's line intrinsic matrix K_L (= det(K) K^-T): image line l = K_L n_c in pixels."""
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    return np.array([[fy, 0.0, 0.0], [0.0, fx, 0.0], [-fy * cx, -fx * cy, fx * fy]])


def project_line(K: np.ndarray, L_c: np.ndarray) -> np.ndarray:
    """(..., 6) camera-frame lines -> (..., 3) homogeneous image lines in pixels (l . (u, v, 1) = 0)."""
    return np.einsum("ij,...j->...i", line_intrinsics(K), L_c[..., :3])


def endpoint_errors(
    K: np.ndarray, L_c: np.ndarray, obs_xy: np.ndarray, jacobian: bool = False, eps: float = 1e-12
) -> np.ndarray | tuple[np.ndarray, np.ndarray]:
    """Signed pixel distances of the observed endpoints (..., 4) to the projected line: (..., 2).

    e_i = p_i . l / sqrt(l1^2 + l2^2), l = K_L n_c. With `jacobian`, also d e / d L_c (..., 2, 6)
    (zero in the v block: the error depends on n_c only). `eps` guards the norm of a degenerate line
    (one through the camera centre); callers drop such observations before optimising.
    """
    KL = line_intrinsics(K)
    l = np.einsum("ij,...j->...i", KL, L_c[..., :3])
    s2 = l[..., 0] ** 2 + l[..., 1] ** 2
    s = np.sqrt(np.maximum(s2, eps))
    p1 = np.concatenate([obs_xy[..., 0:2], np.ones(obs_xy.shape[:-1] + (1,))], -1)
    p2 = np.concatenate([obs_xy[..., 2:4], np.ones(obs_xy.shape[:-1] + (1,))], -1)
    d1 = np.sum(p1 * l, -1)
    d2 = np.sum(p2 * l, -1)
    e = np.stack([d1 / s, d2 / s], -1)
    if not jacobian:
        return e
    l12 = np.concatenate([l[..., :2], np.zeros(l.shape[:-1] + (1,))], -1)
    s3 = (s**3)[..., None]
    si = s[..., None]
    de_dl = np.stack([p1 / si - d1[..., None] * l12 / s3, p2 / si - d2[..., None] * l12 / s3], -2)
    J = np.zeros(e.shape + (6,))
    J[..., :3] = de_dl @ KL
    return e, J


def projected_line_norm(K: np.ndarray, L_c: np.ndarray) -> np.ndarray:
    """|(l1, l2)| / |L_c| -- near zero when the line passes through the camera centre (degenerate)."""
    l = project_line(K, L_c)
    scale = np.linalg.norm(L_c[..., 3:], axis=-1) * max(abs(K[0, 0]), abs(K[1, 1]))
    return np.linalg.norm(l[..., :2], axis=-1) / np.maximum(scale, 1e-300)


# ---- orthonormal representation (Bartoli & Sturm) ------------------------------------------------


def ortho_from_plucker(L: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(..., 6) -> U (..., 3, 3) in SO(3) and phi (...,) with W = R(phi), cos phi ~ |n|, sin phi ~ |v|.

    A line through the origin (n = 0) gets an arbitrary u1 perpendicular to v and phi = 0.
    """
    n, v = L[..., :3], L[..., 3:]
    nn = np.linalg.norm(n, axis=-1)
    vn = np.linalg.norm(v, axis=-1)
    u2 = v / vn[..., None]
    through_origin = nn < 1e-12 * np.maximum(vn, 1e-300)
    helper = np.where(np.abs(u2[..., :1]) < 0.9, _E1, _E2)
    alt = np.cross(u2, helper)
    alt /= np.linalg.norm(alt, axis=-1, keepdims=True)
    u1 = np.where(through_origin[..., None], alt, n / np.where(through_origin, 1.0, nn)[..., None])
    u3 = np.cross(u1, u2)
    U = np.stack([u1, u2, u3], axis=-1)
    phi = np.arctan2(vn, nn)
    return U, phi


def plucker_from_ortho(U: np.ndarray, phi: np.ndarray, to_world: np.ndarray | None = None) -> np.ndarray:
    """U, phi -> (..., 6) Pluecker (cos phi u1, sin phi u2), i.e. distance from origin = cot phi; with
    `to_world` (..., 6, 6, `local_to_world`) U, phi describe the line in that frame."""
    c = np.cos(phi)[..., None]
    s = np.sin(phi)[..., None]
    L = np.concatenate([c * U[..., :, 0], s * U[..., :, 1]], -1)
    return L if to_world is None else np.einsum("...ij,...j->...i", to_world, L)


def ortho_jacobian(U: np.ndarray, phi: np.ndarray, to_world: np.ndarray | None = None) -> np.ndarray:
    """d L / d (delta_psi, delta_phi) (..., 6, 4) for the update U @ Exp(delta_psi), phi + delta_phi
    (of the world line when `to_world` is given, as for plucker_from_ortho)."""
    if to_world is not None:
        return to_world @ ortho_jacobian(U, phi)
    c = np.cos(phi)[..., None, None]
    s = np.sin(phi)[..., None, None]
    J = np.zeros(np.shape(phi) + (6, 4))
    J[..., :3, :3] = -c * (U @ skew(_E1))
    J[..., 3:, :3] = -s * (U @ skew(_E2))
    J[..., :3, 3] = -s[..., 0] * U[..., :, 0]
    J[..., 3:, 3] = c[..., 0] * U[..., :, 1]
    return J


def plucker_to_local(L: np.ndarray, origin: np.ndarray, scale: np.ndarray) -> np.ndarray:
    """(..., 6) world Pluecker -> the same line in the frame X_local = (X - origin) / scale."""
    n, v = L[..., :3], L[..., 3:]
    return np.concatenate([(n - np.cross(origin, v)) / np.asarray(scale)[..., None], v], -1)


def local_to_world(origin: np.ndarray, scale: np.ndarray) -> np.ndarray:
    """(..., 6, 6) linear map taking Pluecker coordinates in that frame back to the world:
    n = scale n_local + origin x v, v = v_local (so it is also d L_world / d L_local)."""
    origin = np.asarray(origin, np.float64)
    M = np.zeros(origin.shape[:-1] + (6, 6))
    M[..., :3, :3] = np.asarray(scale)[..., None, None] * np.eye(3)
    M[..., :3, 3:] = skew(origin)
    M[..., 3:, 3:] = np.eye(3)
    return M


def line_frame(L: np.ndarray, centre: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """A frame for a line's orthonormal coordinates: origin `centre` (e.g. its cameras' mean centre) and
    unit its distance from the line, so the local line is at distance 1 (phi = 45 deg). In the world
    frame cot(phi) is the distance from the world origin: for a line tens of units away a step of
    0.01 rad in phi moves it by metres, and a Gauss-Newton step on such lines fails unless heavily
    damped; in this frame a step moves the line in proportion to its distance from the cameras."""
    d = np.linalg.norm(plucker_to_local(L, centre, np.ones(L.shape[:-1]))[..., :3], axis=-1)
    d /= np.linalg.norm(L[..., 3:], axis=-1)
    return centre, np.where(d > 1e-12, d, 1.0)


def ortho_retract(U: np.ndarray, phi: np.ndarray, delta: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The minimal 4-dof update: (U @ Exp(delta[:3]), phi + delta[3])."""
    return U @ so3_exp(delta[..., :3]), phi + delta[..., 3]


# ---- unit directions: tangent-plane update and latitude/longitude ------------------------------


def tangent_basis(v: np.ndarray) -> np.ndarray:
    """(..., 3) unit vectors -> (..., 3, 2) orthonormal basis of the tangent plane (defined everywhere)."""
    helper = np.where(np.abs(v[..., :1]) < 0.9, _E1, _E2)
    b1 = np.cross(v, helper)
    b1 /= np.linalg.norm(b1, axis=-1, keepdims=True)
    b2 = np.cross(v, b1)
    return np.stack([b1, b2], axis=-1)


def sphere_retract(v: np.ndarray, delta: np.ndarray, basis: np.ndarray | None = None) -> np.ndarray:
    """Exponential map on S^2: v cos|d| + (B d / |d|) sin|d| (gtsam Unit3 retract for gtsam's basis)."""
    B = tangent_basis(v) if basis is None else basis
    t = np.einsum("...ij,...j->...i", B, delta)
    a = np.linalg.norm(t, axis=-1, keepdims=True)
    sinc = np.where(a < 1e-12, 1.0, np.sin(a) / np.where(a < 1e-12, 1.0, a))
    out = np.cos(a) * v + sinc * t
    return out / np.linalg.norm(out, axis=-1, keepdims=True)


def direction_from_latlon(phi: np.ndarray, theta: np.ndarray, jacobian: bool = False):
    """The paper's latitude/longitude: phi = arccos(v_z), theta = atan2(v_x, v_y) + pi.

    v = (-sin phi sin theta, -sin phi cos theta, cos phi); with `jacobian` also dv/d(phi, theta) (..., 3, 2),
    whose second column vanishes at the poles (phi = 0 or pi): the reason we update axes in the tangent plane.
    """
    sp, cp, st, ct = np.sin(phi), np.cos(phi), np.sin(theta), np.cos(theta)
    v = np.stack([-sp * st, -sp * ct, cp], -1)
    if not jacobian:
        return v
    J = np.stack(
        [np.stack([-cp * st, -sp * ct], -1), np.stack([-cp * ct, sp * st], -1), np.stack([-sp, 0 * sp], -1)],
        -2,
    )
    return v, J


def latlon_from_direction(v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Inverse of `direction_from_latlon` for unit v."""
    phi = np.arccos(np.clip(v[..., 2], -1.0, 1.0))
    theta = np.arctan2(v[..., 0], v[..., 1]) + np.pi
    return phi, theta


# ---- anchored (three-parameter) representation --------------------------------------------------


def anchor_from_endpoints(endpoints_w: np.ndarray, T_wr: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Bearing b (..., 3) = (x, y, 1) and inverse depth r (...,) = 1/z of the segment midpoint in the
    reference camera. r <= 0 or non-finite means the midpoint is not in front of that camera."""
    mid_w = endpoints_w.mean(axis=-2)
    mid_c = transform(invert(T_wr), mid_w)
    z = mid_c[..., 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        b = mid_c / z[..., None]
        r = 1.0 / z
    return b, r


def anchor_from_observation(
    obs_xy: np.ndarray, K: np.ndarray, T_wr: np.ndarray, L_w: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Bearing b = K^-1 (midpoint of the observed segment, 1) (..., 3) in the reference camera, the inverse
    depth r (...,) of the ray's point closest to the 3D line L_w, and the sine of the ray-line angle
    (near 0: the line runs along the ray and r is undefined; r <= 0: the line is met behind the camera)."""
    mid = (obs_xy[..., :2] + obs_xy[..., 2:]) / 2.0
    hom = np.concatenate([mid, np.ones(mid.shape[:-1] + (1,))], -1)
    b = hom @ np.linalg.inv(K).T
    r, sin = ray_inverse_depth(b, T_wr, L_w)
    return b, r, sin


def ray_inverse_depth(b: np.ndarray, T_wr: np.ndarray, L_w: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Inverse depth r (...,) of the point of the ray T_wr (t b), t > 0, closest to the line L_w, and the
    sine of the ray-line angle. b (..., 3) has z = 1 in the camera, so the point's depth is t."""
    P0, d = line_point_dir(L_w)
    bw = np.einsum("...ij,...j->...i", T_wr[..., :3, :3], b)
    w0 = T_wr[..., :3, 3] - P0
    a = np.sum(bw * bw, -1)
    bb = np.sum(bw * d, -1)
    dd = np.sum(bw * w0, -1)
    e = np.sum(d * w0, -1)
    den = a - bb**2
    sin = np.sqrt(np.maximum(den / a, 0.0))
    with np.errstate(divide="ignore", invalid="ignore"):
        t = (bb * e - dd) / den
        r = 1.0 / t
    return r, sin


def anchored_plucker(
    v: np.ndarray, r: np.ndarray, bearing_c: np.ndarray, T_wr: np.ndarray, jacobians: bool = False
):
    """L_w = (P_w x v, v) with P_w = T_wr (b / r): the paper's three-parameter line.

    With `jacobians` also dL/dv (..., 6, 3), dL/dr (..., 6) and dL/dxi_ref (..., 6, 6) for T_wr @ Exp(xi).
    For a minimal axis update multiply dL/dv by the tangent basis (..., 3, 2).
    """
    r = np.asarray(r, dtype=np.float64)
    R = T_wr[..., :3, :3]
    P_c = bearing_c / r[..., None]
    P_w = np.einsum("...ij,...j->...i", R, P_c) + T_wr[..., :3, 3]
    L = np.concatenate([np.cross(P_w, v), v], -1)
    if not jacobians:
        return L
    shape = L.shape[:-1]
    Sv = skew(v)
    J_v = np.zeros(shape + (6, 3))
    J_v[..., :3, :] = skew(P_w)
    J_v[..., 3:, :] = np.eye(3)
    J_r = np.zeros(shape + (6,))
    Rb = np.einsum("...ij,...j->...i", R, bearing_c)
    J_r[..., :3] = np.einsum("...ij,...j->...i", Sv, Rb) / (r**2)[..., None]
    J_xi = np.zeros(shape + (6, 6))
    dP_dw = -R @ skew(P_c)
    J_xi[..., :3, :3] = -Sv @ dP_dw
    J_xi[..., :3, 3:] = -Sv @ R
    return L, J_v, J_r, J_xi


def anchor_offset_direction(line_px: np.ndarray, K: np.ndarray) -> np.ndarray:
    """The sideways direction q (..., 3), z = 0, in which `anchored_offset_plucker` moves its anchor: the
    unit pixel normal of the image line `line_px` (..., 3) (a, b, c) mapped by K^-1, so the offset s is in
    pixels across the line in the reference image."""
    n = line_px[..., :2] / np.maximum(np.linalg.norm(line_px[..., :2], axis=-1, keepdims=True), 1e-300)
    hom = np.concatenate([n, np.zeros(n.shape[:-1] + (1,))], -1)
    return hom @ np.linalg.inv(K).T


def anchored_offset_plucker(
    v: np.ndarray,
    rs: np.ndarray,
    bearing_c: np.ndarray,
    q_c: np.ndarray,
    T_wr: np.ndarray,
    jacobians: bool = False,
):
    """L_w = (P_w x v, v) with P_w = T_wr ((b + s q) / r), rs = (r, s) (..., 2): an anchored line with two
    degrees of freedom per line. r is the paper's inverse depth of the anchor in the reference keyframe,
    s moves the anchor s pixels across the line in that image (q from `anchor_offset_direction`, z = 0, so
    1/r stays the anchor's depth). With s the line can reach every line of direction v, not only those
    meeting one fixed ray (the paper's n + 2 form, `anchored_plucker`, is s = 0 held).

    With `jacobians` also dL/dv (..., 6, 3), dL/d(r, s) (..., 6, 2) and dL/dxi_ref (..., 6, 6).
    """
    rs = np.asarray(rs, dtype=np.float64)
    r, s = rs[..., 0], rs[..., 1]
    b = bearing_c + s[..., None] * q_c
    if not jacobians:
        return anchored_plucker(v, r, b, T_wr)
    L, J_v, J_r, J_xi = anchored_plucker(v, r, b, T_wr, jacobians=True)
    J_rs = np.zeros(L.shape + (2,))
    J_rs[..., 0] = J_r
    Rq = np.einsum("...ij,...j->...i", T_wr[..., :3, :3], q_c)
    J_rs[..., :3, 1] = -np.einsum("...ij,...j->...i", skew(v), Rq) / r[..., None]
    return L, J_v, J_rs, J_xi


def offset_anchor_on_line(
    bearing_c: np.ndarray, q_c: np.ndarray, T_wr: np.ndarray, L_w: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """(r, s) (..., 2) that put the anchor (b + s q) / r on the line L_w, and the sine of the angle between
    the line and the anchor plane span(b, q) (near 0: the line lies in that plane and (r, s) is undefined;
    r <= 0: the line meets the plane behind the camera)."""
    P0, d = line_point_dir(L_w)
    Rt = np.swapaxes(T_wr[..., :3, :3], -1, -2)
    X0 = np.einsum("...ij,...j->...i", Rt, P0 - T_wr[..., :3, 3])  # a point of the line, reference frame
    dc = np.einsum("...ij,...j->...i", Rt, d)
    n = np.cross(bearing_c, q_c)  # normal of the anchor plane
    nn = np.linalg.norm(n, axis=-1)
    dn = np.sum(dc * n, -1)
    sin = np.abs(dn) / np.maximum(nn * np.linalg.norm(dc, axis=-1), 1e-300)
    with np.errstate(divide="ignore", invalid="ignore"):
        t = -np.sum(X0 * n, -1) / dn
        X = X0 + t[..., None] * dc  # where the line meets the plane: X = z (b + s q), z = X_z (q_z = 0)
        z = X[..., 2]
        r = 1.0 / z
        qq = np.sum(q_c * q_c, -1)
        s = np.sum((X / z[..., None] - bearing_c) * q_c, -1) / qq
    return np.stack([r, s], -1), sin


# ---- endpoints from an infinite line --------------------------------------------------------


def clip_to_observations(
    L_w: np.ndarray,
    line_index: np.ndarray,
    T_wc: np.ndarray,
    K: np.ndarray,
    obs_xy: np.ndarray,
    n_lines: int,
    min_cos: float = 1e-3,
) -> tuple[np.ndarray, np.ndarray]:
    """Endpoints (M, 2, 3) spanning the observed extent of each infinite line, and an ok mask (M,).

    Each observed endpoint's viewing ray is intersected (closest approach) with its 3D line; the
    segment runs from the smallest to the largest parameter along the line. Rays nearly parallel to the
    line (|sin| < min_cos) or hitting behind the camera are ignored; a line left with none is not ok.
    L_w (M, 6); line_index (K,) rows of L_w; T_wc (K, 4, 4) and obs_xy (K, 4) per observation.
    """
    P0, d = line_point_dir(L_w)  # (M, 3) each
    Kinv = np.linalg.inv(K)
    px = obs_xy.reshape(-1, 2, 2)  # (K, 2, 2)
    hom = np.concatenate([px, np.ones(px.shape[:-1] + (1,))], -1)  # (K, 2, 3)
    rays_c = hom @ Kinv.T
    R = T_wc[:, None, :3, :3]
    rays = np.einsum("kaij,kaj->kai", np.broadcast_to(R, rays_c.shape[:2] + (3, 3)), rays_c)
    rays /= np.linalg.norm(rays, axis=-1, keepdims=True)
    C = T_wc[:, None, :3, 3]
    Pl = P0[line_index][:, None, :]
    dl = d[line_index][:, None, :]
    w0 = Pl - C
    b = np.sum(dl * rays, -1)
    dd = np.sum(dl * w0, -1)
    e = np.sum(rays * w0, -1)
    den = 1.0 - b**2
    good = den > min_cos**2
    s = np.where(good, (b * e - dd) / np.where(good, den, 1.0), np.nan)
    t = np.where(good, (e - b * dd) / np.where(good, den, 1.0), np.nan)
    good &= t > 0
    s = np.where(good, s, np.nan)
    smin = np.full(n_lines, np.inf)
    smax = np.full(n_lines, -np.inf)
    idx = np.repeat(line_index, 2)
    sv = s.ravel()
    ok_obs = np.isfinite(sv)
    np.minimum.at(smin, idx[ok_obs], sv[ok_obs])
    np.maximum.at(smax, idx[ok_obs], sv[ok_obs])
    ok = np.isfinite(smin) & np.isfinite(smax)
    smin = np.where(ok, smin, -0.5)
    smax = np.where(ok, smax, 0.5)
    ends = np.stack([P0 + smin[:, None] * d, P0 + smax[:, None] * d], axis=1)
    return ends, ok


def line_parallax_deg(
    L_w: np.ndarray, line_index: np.ndarray, centres: np.ndarray, n_lines: int
) -> np.ndarray:
    """Angle (degrees, (M,), 0..90) that the observing camera centres span about each line: the largest
    angle between back-projection planes (camera centre + line), from where the centres lie, not from noisy
    image lines. Near 0 every view sees the line in one plane (e.g. a camera walking along it) and its depth
    is unobservable. L_w (M, 6); line_index (K,) rows of L_w; centres (K, 3)."""
    P0, d = line_point_dir(L_w)
    u = centres - P0[line_index]
    dl = d[line_index]
    u = u - np.sum(u * dl, -1, keepdims=True) * dl
    B = tangent_basis(d)[line_index]  # (K, 3, 2)
    xy = np.einsum("kj,kja->ka", u, B)
    ang = np.arctan2(xy[:, 1], xy[:, 0])
    first = np.full(n_lines, np.nan)
    order = np.argsort(line_index, kind="stable")
    idx = line_index[order]
    head = np.ones(len(idx), bool)
    head[1:] = idx[1:] != idx[:-1]
    first[idx[head]] = ang[order][head]
    # planes, not rays: centres on opposite sides of the line (angles pi apart) give one plane
    rel = np.angle(np.exp(2j * (ang - first[line_index]))) / 2  # relative to the first view, (-pi/2, pi/2]
    lo = np.full(n_lines, np.inf)
    hi = np.full(n_lines, -np.inf)
    np.minimum.at(lo, line_index, rel)
    np.maximum.at(hi, line_index, rel)
    span = np.where(np.isfinite(lo), np.degrees(hi - lo), 0.0)
    return np.minimum(span, 180.0 - span)


# ---- comparing lines -----------------------------------------------------------------------


def line_distance(L_a: np.ndarray, L_b: np.ndarray) -> np.ndarray:
    """The paper's Error_l: norm of the difference of Pluecker coordinates, both scaled to |v| = 1 and
    signed so that v_a . v_b >= 0 (so the measure does not depend on scale or orientation)."""
    A = normalize_plucker(L_a)
    B = normalize_plucker(L_b)
    sign = np.where(np.sum(A[..., 3:] * B[..., 3:], -1) < 0, -1.0, 1.0)[..., None]
    return np.linalg.norm(A - sign * B, axis=-1)


def line_angle_deg(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Angles in degrees (0..90) between undirected directions a (..., 3) and b (..., 3), broadcasting.

    atan2(|a x b|, |a . b|): exact down to zero (arccos of the cosine runs out of digits near 1e-6
    degrees, which machine-dependent rounding then shows); the lengths cancel, so a Pluecker line's
    direction `L[..., 3:]` needs no normalising.
    """
    a = np.asarray(a, np.float64)
    b = np.asarray(b, np.float64)
    a0, a1, a2 = a[..., 0], a[..., 1], a[..., 2]
    b0, b1, b2 = b[..., 0], b[..., 1], b[..., 2]  # by components: np.cross and a norm cost 4x (hot in VPs)
    dot = np.abs(a0 * b0 + a1 * b1 + a2 * b2)
    cross = np.sqrt((a1 * b2 - a2 * b1) ** 2 + (a2 * b0 - a0 * b2) ** 2 + (a0 * b1 - a1 * b0) ** 2)
    return np.degrees(np.arctan2(cross, dot))
