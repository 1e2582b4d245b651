"""Geometry: analytic Jacobians against finite differences, representations round-trip, triangulation."""

from __future__ import annotations

import numpy as np
import pytest

from papl_mapper import geometry as g

JAC_RTOL = 1e-5  # relative tolerance of analytic vs central-difference Jacobians
FD_STEP = 1e-6
K = np.array([[500.0, 0, 320.0], [0, 510.0, 240.0], [0, 0, 1]])


def num_jac(f, x0: np.ndarray, retract=None, dim: int | None = None) -> np.ndarray:
    """Central differences of f at x0 along the local coordinates of `retract` (default: additive)."""
    dim = x0.size if dim is None else dim
    cols = []
    for i in range(dim):
        d = np.zeros(dim)
        d[i] = FD_STEP
        xp = retract(x0, d) if retract else x0 + d
        xm = retract(x0, -d) if retract else x0 - d
        cols.append((np.ravel(f(xp)) - np.ravel(f(xm))) / (2 * FD_STEP))
    return np.stack(cols, -1)


def assert_jac(analytic: np.ndarray, numeric: np.ndarray) -> None:
    scale = max(np.abs(numeric).max(), 1.0)
    np.testing.assert_allclose(analytic, numeric, atol=JAC_RTOL * scale, rtol=0)


def random_pose(rng: np.random.Generator, t_scale: float = 1.0) -> np.ndarray:
    return g.make_T(g.so3_exp(rng.normal(size=3) * 0.5), rng.normal(size=3) * t_scale)


@pytest.fixture
def rng() -> np.random.Generator:
    return np.random.default_rng(7)


def test_se3_exp_log_invert(rng):
    w = rng.normal(size=(20, 3))
    w *= (rng.uniform(0, 3.1, 20) / np.linalg.norm(w, axis=1))[:, None]
    np.testing.assert_allclose(g.so3_log(g.so3_exp(w)), w, atol=1e-9)
    np.testing.assert_allclose(g.so3_log(g.so3_exp(np.array([0, 0, np.pi]))), [0, 0, np.pi], atol=1e-6)
    T = random_pose(rng)
    np.testing.assert_allclose(T @ g.invert(T), np.eye(4), atol=1e-12)


def test_pose_retraction_matches_gtsam(rng):
    gtsam = pytest.importorskip("gtsam")
    T = random_pose(rng)
    xi = rng.normal(size=6) * 0.3
    np.testing.assert_allclose(
        g.retract(T, xi)[:3, :3], gtsam.Pose3(T).retract(xi).matrix()[:3, :3], atol=1e-9
    )


def test_plucker_constructors_and_transform(rng):
    P1, P2 = rng.normal(size=(2, 5, 3))
    L = g.plucker_from_endpoints(P1, P2)
    L2 = g.plucker_from_point_dir(P1, P2 - P1)
    np.testing.assert_allclose(L, L2, atol=1e-12)
    T = random_pose(rng)
    Lc = g.plucker_to_camera(L, T)
    Tcw = g.invert(T)
    Lc_ref = g.plucker_from_endpoints(g.transform(Tcw, P1), g.transform(Tcw, P2))
    np.testing.assert_allclose(Lc, Lc_ref, atol=1e-10)
    np.testing.assert_allclose(g.plucker_to_world(Lc, T), L, atol=1e-10)
    assert np.abs(np.sum(L[:, :3] * L[:, 3:], 1)).max() < 1e-12  # Klein constraint


def test_plucker_to_camera_jacobians(rng):
    L = g.plucker_from_endpoints(rng.normal(size=3), rng.normal(size=3) + 2)
    T = random_pose(rng)
    _, J_xi, J_L = g.plucker_to_camera(L, T, jacobians=True)
    assert_jac(J_xi, num_jac(lambda T_: g.plucker_to_camera(L, T_), T, g.retract, 6))
    assert_jac(J_L, num_jac(lambda L_: g.plucker_to_camera(L_, T), L))


def test_projection_matches_projected_endpoints(rng):
    P1 = np.array([-1.0, 0.3, 4.0])
    P2 = np.array([1.0, -0.2, 5.0])
    T = np.eye(4)
    uv, _ = g.project_points(K, np.stack([T, T]), np.stack([P1, P2]))
    l = g.project_line(K, g.plucker_from_endpoints(P1, P2))
    np.testing.assert_allclose(np.concatenate([uv, np.ones((2, 1))], 1) @ l, 0, atol=1e-8 * np.abs(l).max())
    e = g.endpoint_errors(K, g.plucker_from_endpoints(P1, P2), uv.ravel())
    np.testing.assert_allclose(e, 0, atol=1e-9)
    # shifting the observation by 3 px along the line normal gives 3 px errors
    nrm = l[:2] / np.linalg.norm(l[:2])
    e = g.endpoint_errors(K, g.plucker_from_endpoints(P1, P2), (uv + 3 * nrm).ravel())
    np.testing.assert_allclose(e, [3, 3], atol=1e-9)


def test_endpoint_error_jacobian(rng):
    Lc = g.plucker_from_endpoints(np.array([-1.0, 0.3, 4.0]), np.array([1.0, -0.2, 5.0]))
    obs = np.array([100.0, 200.0, 400.0, 260.0])
    _, J = g.endpoint_errors(K, Lc, obs, jacobian=True)
    assert_jac(J, num_jac(lambda L_: g.endpoint_errors(K, L_, obs), Lc))


def test_orthonormal_roundtrip_and_jacobian(rng):
    L = g.normalize_plucker(g.plucker_from_endpoints(rng.normal(size=3), rng.normal(size=3)))
    U, phi = g.ortho_from_plucker(L)
    np.testing.assert_allclose(U.T @ U, np.eye(3), atol=1e-12)
    assert np.linalg.det(U) > 0
    np.testing.assert_allclose(g.normalize_plucker(g.plucker_from_ortho(U, phi)), L, atol=1e-12)
    J = g.ortho_jacobian(U, phi)

    def f(delta):
        U2, p2 = g.ortho_retract(U, phi, delta)
        return g.plucker_from_ortho(U2, p2)

    assert_jac(J, num_jac(f, np.zeros(4)))
    # a line through the origin still gets a valid frame
    U0, phi0 = g.ortho_from_plucker(np.array([0, 0, 0, 0, 0, 1.0]))
    np.testing.assert_allclose(U0.T @ U0, np.eye(3), atol=1e-12)
    assert phi0 == pytest.approx(np.pi / 2)


def test_line_frame_roundtrip_and_chain_jacobian(rng):
    """A line far from the world origin, moved into its frame (origin near it, unit its distance): the
    local line is at distance 1 (phi = 45 deg), maps back exactly, and local_to_world is dL_world/dL_local."""
    L = g.normalize_plucker(g.plucker_from_point_dir(np.array([300.0, -40.0, 7.0]), rng.normal(size=3)))
    centre = np.array([302.0, -38.0, 5.0])
    origin, scale = g.line_frame(L, centre)
    L_loc = g.plucker_to_local(L, origin, scale)
    assert np.linalg.norm(L_loc[:3]) / np.linalg.norm(L_loc[3:]) == pytest.approx(1.0)
    np.testing.assert_allclose(g.local_to_world(origin, scale) @ L_loc, L, atol=1e-9)
    U, phi = g.ortho_from_plucker(L_loc)
    assert phi == pytest.approx(np.pi / 4)
    M = g.local_to_world(origin, scale)
    np.testing.assert_allclose(g.normalize_plucker(g.plucker_from_ortho(U, phi, M)), L, atol=1e-9)

    def f(delta):
        U2, p2 = g.ortho_retract(U, phi, delta)
        return g.plucker_from_ortho(U2, p2, M)

    assert_jac(g.ortho_jacobian(U, phi, M), num_jac(f, np.zeros(4)))


def test_anchored_roundtrip_and_jacobians(rng):
    T_wr = random_pose(rng)
    ends = g.transform(T_wr, np.array([[-1.0, 0.2, 4.0], [1.0, 0.4, 5.0]]))
    v = (ends[1] - ends[0]) / np.linalg.norm(ends[1] - ends[0])
    b, r = g.anchor_from_endpoints(ends, T_wr)
    assert b[2] == pytest.approx(1.0) and r == pytest.approx(1 / 4.5)
    L = g.anchored_plucker(v, r, b, T_wr)
    np.testing.assert_allclose(g.line_distance(L, g.plucker_from_endpoints(*ends)), 0, atol=1e-12)
    _, J_v, J_r, J_xi = g.anchored_plucker(v, r, b, T_wr, jacobians=True)
    assert_jac(J_v, num_jac(lambda v_: g.anchored_plucker(v_, r, b, T_wr), v))
    assert_jac(J_r[:, None], num_jac(lambda r_: g.anchored_plucker(v, r_[0], b, T_wr), np.atleast_1d(r)))
    assert_jac(J_xi, num_jac(lambda T_: g.anchored_plucker(v, r, b, T_), T_wr, g.retract, 6))
    # minimal axis update: chain with the tangent basis
    B = g.tangent_basis(v)
    J_num = num_jac(lambda d: g.anchored_plucker(g.sphere_retract(v, d, B), r, b, T_wr), np.zeros(2))
    assert_jac(J_v @ B, J_num)


def test_full_chain_anchored_error_jacobian(rng):
    """e(v, r, T_ref, T_obs): the exact chain the backend uses, end to end."""
    T_wr = random_pose(rng)
    T_wc = T_wr @ g.make_T(g.so3_exp([0.05, -0.1, 0.02]), [0.5, 0.1, -0.2])
    ends = g.transform(T_wr, np.array([[-1.0, 0.2, 4.0], [1.0, 0.4, 5.0]]))
    v = (ends[1] - ends[0]) / np.linalg.norm(ends[1] - ends[0])
    b, r = g.anchor_from_endpoints(ends, T_wr)
    obs = np.array([100.0, 200.0, 400.0, 260.0])

    def err(v_, r_, Tr, Tc):
        return g.endpoint_errors(K, g.plucker_to_camera(g.anchored_plucker(v_, r_, b, Tr), Tc), obs)

    L, J_v, J_r, J_xr = g.anchored_plucker(v, r, b, T_wr, jacobians=True)
    Lc, J_xc, J_L = g.plucker_to_camera(L, T_wc, jacobians=True)
    _, J_e = g.endpoint_errors(K, Lc, obs, jacobian=True)
    JeL = J_e @ J_L
    assert_jac(JeL @ J_xr, num_jac(lambda T_: err(v, r, T_, T_wc), T_wr, g.retract, 6))
    assert_jac(J_e @ J_xc, num_jac(lambda T_: err(v, r, T_wr, T_), T_wc, g.retract, 6))
    assert_jac((JeL @ J_r)[:, None], num_jac(lambda r_: err(v, r_[0], T_wr, T_wc), np.atleast_1d(r)))


def test_latlon_is_singular_at_the_pole_tangent_is_not():
    """Why axes are updated in the tangent plane: world +Z (the vertical axis) is the latitude pole."""
    for phi in (1e-9, 0.3):
        v, J = g.direction_from_latlon(np.array(phi), np.array(0.7), jacobian=True)
        assert_jac(J, num_jac(lambda x: g.direction_from_latlon(x[0], x[1]), np.array([phi, 0.7])))
        phi_b, th_b = g.latlon_from_direction(v)
        np.testing.assert_allclose(g.direction_from_latlon(phi_b, th_b), v, atol=1e-9)
    _, J_pole = g.direction_from_latlon(np.array(1e-9), np.array(0.7), jacobian=True)
    sv = np.linalg.svd(J_pole, compute_uv=False)
    assert sv[1] < 1e-8  # one direction of motion is lost: the normal equations become singular
    B = g.tangent_basis(np.array([0.0, 0.0, 1.0]))
    np.testing.assert_allclose(np.linalg.svd(B, compute_uv=False), [1, 1], atol=1e-12)


def test_sphere_retract_stays_unit_and_moves_by_angle(rng):
    v = np.array([0.0, 0.0, 1.0])
    out = g.sphere_retract(v, np.array([0.2, 0.0]))
    assert np.linalg.norm(out) == pytest.approx(1.0)
    assert np.degrees(np.arccos(out @ v)) == pytest.approx(np.degrees(0.2))


def test_clip_to_observations_recovers_observed_extent(rng):
    P1, P2 = np.array([-1.0, 0.5, 5.0]), np.array([1.5, 0.3, 6.0])
    T = np.stack([np.eye(4), g.make_T(np.eye(3), [0.6, 0.0, 0.0])])
    uv, _ = g.project_points(K, np.repeat(T[:, None], 2, 1), np.stack([P1, P2])[None].repeat(2, 0))
    L = g.plucker_from_endpoints(P1, P2)
    ends, ok = g.clip_to_observations(L[None], np.zeros(2, int), T, K, uv.reshape(2, 4), 1)
    assert ok.all()
    np.testing.assert_allclose(ends[0], np.stack([P1, P2]), atol=1e-9)
    # a line seen end-on (parallel to the rays) cannot be clipped
    Lp = g.plucker_from_point_dir(np.zeros(3), np.array([0, 0, 1.0]))
    obs = np.array([[320.0, 240, 320, 240]])
    _, ok = g.clip_to_observations(Lp[None], np.zeros(1, int), np.eye(4)[None], K, obs, 1)
    assert not ok.any()


def _scene_lines(rng, n):
    P1 = rng.uniform([-3, -3, 4], [3, 3, 8], (n, 3))
    P2 = P1 + rng.normal(size=(n, 3))
    return P1, P2


def test_triangulate_lines_two_and_multi_view(rng):
    n = 30
    P1, P2 = _scene_lines(rng, n)
    L_true = g.plucker_from_endpoints(P1, P2)
    T = np.stack([g.make_T(g.so3_exp(rng.normal(size=3) * 0.05), [0.4 * i, 0.1 * i, 0]) for i in range(4)])
    idx = np.repeat(np.arange(n), len(T))
    Tk = np.tile(T, (n, 1, 1))
    X = np.stack([P1[idx], P2[idx]], 1)
    uv, _ = g.project_points(K, Tk[:, None], X)
    obs = uv.reshape(-1, 4)
    L, ok = g.triangulate_lines(idx, Tk, K, obs, n)
    assert ok.all()
    assert g.line_distance(L, L_true).max() < 1e-8
    planes = g.observation_planes(Tk, K, obs)
    L2, sin = g.triangulate_line_two_view(planes[0::4], planes[3::4])
    assert g.line_distance(L2, L_true).max() < 1e-8 and (sin > 0).all()
    # with 0.5 px noise on the endpoints the lines stay close
    noisy = obs + rng.normal(scale=0.5, size=obs.shape)
    Ln, ok = g.triangulate_lines(idx, Tk, K, noisy, n)
    d_est, d_true = (L[ok, 3:] / np.linalg.norm(L[ok, 3:], axis=1, keepdims=True) for L in (Ln, L_true))
    assert np.median(g.line_angle_deg(d_est, d_true)) < 2.0
    # a single view, or a line lying along the baseline, is rejected
    _, ok1 = g.triangulate_lines(np.zeros(1, int), T[:1], K, obs[:1], 1)
    assert not ok1.any()
    Pb1, Pb2 = np.array([-2.0, 0.0, 5.0]), np.array([2.0, 0.0, 5.0])  # along the baseline (x axis)
    T_along = np.stack([np.eye(4), g.make_T(np.eye(3), [0.5, 0, 0])])
    uvb, _ = g.project_points(K, T_along[:, None], np.stack([Pb1, Pb2])[None].repeat(2, 0))
    _, okb = g.triangulate_lines(np.zeros(2, int), T_along, K, uvb.reshape(2, 4), 1)
    assert not okb.any()


def test_triangulate_points(rng):
    n = 40
    X = rng.uniform([-3, -3, 4], [3, 3, 8], (n, 3))
    T = np.stack([g.make_T(np.eye(3), [0.3 * i, 0, 0]) for i in range(3)])
    idx = np.repeat(np.arange(n), 3)
    Tk = np.tile(T, (n, 1, 1))
    uv, _ = g.project_points(K, Tk, X[idx])
    Xh, ok = g.triangulate_points(idx, Tk, K, uv, n)
    assert ok.all() and np.abs(Xh - X).max() < 1e-9
    # one observation only, and no parallax, are rejected
    Xh, ok = g.triangulate_points(np.zeros(2, int), np.stack([np.eye(4)] * 2), K, uv[:2] * 0 + 300, 1)
    assert not ok.any()


def test_a_point_on_a_camera_centre_is_refused():
    """Camera A looks through camera B's centre: its ray and B's meet just off B's centre, whatever B saw,
    with no reprojection error in either view and a wide angle between the observed rays. The midpoint is
    there; it is refused (a point that near B's centre would leave a BA indeterminate), a real point seen
    by the same cameras is not."""
    T = np.stack([np.eye(4), g.make_T(np.eye(3), [0.1, 0.0, 1.0])])
    ray_b = np.array([0.3, -0.2, 1.0]) / np.linalg.norm([0.3, -0.2, 1.0])
    X_bad = T[1, :3, 3] + 1e-4 * ray_b
    X_good = np.array([2.0, 0.5, 3.0])
    idx = np.array([0, 0, 1, 1])
    uv, _ = g.project_points(K, T[[0, 1, 0, 1]], np.stack([X_bad, X_bad, X_good, X_good]))
    Xh, ok = g.triangulate_points(idx, T[[0, 1, 0, 1]], K, uv, 2)
    np.testing.assert_allclose(Xh[0], X_bad, atol=1e-9)
    assert g.max_reprojection_px(idx, np.linalg.inv(T[[0, 1, 0, 1]]), K, uv, Xh)[0] < 1e-6
    assert ok.tolist() == [False, True]


def test_anchor_from_observation_meets_the_line(rng):
    T_wr = random_pose(rng)
    ends_c = np.array([[-1.0, 0.2, 4.0], [1.0, 0.4, 5.0]])
    ends = g.transform(T_wr, ends_c)
    uv, _ = g.project_points(K, np.stack([T_wr, T_wr]), ends)
    L = g.plucker_from_endpoints(*ends)
    b, r, sin = g.anchor_from_observation(uv.ravel(), K, T_wr, L)
    assert sin > 0.1 and r > 0
    # the ray through the observed midpoint meets the line at depth 1/r; anchoring it reproduces the line
    v = (ends[1] - ends[0]) / np.linalg.norm(ends[1] - ends[0])
    np.testing.assert_allclose(g.line_distance(g.anchored_plucker(v, r, b, T_wr), L), 0, atol=1e-9)
    # the observed midpoint is not the projection of the 3D midpoint (perspective), so z differs
    assert abs(1 / r - ends_c[:, 2].mean()) > 1e-3


def test_anchored_offset_reaches_any_parallel_line_and_jacobians(rng):
    """The 2-dof anchor (r, s): placed on a line that misses the observed-midpoint ray, it reproduces the
    line exactly; its Jacobians (v, (r, s), reference pose) match central differences."""
    T_wr = random_pose(rng)
    ends_c = np.array([[-1.0, 0.2, 4.0], [1.0, 0.4, 5.0]])
    ends = g.transform(T_wr, ends_c)
    uv, _ = g.project_points(K, np.stack([T_wr, T_wr]), ends)
    L = g.plucker_from_endpoints(*ends)
    v = L[3:] / np.linalg.norm(L[3:])
    noisy = uv.ravel() + np.array([0.0, 3.0, 0.0, 3.0])  # the reference observation is 3 px off
    b, _, _ = g.anchor_from_observation(noisy, K, T_wr, L)
    line_px = np.cross(np.append(noisy[:2], 1.0), np.append(noisy[2:], 1.0))
    q = g.anchor_offset_direction(line_px, K)
    assert q[2] == 0.0
    rs, sin = g.offset_anchor_on_line(b, q, T_wr, L)
    assert sin > 0.1 and rs[0] > 0 and abs(rs[1]) > 1.0  # about 3 px across
    np.testing.assert_allclose(g.line_distance(g.anchored_offset_plucker(v, rs, b, q, T_wr), L), 0, atol=1e-9)
    # the paper's one-dof anchor on that ray cannot: the best depth leaves a gap
    r_paper, _ = g.ray_inverse_depth(b, T_wr, L)
    assert g.line_distance(g.anchored_plucker(v, r_paper, b, T_wr), L) > 1e-3
    _, J_v, J_rs, J_xi = g.anchored_offset_plucker(v, rs, b, q, T_wr, jacobians=True)
    assert_jac(J_v, num_jac(lambda v_: g.anchored_offset_plucker(v_, rs, b, q, T_wr), v))
    assert_jac(J_rs, num_jac(lambda p: g.anchored_offset_plucker(v, p, b, q, T_wr), rs))
    assert_jac(J_xi, num_jac(lambda T_: g.anchored_offset_plucker(v, rs, b, q, T_), T_wr, g.retract, 6))
    # with s = 0 it is the paper's form
    np.testing.assert_allclose(
        g.anchored_offset_plucker(v, np.array([0.3, 0.0]), b, q, T_wr), g.anchored_plucker(v, 0.3, b, T_wr)
    )


def test_similarity_T_cw_keeps_what_the_camera_sees():
    """Moving the world by x -> s R x + t and the pose by similarity_T_cw scales camera coordinates by s."""
    from papl_mapper.geometry.se3 import similarity_T_cw, so3_exp

    rng = np.random.default_rng(3)
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = so3_exp(rng.normal(size=3)), rng.normal(size=3)
    R, t, s = so3_exp(rng.normal(size=3)), rng.normal(size=3), 1.7
    X = rng.normal(size=(5, 3))
    T2 = similarity_T_cw(T, R, t, s)
    np.testing.assert_allclose((s * X @ R.T + t) @ T2[:3, :3].T + T2[:3, 3], s * (X @ T[:3, :3].T + T[:3, 3]))


def test_similarity_T_cw_batched_equals_one_at_a_time():
    from papl_mapper.geometry.se3 import make_T, similarity_T_cw, so3_exp

    rng = np.random.default_rng(4)
    T = make_T(so3_exp(rng.normal(size=(6, 3))), rng.normal(size=(6, 3)))
    R, t, s = so3_exp(rng.normal(size=(6, 3))), rng.normal(size=(6, 3)), rng.uniform(0.5, 2.0, 6)
    batched = similarity_T_cw(T, R, t, s)
    for k in range(6):
        np.testing.assert_allclose(batched[k], similarity_T_cw(T[k], R[k], t[k], float(s[k])), atol=1e-12)


def test_max_reprojection_px_is_the_worst_view_and_inf_behind_a_camera():
    K = np.array([[500.0, 0, 320], [0, 500, 240], [0, 0, 1]])
    X = np.array([[0.0, 0, 5], [1.0, 0, 5]])
    behind = np.eye(4)
    behind[2, 3] = -10.0  # moves both points to z = -5
    T_cw = np.stack([np.eye(4), np.eye(4), np.eye(4), behind])
    index = np.array([0, 0, 1, 1])
    uv = np.array([[320.0, 240], [323, 244], [420, 240], [420, 240]])
    worst = g.max_reprojection_px(index, T_cw, K, uv, X)
    assert worst[0] == 5.0 and worst[1] == np.inf


@pytest.mark.parametrize("t_deg", [0.0, 1e-9, 1e-5, 0.3, 45.0, 89.9999, 90.0, 135.0, 179.99])
def test_line_angle_is_exact_at_any_angle_and_ignores_sign_and_length(t_deg: float) -> None:
    """The undirected angle between two directions, exact down to zero (an arccos of the cosine
    cannot resolve angles below about 1e-6 degrees)."""
    from papl_mapper.geometry.lines import line_angle_deg

    t = np.radians(t_deg)
    a = np.array([1.0, 0.0, 0.0])
    b = np.array([np.cos(t), np.sin(t), 0.0])
    expected = min(t_deg, 180.0 - t_deg)
    for aa, bb in ((a, b), (-a, b), (3.0 * a, 0.5 * b)):
        assert line_angle_deg(aa, bb) == pytest.approx(expected, rel=1e-9, abs=1e-12)
    assert line_angle_deg(np.stack([a, b]), b[None]).shape == (2,)


def test_rotation_alignment_recovers_a_common_rotation():
    from papl_mapper.geometry.se3 import rotation_alignment, rotation_angle_deg, so3_exp

    rng = np.random.default_rng(4)
    R_from = np.array([so3_exp(rng.normal(0, 1.0, 3)) for _ in range(20)])
    G = so3_exp(np.array([0.3, -1.2, 0.7]))
    R_to = np.array([so3_exp(rng.normal(0, 0.001, 3)) @ G @ R for R in R_from])  # 0.1 deg each
    assert rotation_angle_deg(rotation_alignment(R_from, R_to), G) < 0.05
    assert rotation_angle_deg(rotation_alignment(R_from, G @ R_from), G) < 1e-9
