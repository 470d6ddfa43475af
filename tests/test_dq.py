"""dqskin.dq against independent float64 oracles: SciPy rotations, 4x4 matrices, expm/logm."""

import numpy as np
import pytest
from scipy.linalg import expm, logm
from scipy.spatial.transform import Rotation

from dqskin import dq, dual, quat

BATCH = (3, 5)


def random_quats(rng, shape=BATCH):
    q = rng.normal(size=(*shape, 4))
    return q / np.linalg.norm(q, axis=-1, keepdims=True)


def rigid_matrix(q, t):
    """4x4 transforms [[R, t], [0, 1]] with R from SciPy (no dqskin code involved)."""
    shape = np.broadcast_shapes(np.shape(q)[:-1], np.shape(t)[:-1])
    xyzw = np.broadcast_to(q, (*shape, 4)).reshape(-1, 4)[:, [1, 2, 3, 0]]  # SciPy is scalar-last
    rot = Rotation.from_quat(xyzw)
    m = np.zeros((*shape, 4, 4))
    m[..., :3, :3] = rot.as_matrix().reshape(*shape, 3, 3)
    m[..., :3, 3] = np.broadcast_to(t, (*shape, 3))
    m[..., 3, 3] = 1
    return m


def random_poses(rng, shape=BATCH, scale=2.0):
    """Unit dual quaternions and their oracle matrices."""
    q = random_quats(rng, shape)
    t = scale * rng.normal(size=(*shape, 3))
    return dq.from_rt(q, t), rigid_matrix(q, t)


def hat(omega, v):
    """se(3) matrix [[S(omega), v], [0, 0]] ([MS] eq. 21, 23)."""
    x = np.zeros((4, 4))
    x[:3, :3] = [[0, -omega[2], omega[1]], [omega[2], 0, -omega[0]], [-omega[1], omega[0], 0]]
    x[:3, 3] = v
    return x


def apply_points(m, p):
    """Apply 4x4 matrices to 3-D points: (m @ [p, 1])[:3]."""
    return np.einsum("...ij,...j->...i", m[..., :3, :3], p) + m[..., :3, 3]


def same_pose(a, b, atol=1e-12):
    np.testing.assert_allclose(dq.to_matrix(a), dq.to_matrix(b), atol=atol)


def align(x, ref):
    """x with the sign that puts its real part in ref's hemisphere."""
    return np.where(np.sum(x[..., :4] * ref[..., :4], axis=-1, keepdims=True) < 0, -x, x)


# --- construction and conversion -------------------------------------------------------


def test_from_rt_to_matrix_matches_oracle():
    rng = np.random.default_rng(10)
    q = random_quats(rng)
    t = rng.normal(size=(*BATCH, 3))
    np.testing.assert_allclose(dq.to_matrix(dq.from_rt(q, t)), rigid_matrix(q, t), atol=1e-12)
    # from_rt normalizes q.
    np.testing.assert_allclose(dq.from_rt(4.0 * q, t), dq.from_rt(q, t), atol=1e-15)


def test_from_rotation_and_translation_compose_to_from_rt():
    rng = np.random.default_rng(11)
    q = random_quats(rng)
    t = rng.normal(size=(*BATCH, 3))
    composed = dq.mul(dq.from_translation(t), dq.from_rotation(q))
    np.testing.assert_allclose(composed, dq.from_rt(q, t), atol=1e-15)
    np.testing.assert_array_equal(dq.from_translation([2.0, 4, 6]), [1, 0, 0, 0, 0, 1, 2, 3])
    np.testing.assert_array_equal(dq.identity((2, 3))[1, 2], [1, 0, 0, 0, 0, 0, 0, 0])


def test_to_rt_round_trip_and_scale_invariance():
    rng = np.random.default_rng(12)
    q = random_quats(rng)
    t = rng.normal(size=(*BATCH, 3))
    x = dq.from_rt(q, t)
    q_out, t_out = dq.to_rt(x)
    np.testing.assert_allclose(q_out, q, atol=1e-15)
    np.testing.assert_allclose(t_out, t, atol=1e-14)
    q_scaled, t_scaled = dq.to_rt(-3.0 * x)
    np.testing.assert_allclose(q_scaled, -q, atol=1e-15)
    np.testing.assert_allclose(t_scaled, t, atol=1e-14)


def test_matrix_round_trips():
    rng = np.random.default_rng(13)
    x, m = random_poses(rng)
    y = dq.from_matrix(m)
    assert np.all(y[..., 0] >= 0)
    np.testing.assert_allclose(y, align(x, y), atol=1e-14)
    np.testing.assert_allclose(dq.to_matrix(y), m, atol=1e-12)


def test_mul_matches_matrix_product_with_broadcasting():
    rng = np.random.default_rng(14)
    a, ma = random_poses(rng)
    b, mb = random_poses(rng, (5,))
    np.testing.assert_allclose(dq.to_matrix(dq.mul(a, b)), ma @ mb, atol=1e-12)
    np.testing.assert_allclose(dq.mul(dq.identity(), a), a, atol=0)


def test_transform_point_and_vector_match_matrix():
    rng = np.random.default_rng(15)
    x, m = random_poses(rng)
    p = rng.normal(size=(*BATCH, 3))
    expected = apply_points(m, p)
    np.testing.assert_allclose(dq.transform_point(x, p), expected, atol=1e-12)
    np.testing.assert_allclose(dq.transform_point(2.5 * x, p), expected, atol=1e-12)
    np.testing.assert_allclose(
        dq.transform_vector(x, p), np.einsum("...ij,...j->...i", m[..., :3, :3], p), atol=1e-12
    )


# --- conjugates, norm, normalization, inverse ------------------------------------------


def test_three_conjugates():
    x = np.arange(1.0, 9.0)
    np.testing.assert_array_equal(dq.conjugate_quat(x), [1, -2, -3, -4, 5, -6, -7, -8])
    np.testing.assert_array_equal(dq.conjugate_dual(x), [1, 2, 3, 4, -5, -6, -7, -8])
    np.testing.assert_array_equal(dq.conjugate_both(x), [1, -2, -3, -4, -5, 6, 7, 8])
    rng = np.random.default_rng(16)
    a, b = rng.normal(size=(2, *BATCH, 8))
    expected = dq.mul(dq.conjugate_quat(b), dq.conjugate_quat(a))
    np.testing.assert_allclose(dq.conjugate_quat(dq.mul(a, b)), expected, atol=1e-12)


def test_point_transform_with_combined_conjugate():
    """[MS] eq. 18: 1 + eps p' = dq (1 + eps p) conjugate_both(dq)."""
    rng = np.random.default_rng(17)
    x, m = random_poses(rng)
    p = rng.normal(size=(*BATCH, 3))
    point = dq.from_translation(2 * p)  # 1 + eps p
    moved = dq.mul(dq.mul(x, point), dq.conjugate_both(x))
    np.testing.assert_allclose(moved[..., :5], np.eye(5)[0] + np.zeros((*BATCH, 5)), atol=1e-12)
    np.testing.assert_allclose(moved[..., 5:], dq.transform_point(x, p), atol=1e-12)


def test_norm_is_dual_number_and_multiplicative():
    rng = np.random.default_rng(18)
    x, _ = random_poses(rng)
    real, du = dq.norm(x)
    np.testing.assert_allclose(real, 1.0)
    np.testing.assert_allclose(du, 0.0, atol=1e-14)
    a, b = rng.normal(size=(2, *BATCH, 8))
    r, d = a[..., :4], a[..., 4:]
    real, du = dq.norm(a)
    np.testing.assert_allclose(real, np.linalg.norm(r, axis=-1))
    np.testing.assert_allclose(du, np.sum(r * d, -1) / np.linalg.norm(r, axis=-1))
    ab = dq.norm(dq.mul(a, b))
    expected = dual.mul(dq.norm(a), dq.norm(b))
    np.testing.assert_allclose(ab, expected, atol=1e-12)


def test_normalize_unit_plucker_idempotent_scaled():
    rng = np.random.default_rng(19)
    raw = rng.normal(size=(*BATCH, 8))
    n = dq.normalize(raw)
    np.testing.assert_allclose(np.linalg.norm(n[..., :4], axis=-1), 1.0)
    np.testing.assert_allclose(np.sum(n[..., :4] * n[..., 4:], -1), 0.0, atol=1e-14)
    np.testing.assert_allclose(dq.normalize(n), n, atol=1e-15)
    # The pose of a unit dual quaternion survives scaling: normalize(k x) = sign(k) x.
    x, m = random_poses(rng)
    k = rng.choice([-5.0, -0.3, 0.2, 7.0], size=(*BATCH, 1))
    np.testing.assert_allclose(dq.normalize(k * x), np.sign(k) * x, atol=1e-14)
    np.testing.assert_allclose(dq.to_matrix(dq.normalize(k * x)), m, atol=1e-12)
    # [MS] eq. 14 as a projection: only the component of d along r is removed.
    r, d = raw[..., :4], raw[..., 4:]
    nr = np.linalg.norm(r, axis=-1, keepdims=True)
    expected_d = d / nr - np.sum(r * d, -1, keepdims=True) * r / nr**3
    np.testing.assert_allclose(n[..., 4:], expected_d, atol=1e-12)
    # [MS] eq. 15.
    other = rng.normal(size=(*BATCH, 8))
    np.testing.assert_allclose(
        dq.normalize(dq.mul(raw, other)), dq.mul(dq.normalize(raw), dq.normalize(other)), atol=1e-12
    )


def test_inverse():
    rng = np.random.default_rng(20)
    raw = rng.normal(size=(*BATCH, 8))
    np.testing.assert_allclose(dq.mul(raw, dq.inverse(raw)), dq.identity(BATCH), atol=1e-12)
    np.testing.assert_allclose(dq.mul(dq.inverse(raw), raw), dq.identity(BATCH), atol=1e-12)
    x, m = random_poses(rng)
    np.testing.assert_allclose(dq.inverse_unit(x), dq.inverse(x), atol=1e-14)
    np.testing.assert_allclose(dq.to_matrix(dq.inverse_unit(x)), np.linalg.inv(m), atol=1e-12)


def test_dot_is_real_part_dot():
    rng = np.random.default_rng(21)
    a, b = rng.normal(size=(2, *BATCH, 8))
    np.testing.assert_allclose(dq.dot(a, b), np.sum(a[..., :4] * b[..., :4], -1))


# --- screw parameters and power --------------------------------------------------------


def test_screw_round_trip_and_geometry():
    rng = np.random.default_rng(22)
    x, m = random_poses(rng)
    theta, d, l, mom = dq.to_screw(x)
    np.testing.assert_allclose(dq.from_screw(theta, d, l, mom), x, atol=1e-12)
    np.testing.assert_allclose(np.linalg.norm(l, axis=-1), 1.0)
    np.testing.assert_allclose(np.sum(l * mom, -1), 0.0, atol=1e-12)
    # Independent geometry: R l = l, the rotation angle matches, and the axis
    # point p = l x m moves by d along the axis.
    rot = m[..., :3, :3]
    np.testing.assert_allclose(np.einsum("...ij,...j->...i", rot, l), l, atol=1e-12)
    cos_angle = (np.trace(rot, axis1=-2, axis2=-1) - 1) / 2
    np.testing.assert_allclose(np.cos(theta), cos_angle, atol=1e-12)
    p = np.cross(l, mom)
    moved = apply_points(m, p)
    np.testing.assert_allclose(moved, p + d[..., None] * l, atol=1e-10)
    # -dq is the same screw: (2 pi - theta, -d, -l, -m).
    neg = dq.to_screw(-x)
    for got, want in zip(neg, (2 * np.pi - theta, -d, -l, -mom)):
        np.testing.assert_allclose(got, want, atol=1e-11)


def test_screw_of_pure_translation_and_identity():
    t = np.array([[0.0, 3.0, 4.0], [0.0, 0.0, 0.0]])
    theta, d, l, mom = dq.to_screw(dq.from_translation(t))
    np.testing.assert_array_equal(theta, [0, 0])
    np.testing.assert_allclose(d, [5, 0])
    np.testing.assert_allclose(l, [[0, 0.6, 0.8], [1, 0, 0]])
    np.testing.assert_array_equal(mom, np.zeros((2, 3)))
    np.testing.assert_allclose(dq.from_screw(theta, d, l, mom), dq.from_translation(t), atol=1e-15)
    # Full turn (rw = -1): theta = 2 pi with d >= 0.
    theta, d, l, mom = dq.to_screw(-dq.from_translation(t[0]))
    np.testing.assert_allclose([theta, d], [2 * np.pi, 5])
    np.testing.assert_allclose(l, [0, 0.6, 0.8])


def test_power():
    rng = np.random.default_rng(23)
    x, _ = random_poses(rng)
    np.testing.assert_array_equal(dq.power(x, 0.0), dq.identity(BATCH))
    np.testing.assert_allclose(dq.power(x, 1.0), x, atol=1e-12)
    np.testing.assert_allclose(dq.power(x, 2.0), dq.mul(x, x), atol=1e-11)
    np.testing.assert_allclose(dq.power(x, -1.0), dq.inverse_unit(x), atol=1e-11)
    half = dq.power(x, 0.5)
    np.testing.assert_allclose(dq.mul(half, half), x, atol=1e-12)
    t = rng.uniform(-1.5, 1.5, size=BATCH)
    np.testing.assert_allclose(dq.power(x, t), dq.exp(t[..., None] * dq.log(x)), atol=1e-11)


# --- exp / log ------------------------------------------------------------------------


def test_exp_twist_matches_matrix_expm():
    rng = np.random.default_rng(24)
    omega = rng.normal(size=(*BATCH, 3))
    v = rng.normal(size=(*BATCH, 3))
    pairs = zip(omega.reshape(-1, 3), v.reshape(-1, 3))
    expected = np.array([expm(hat(w_, v_)) for w_, v_ in pairs])
    got = dq.to_matrix(dq.exp_twist(omega, v)).reshape(-1, 4, 4)
    np.testing.assert_allclose(got, expected, atol=1e-12)
    xi = np.concatenate([np.zeros((*BATCH, 1)), omega / 2, np.zeros((*BATCH, 1)), v / 2], -1)
    np.testing.assert_allclose(dq.exp(xi), dq.exp_twist(omega, v), atol=0)


def test_log_matches_matrix_logm():
    rng = np.random.default_rng(25)
    x, m = random_poses(rng)
    x = align(x, dq.identity())  # rotation angle < pi: the principal branch of logm
    ours = dq.log(x)
    np.testing.assert_allclose(ours[..., [0, 4]], 0.0, atol=1e-14)
    for got, mat in zip(ours.reshape(-1, 8), m.reshape(-1, 4, 4)):
        ref = logm(mat).real
        omega = np.array([ref[2, 1], ref[0, 2], ref[1, 0]])
        np.testing.assert_allclose(got[1:4], omega / 2, atol=1e-10)
        np.testing.assert_allclose(got[5:8], ref[:3, 3] / 2, atol=1e-10)


def test_exp_log_inverse_pairs():
    rng = np.random.default_rng(26)
    raw = rng.normal(size=(*BATCH, 8))  # general, non-unit
    np.testing.assert_allclose(dq.exp(dq.log(raw)), raw, atol=1e-12)
    x, _ = random_poses(rng)
    np.testing.assert_allclose(dq.exp(dq.log(x)), x, atol=1e-12)
    np.testing.assert_allclose(dq.exp(dq.log(-x)), -x, atol=1e-12)
    # log(exp xi) = xi for vector xi with half-angle |xi_r| < pi.
    direction = rng.normal(size=(*BATCH, 3))
    direction /= np.linalg.norm(direction, axis=-1, keepdims=True)
    half = rng.uniform(0.0, 3.1, size=(*BATCH, 1))
    zero = np.zeros((*BATCH, 1))
    xi = np.concatenate([zero, half * direction, zero, rng.normal(size=(*BATCH, 3))], -1)
    np.testing.assert_allclose(dq.log(dq.exp(xi)), xi, atol=1e-11)
    # exp with scalar parts multiplies by the central dual number e^a (1 + eps b).
    xi_s = xi.copy()
    xi_s[..., 0], xi_s[..., 4] = 0.3, -0.7
    np.testing.assert_allclose(dq.exp(xi_s)[..., :4], np.exp(0.3) * dq.exp(xi)[..., :4], atol=1e-12)


def test_log_singular_points():
    np.testing.assert_array_equal(dq.log(dq.identity((2,))), np.zeros((2, 8)))
    y = np.array([0.0, 3.0, 4.0])
    full_turn = np.concatenate([[-1.0, 0, 0, 0, 0], y])  # -1 + eps y
    out = dq.log(full_turn)
    np.testing.assert_allclose(out, [0, 0, -0.6 * np.pi, -0.8 * np.pi, 0, 0, -3, -4], atol=1e-15)
    np.testing.assert_allclose(dq.exp(out), full_turn, atol=1e-12)
    np.testing.assert_allclose(dq.log(-dq.identity()), [0, np.pi, 0, 0, 0, 0, 0, 0])
    with pytest.raises(ValueError, match="zero"):
        dq.log(np.zeros(8))
    with pytest.raises(ValueError, match="zero"):
        dq.normalize(np.array([[1.0, 0, 0, 0, 0, 0, 0, 0], [0, 0, 0, 0, 1, 0, 0, 0]]))
    with pytest.raises(ValueError, match="zero"):
        dq.inverse(np.zeros((3, 8)))


# --- interpolation and blending -----------------------------------------------------------


def test_sclerp_matches_matrix_screw_interpolation():
    rng = np.random.default_rng(27)
    a, ma = random_poses(rng)
    b, mb = random_poses(rng)
    t = np.array([0.0, 0.25, 0.6, 1.0])[:, None, None]
    ours = dq.sclerp(a, b, t)
    assert ours.shape == (4, *BATCH, 8)
    got = dq.to_matrix(ours)
    for i in range(BATCH[0]):
        for j in range(BATCH[1]):
            rel = logm(np.linalg.inv(ma[i, j]) @ mb[i, j]).real
            for k, tk in enumerate(t[:, 0, 0]):
                np.testing.assert_allclose(got[k, i, j], ma[i, j] @ expm(tk * rel), atol=1e-10)


def test_sclerp_endpoints_and_shortest_path():
    rng = np.random.default_rng(28)
    a, _ = random_poses(rng)
    b, _ = random_poses(rng)
    np.testing.assert_array_equal(dq.sclerp(a, b, 0.0), dq.normalize(a))
    np.testing.assert_allclose(dq.sclerp(a, b, 0.0), a, atol=1e-15)
    np.testing.assert_allclose(dq.sclerp(a, b, 1.0), align(b, a), atol=1e-12)
    t = np.linspace(0, 1, 5)[:, None, None]
    np.testing.assert_allclose(dq.sclerp(a, -b, t), dq.sclerp(a, b, t), atol=1e-15)
    np.testing.assert_allclose(dq.sclerp(3.0 * a, b, t), dq.sclerp(a, b, t), atol=1e-12)


def test_sclerp_equals_power_and_exp_log_forms():
    rng = np.random.default_rng(29)
    a, _ = random_poses(rng)
    b, _ = random_poses(rng)
    b = align(b, a)
    t = rng.uniform(0, 1, size=BATCH)
    rel = dq.mul(dq.inverse_unit(a), b)
    ours = dq.sclerp(a, b, t)
    np.testing.assert_allclose(ours, dq.mul(a, dq.power(rel, t)), atol=1e-12)
    np.testing.assert_allclose(ours, dq.mul(a, dq.exp(t[..., None] * dq.log(rel))), atol=1e-11)
    # [MS] eq. 41, second form.
    np.testing.assert_allclose(
        ours, dq.mul(dq.exp(t[..., None] * dq.log(dq.mul(b, dq.inverse_unit(a)))), a), atol=1e-11
    )


def test_sclerp_constant_speed():
    rng = np.random.default_rng(30)
    a, _ = random_poses(rng)
    b, _ = random_poses(rng)
    t = np.linspace(0, 1, 9)
    path = dq.sclerp(a, b, t[:, None, None])
    mats = dq.to_matrix(path)
    steps = np.linalg.inv(mats[:-1]) @ mats[1:]
    np.testing.assert_allclose(steps, np.broadcast_to(steps[0], steps.shape), atol=1e-10)
    theta, d, _, _ = dq.to_screw(dq.mul(dq.inverse_unit(a), path))
    np.testing.assert_allclose(theta, t[:, None, None] * theta[-1], atol=1e-10)
    np.testing.assert_allclose(d, t[:, None, None] * d[-1], atol=1e-10)
    assert np.all(theta[-1] <= np.pi + 1e-12)  # shorter of the two screw motions


def test_sclerp_between_pure_translations_is_linear():
    t0, t1 = np.array([1.0, 2.0, 3.0]), np.array([-2.0, 0.0, 5.0])
    s = np.linspace(0, 1, 4)[:, None]
    path = dq.sclerp(dq.from_translation(t0), dq.from_translation(t1), s[:, 0])
    np.testing.assert_allclose(dq.to_rt(path)[1], t0 + s * (t1 - t0), atol=1e-14)
    np.testing.assert_allclose(dq.to_rt(path)[0], quat.identity(4), atol=1e-15)


def test_nlerp():
    rng = np.random.default_rng(31)
    a, _ = random_poses(rng)
    b, _ = random_poses(rng)
    np.testing.assert_allclose(dq.nlerp(a, b, 0.0), a, atol=1e-15)
    np.testing.assert_allclose(dq.nlerp(a, b, 1.0), align(b, a), atol=1e-14)
    mid = dq.nlerp(a, -b, 0.5)
    np.testing.assert_allclose(mid, dq.nlerp(a, b, 0.5), atol=1e-15)
    np.testing.assert_allclose(dq.norm(mid)[0], 1.0)
    np.testing.assert_allclose(dq.norm(mid)[1], 0.0, atol=1e-14)
    # Rotations about one axis: nlerp at 1/2 bisects the angle.
    z = np.array([0.0, 0.0, 1.0])
    start, end = dq.from_rotation(quat.from_axis_angle(z, [0.2, 1.4]))
    out = dq.nlerp(start, end, 0.5)
    np.testing.assert_allclose(out, dq.from_rotation(quat.from_axis_angle(z, 0.8)), atol=1e-15)


def test_dlb_single_and_dominant_input():
    rng = np.random.default_rng(32)
    x, _ = random_poses(rng, (*BATCH, 1))
    np.testing.assert_allclose(dq.dlb(x, np.full((*BATCH, 1), 0.7)), x[..., 0, :], atol=1e-15)
    y, _ = random_poses(rng, (*BATCH, 3))
    weights = np.array([0.0, 1.0, 0.0])
    np.testing.assert_allclose(dq.dlb(y, weights), y[..., 1, :], atol=1e-15)


def test_dlb_sign_invariance():
    rng = np.random.default_rng(33)
    y, _ = random_poses(rng, (*BATCH, 4))
    weights = rng.dirichlet(np.ones(4), size=BATCH)
    ref = dq.dlb(y, weights)
    pivot = np.argmax(weights, axis=-1)
    for k in range(4):
        flipped = y.copy()
        flipped[..., k, :] *= -1
        expected = np.where((pivot == k)[..., None], -ref, ref)
        np.testing.assert_allclose(dq.dlb(flipped, weights), expected, atol=1e-14)
        same_pose(dq.dlb(flipped, weights), ref)


def test_dlb_closed_forms():
    # Same-axis rotations blend to the weighted angle bisector when equally weighted.
    z = np.array([0.0, 0.0, 1.0])
    angles = np.array([[0.3, 2.9], [-1.0, 2.0]])
    rots = dq.from_rotation(quat.from_axis_angle(z, angles))
    out = dq.dlb(rots, [0.5, 0.5])
    expected = dq.from_rotation(quat.from_axis_angle(z, angles.mean(-1)))
    np.testing.assert_allclose(out, expected, atol=1e-15)
    # Pure translations blend to the normalized weighted mean translation.
    rng = np.random.default_rng(34)
    t = rng.normal(size=(*BATCH, 3, 3))
    w = rng.uniform(0.1, 1.0, size=(*BATCH, 3))
    out = dq.dlb(dq.from_translation(t), w)
    expected = np.sum(w[..., None] * t, -2) / np.sum(w, -1, keepdims=True)
    np.testing.assert_allclose(dq.to_rt(out)[1], expected, atol=1e-14)
    with pytest.raises(ValueError, match="zero"):
        dq.dlb(rots, [0.0, 0.0])


# --- kinematics -------------------------------------------------------------------------


def _finite_difference(poses_at, time, h=1e-6):
    """Pose dual quaternion and its central-difference derivative, signs kept continuous."""
    eta = dq.from_matrix(poses_at(time))
    before = align(dq.from_matrix(poses_at(time - h)), eta)
    after = align(dq.from_matrix(poses_at(time + h)), eta)
    return eta, (after - before) / (2 * h)


@pytest.mark.parametrize("frame", ["body", "spatial"])
def test_twist_matches_matrix_motion(frame):
    rng = np.random.default_rng(35)
    _, m0 = random_poses(rng, (4,))
    omega = rng.normal(size=(4, 3))
    v = rng.normal(size=(4, 3))
    xi = np.array([hat(w_, v_) for w_, v_ in zip(omega, v)])

    def poses_at(time):
        motion = np.array([expm(time * x) for x in xi])
        return m0 @ motion if frame == "body" else motion @ m0  # [MS] eq. 23 / fixed frame

    eta, eta_dot = _finite_difference(poses_at, 0.4)
    w_out, v_out = dq.twist(eta, eta_dot, frame=frame)
    np.testing.assert_allclose(w_out, omega, atol=1e-7)
    np.testing.assert_allclose(v_out, v, atol=1e-7)


def test_exp_twist_has_constant_body_twist():
    rng = np.random.default_rng(36)
    x0, _ = random_poses(rng, (4,))
    omega, v = rng.normal(size=(2, 4, 3))
    h, time = 1e-6, 0.7
    eta = dq.mul(x0, dq.exp_twist(time * omega, time * v))
    eta_dot = (dq.mul(x0, dq.exp_twist((time + h) * omega, (time + h) * v))
               - dq.mul(x0, dq.exp_twist((time - h) * omega, (time - h) * v))) / (2 * h)
    w_out, v_out = dq.twist(eta, eta_dot)
    np.testing.assert_allclose(w_out, omega, atol=1e-7)
    np.testing.assert_allclose(v_out, v, atol=1e-7)
    with pytest.raises(ValueError, match="frame"):
        dq.twist(eta, eta_dot, frame="world")


def test_wrench_power():
    """[MS] eq. 27, 30: wrench . (omega/2 + eps v/2) = torque . omega + force . v."""
    rng = np.random.default_rng(37)
    torque, force, omega, v = rng.normal(size=(4, *BATCH, 3))
    tau = dq.wrench(torque, force)
    np.testing.assert_array_equal(tau[..., 1:4], 2 * torque)
    np.testing.assert_array_equal(tau[..., 5:8], 2 * force)
    np.testing.assert_array_equal(tau[..., [0, 4]], 0)
    phi = np.concatenate([np.zeros((*BATCH, 1)), omega / 2, np.zeros((*BATCH, 1)), v / 2], -1)
    power = np.sum(torque * omega + force * v, -1)
    np.testing.assert_allclose(np.sum(tau * phi, -1), power, atol=1e-12)


def test_lie_difference():
    rng = np.random.default_rng(38)
    a, _ = random_poses(rng)
    b, _ = random_poses(rng)
    diff = dq.lie_difference(a, b)
    np.testing.assert_allclose(dq.mul(a, dq.exp(diff)), b, atol=1e-11)
    # First-order agreement with [MS] eq. 37, Im(a* b), for nearby poses.
    small = 1e-4 * rng.normal(size=(*BATCH, 8))
    small[..., [0, 4]] = 0
    near = dq.mul(a, dq.exp(small))
    approx = dq.mul(dq.conjugate_quat(a), near)
    approx[..., [0, 4]] = 0
    np.testing.assert_allclose(dq.lie_difference(a, near), small, atol=1e-14)
    np.testing.assert_allclose(approx, small, atol=1e-10)


# --- dtypes and shapes -------------------------------------------------------------------


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_dtype_preserved(dtype):
    rng = np.random.default_rng(39)
    x, m = random_poses(rng)
    x, m = x.astype(dtype), m.astype(dtype)
    y = x[::-1]
    q = x[..., :4]
    p = rng.normal(size=3).astype(dtype)
    results = [
        dq.identity(BATCH, dtype), dq.mul(x, y), dq.conjugate_quat(x), dq.conjugate_dual(x),
        dq.conjugate_both(x), *dq.norm(x), dq.normalize(x), dq.inverse(x), dq.inverse_unit(x),
        dq.dot(x, y), dq.from_rotation(q), dq.from_translation(p), dq.from_rt(q, p), *dq.to_rt(x),
        dq.from_matrix(m), dq.to_matrix(x), dq.transform_point(x, p), dq.transform_vector(x, p),
        *dq.to_screw(x), dq.from_screw(0.5, 0.1, p, p), dq.power(x, 0.3), dq.sclerp(x, y, 0.3),
        dq.nlerp(x, y, 0.3), dq.dlb(x, np.ones(5)), dq.exp(x), dq.log(x), dq.exp_twist(p, p),
        dq.lie_difference(x, y), *dq.twist(x, y), dq.wrench(p, p),
    ]
    bad = [i for i, r in enumerate(results) if r.dtype != dtype]
    assert not bad


def test_float32_accuracy():
    rng = np.random.default_rng(40)
    x, m = random_poses(rng)
    x32 = x.astype(np.float32)
    np.testing.assert_allclose(dq.to_matrix(x32), m, atol=1e-5)
    expected = dq.sclerp(x, x[::-1], 0.5)
    np.testing.assert_allclose(dq.sclerp(x32, x32[::-1], 0.5), expected, atol=1e-5)


def test_integers_compute_in_float64():
    out = dq.mul([1, 0, 0, 0, 0, 1, 0, 0], [1, 0, 0, 0, 0, 0, 1, 0])
    assert out.dtype == np.float64
    assert dq.from_translation([1, 2, 3]).dtype == np.float64


@pytest.mark.parametrize(
    "call, name",
    [
        (lambda: dq.mul(np.ones((3, 8)), np.ones((3, 4))), "b"),
        (lambda: dq.normalize(np.ones((8, 3))), "dq"),
        (lambda: dq.from_rt(np.ones(4), np.ones(4)), "t"),
        (lambda: dq.from_rt(np.ones(3), np.ones(3)), "q"),
        (lambda: dq.from_matrix(np.eye(3)), "m"),
        (lambda: dq.transform_point(np.ones(8), np.ones(4)), "p"),
        (lambda: dq.sclerp(np.ones(8), np.ones(7), 0.5), "b"),
        (lambda: dq.dlb(np.ones(8), np.ones(1)), "dqs"),
        (lambda: dq.dlb(np.ones((2, 8)), np.ones(3)), "weights"),
        (lambda: dq.from_screw(0.0, 0.0, np.ones(4), np.ones(3)), "l"),
        (lambda: dq.twist(np.ones(7), np.ones(8)), "eta"),
        (lambda: dq.lie_difference(np.ones(6), np.ones(8)), "a"),
        (lambda: dq.wrench(np.ones(3), np.ones(2)), "force"),
    ],
)
def test_wrong_shapes_raise(call, name):
    with pytest.raises(ValueError, match=rf"^{name} must have shape"):
        call()
