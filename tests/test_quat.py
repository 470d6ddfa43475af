"""dqskin.quat against SciPy's Rotation (an independent float64 implementation)."""

import numpy as np
import pytest
from scipy.spatial.transform import Rotation, Slerp

from dqskin import quat

BATCH = (3, 5)


def random_quats(rng, shape=BATCH):
    q = rng.normal(size=(*shape, 4))
    return q / np.linalg.norm(q, axis=-1, keepdims=True)


def scipy_matrix(q):
    """Rotation matrices of (w, x, y, z) quaternions, computed by SciPy (scalar-last)."""
    flat = np.asarray(q, dtype=np.float64).reshape(-1, 4)
    return Rotation.from_quat(flat[:, [1, 2, 3, 0]]).as_matrix().reshape(*np.shape(q)[:-1], 3, 3)


def same_rotation(a, b, atol=1e-12):
    """Quaternions equal up to the sign ambiguity q ~ -q."""
    sign = np.where(np.sum(a * b, axis=-1, keepdims=True) < 0, -1, 1)
    np.testing.assert_allclose(a, sign * b, atol=atol)


def test_to_matrix_matches_scipy_also_for_unnormalized_input():
    rng = np.random.default_rng(0)
    q = random_quats(rng)
    np.testing.assert_allclose(quat.to_matrix(q), scipy_matrix(q), atol=1e-12)
    np.testing.assert_allclose(quat.to_matrix(3.7 * q), scipy_matrix(q), atol=1e-12)


def test_mul_is_composition_apply_right_first():
    rng = np.random.default_rng(1)
    a, b = random_quats(rng), random_quats(rng, (5,))
    expected = scipy_matrix(a) @ scipy_matrix(b)
    np.testing.assert_allclose(quat.to_matrix(quat.mul(a, b)), expected, atol=1e-12)


def test_mul_hamilton_basis():
    i, j, k = np.eye(4)[1], np.eye(4)[2], np.eye(4)[3]
    np.testing.assert_array_equal(quat.mul(i, j), k)
    np.testing.assert_array_equal(quat.mul(j, i), -k)
    np.testing.assert_array_equal(quat.mul(i, i), [-1, 0, 0, 0])


def test_rotate_matches_scipy_apply():
    rng = np.random.default_rng(2)
    q = random_quats(rng)
    v = rng.normal(size=(*BATCH, 3))
    expected = np.einsum("...ij,...j->...i", scipy_matrix(q), v)
    np.testing.assert_allclose(quat.rotate(q, v), expected, atol=1e-12)
    np.testing.assert_allclose(quat.rotate(-2.5 * q, v), expected, atol=1e-12)


def test_inverse_conjugate_norm_dot():
    rng = np.random.default_rng(3)
    q = 2.0 * random_quats(rng)
    np.testing.assert_allclose(quat.mul(q, quat.inverse(q)), quat.identity(BATCH), atol=1e-12)
    np.testing.assert_allclose(quat.norm(q), 2.0)
    np.testing.assert_allclose(quat.dot(q, q), 4.0)
    np.testing.assert_array_equal(quat.conjugate(q)[..., 1:], -q[..., 1:])
    np.testing.assert_allclose(quat.norm(quat.normalize(q)), 1.0)


def test_axis_angle_matches_scipy_rotvec_and_round_trips():
    rng = np.random.default_rng(4)
    axis = rng.normal(size=(*BATCH, 3))
    angle = rng.uniform(-3.0, 3.0, size=BATCH)
    q = quat.from_axis_angle(axis, angle)
    unit = axis / np.linalg.norm(axis, axis=-1, keepdims=True)
    rotvec = (unit * angle[..., None]).reshape(-1, 3)
    expected = Rotation.from_rotvec(rotvec).as_matrix()
    np.testing.assert_allclose(quat.to_matrix(q).reshape(-1, 3, 3), expected, atol=1e-12)
    out_axis, out_angle = quat.to_axis_angle(q)
    assert np.all((out_angle >= 0) & (out_angle <= np.pi))
    np.testing.assert_allclose(out_axis * out_angle[..., None], unit * angle[..., None], atol=1e-12)
    neg_axis, neg_angle = quat.to_axis_angle(-q)
    np.testing.assert_allclose(neg_angle, out_angle, atol=1e-12)
    np.testing.assert_allclose(neg_axis, out_axis, atol=1e-12)


def test_from_matrix_round_trip_all_branches():
    rng = np.random.default_rng(5)
    q = random_quats(rng)
    # Angles at and near pi (trace near -1) exercise the non-trace branches.
    axis = rng.normal(size=(4, 3))
    near_pi = quat.from_axis_angle(axis, [np.pi, np.pi - 1e-9, np.pi, 1e-9])
    for q_in in (q, near_pi):
        m = scipy_matrix(q_in)
        q_out = quat.from_matrix(m)
        assert np.all(q_out[..., 0] >= 0)
        same_rotation(q_out, q_in)
        np.testing.assert_allclose(quat.to_matrix(q_out), m, atol=1e-12)
    m4 = np.zeros((*BATCH, 4, 4))
    m4[..., :3, :3] = scipy_matrix(q)
    m4[..., :3, 3] = 7.0
    same_rotation(quat.from_matrix(m4), q)


def test_exp_log():
    rng = np.random.default_rng(6)
    q = 1.7 * random_quats(rng)
    np.testing.assert_allclose(quat.exp(quat.log(q)), q, atol=1e-12)
    pure = np.zeros((*BATCH, 4))
    direction = rng.normal(size=(*BATCH, 3))
    direction /= np.linalg.norm(direction, axis=-1, keepdims=True)
    half = rng.uniform(0.0, 3.1, size=BATCH)
    pure[..., 1:] = direction * half[..., None]
    np.testing.assert_allclose(quat.log(quat.exp(pure)), pure, atol=1e-12)
    # exp of the pure quaternion theta a is the rotation by 2 theta about a.
    expected = Rotation.from_rotvec((2 * pure[..., 1:]).reshape(-1, 3)).as_matrix()
    got = quat.to_matrix(quat.exp(pure)).reshape(-1, 3, 3)
    np.testing.assert_allclose(got, expected, atol=1e-12)


def test_slerp_matches_scipy_and_takes_shortest_path():
    rng = np.random.default_rng(7)
    q0, q1 = random_quats(rng, (6,)), random_quats(rng, (6,))
    t = np.linspace(0.0, 1.0, 5)
    ours = quat.slerp(q0, q1, t[:, None])
    assert ours.shape == (5, 6, 4)
    for k in range(6):
        key = Rotation.from_quat(np.stack([q0[k], q1[k]])[:, [1, 2, 3, 0]])
        expected = Slerp([0.0, 1.0], key)(t).as_matrix()
        np.testing.assert_allclose(quat.to_matrix(ours[:, k]), expected, atol=1e-12)
    np.testing.assert_allclose(quat.slerp(q0, -q1, t[:, None]), ours, atol=1e-15)
    np.testing.assert_allclose(ours[0], q0, atol=1e-15)
    same_rotation(ours[-1], q1)
    # [K] eq. 16: q0 (q0* q1)^t, with q1 in q0's hemisphere.
    q1_near = np.where(quat.dot(q0, q1)[..., None] < 0, -q1, q1)
    rel_log = quat.log(quat.mul(quat.conjugate(q0), q1_near))
    eq16 = quat.mul(q0, quat.exp(t[:, None, None] * rel_log))
    np.testing.assert_allclose(ours, eq16, atol=1e-12)


def test_slerp_of_equal_quaternions_is_finite():
    q = random_quats(np.random.default_rng(8))
    np.testing.assert_allclose(quat.slerp(q, q, 0.3), q, atol=1e-15)


def test_singular_points():
    with pytest.raises(ValueError, match="zero"):
        quat.normalize(np.zeros((2, 4)))
    with pytest.raises(ValueError, match="zero"):
        quat.inverse([[1.0, 0, 0, 0], [0, 0, 0, 0]])
    with pytest.raises(ValueError, match="zero"):
        quat.from_axis_angle([0.0, 0, 0], 1.0)
    axis, angle = quat.to_axis_angle(quat.identity((2,)))
    np.testing.assert_array_equal(axis, [[1, 0, 0], [1, 0, 0]])
    np.testing.assert_array_equal(angle, [0, 0])
    np.testing.assert_allclose(quat.log([-2.0, 0, 0, 0]), [np.log(2.0), np.pi, 0, 0])
    np.testing.assert_array_equal(quat.log(quat.identity()), np.zeros(4))


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_dtype_preserved(dtype):
    rng = np.random.default_rng(9)
    q = random_quats(rng).astype(dtype)
    v = rng.normal(size=3).astype(dtype)
    m = scipy_matrix(q).astype(dtype)
    results = [
        quat.mul(q, q), quat.conjugate(q), quat.inverse(q), quat.dot(q, q), quat.norm(q),
        quat.normalize(q), quat.rotate(q, v), quat.from_axis_angle(v, 0.5), *quat.to_axis_angle(q),
        quat.from_matrix(m), quat.to_matrix(q), quat.exp(q), quat.log(q),
        quat.slerp(q, q[::-1], 0.25),
        quat.identity(BATCH, dtype),
    ]
    assert all(r.dtype == dtype for r in results)


def test_integers_compute_in_float64():
    assert quat.mul([1, 0, 0, 0], [0, 1, 0, 0]).dtype == np.float64
    assert quat.rotate([0, 0, 0, 1], [1, 0, 0]).dtype == np.float64


@pytest.mark.parametrize(
    "call, name",
    [
        (lambda: quat.mul(np.ones((3, 4)), np.ones((3, 3))), "b"),
        (lambda: quat.rotate(np.ones(4), np.ones((2, 4))), "v"),
        (lambda: quat.normalize(np.ones((4, 3))), "q"),
        (lambda: quat.from_matrix(np.eye(3)[:, :2]), "m"),
        (lambda: quat.from_axis_angle(np.ones(4), 1.0), "axis"),
        (lambda: quat.slerp(np.ones(4), np.ones(5), 0.5), "q1"),
    ],
)
def test_wrong_shapes_raise(call, name):
    with pytest.raises(ValueError, match=rf"^{name} must have shape"):
        call()
