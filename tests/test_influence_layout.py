"""The one influence layout (:class:`dqskin.influences.Influences` →
:class:`dqskin.kernels.layout.InfluenceLayout`): skinning through the packed layout equals float64
NumPy skinning written from the equations over the raw (V, K) arrays; padding slots weigh
nothing; concatenated meshes land at their vertex and joint offsets; one joint-range check."""

import numpy as np
import pytest
import warp as wp
from scipy.spatial.transform import Rotation
from test_sign_reference import dqs_reference

import dqskin
from dqskin.errors import InputError
from dqskin.influences import Influences, check_influences, check_joint_range
from dqskin.kernels import skin as K
from dqskin.kernels.dqmath import mat34, vec8


def rig(rng, V, K_, J=10):
    points = rng.normal(size=(V, 3))
    idx = rng.integers(0, J, size=(V, K_))
    w = rng.random((V, K_))
    w[:, 0] *= 3.0  # an input slot other than the largest weight's, sometimes
    if K_ > 1:
        w[::5, -1] = 0.0  # (every vertex keeps a weight: a zero blend has no DQS reference)
    M = np.tile(np.eye(4), (J, 1, 1))
    M[:, :3, :3] = Rotation.random(J, random_state=rng).as_matrix()
    M[:, :3, 3] = rng.normal(size=(J, 3))
    return points, idx, w, M


def lbs64(points, idx, w, M):
    """``Σ wᵢ·Mᵢ·[p, 1]`` in float64, weights as given."""
    ph = np.concatenate([points, np.ones((len(points), 1))], 1)
    return np.einsum("vk,vkij,vj->vi", w, M[idx], ph)[:, :3]


def empty(dtype, device):
    return wp.empty(0, dtype=dtype, device=device)


def skin_through_layout(layout, points, M, method, device):
    """The point kernels on ``layout``, one frame, nothing else of dqskin's API."""
    J = len(M)
    xf = wp.array(M[None].astype(np.float32), dtype=wp.mat44, device=device)
    joints = K.joints(affines=wp.empty((1, J), dtype=mat34, device=device),
                      dqs=wp.empty((1, J), dtype=vec8, device=device),
                      residuals=wp.empty((1, J), dtype=wp.mat33, device=device),
                      has_residual=wp.zeros(1, dtype=wp.int32, device=device))
    K.prepare_points(xforms=xf, joints=joints, device=device)
    out = wp.empty((1, len(points)), dtype=wp.vec3, device=device)
    src = wp.array(points[None].astype(np.float32), dtype=wp.vec3, device=device)
    K.skin_points(method=method, points=src, influences=layout, joints=joints, rigid=True,
                  out=out, device=device)
    return out.numpy()[0]


@pytest.mark.parametrize("K_", [1, 3, 4, 5, 8])
@pytest.mark.parametrize("order,rule", [("weight", "largest_weight"),
                                        ("input", "largest_weight"),
                                        ("input", "running_sum")])
def test_packed_layout_skins_as_float64_numpy(device, K_, order, rule):
    rng = np.random.default_rng(10 * K_ + len(order) + len(rule))
    points, idx, w, M = rig(rng, 301, K_)
    inf = Influences(idx, w)
    layout = inf.layout(device, order, blend=empty(float, device),
                        centers=empty(wp.vec4, device), running_sum=rule == "running_sum")
    assert (layout.groups, layout.unsorted, layout.running_sum) == (
        -(-K_ // 4), int(order == "input"), int(rule == "running_sum"))
    w32 = w.astype(np.float32).astype(np.float64)  # the device's weights, exactly
    np.testing.assert_allclose(skin_through_layout(layout, points, M, K.LBS, device),
                               lbs64(points, idx, w32, M), atol=2e-5)
    np.testing.assert_allclose(skin_through_layout(layout, points, M, K.DQS, device),
                               dqs_reference(points, idx, w32, M[None], rule)[0], atol=2e-5)


@pytest.mark.parametrize("K_", [0, 1, 3, 4, 5, 9])
def test_padding_slots_weigh_nothing(device, K_):
    """Past its K influences a vertex's groups hold joint 0 with weight 0, in both orders; the
    weight order is the stable descending sort (ties: first input first)."""
    rng = np.random.default_rng(K_)
    V = 64
    w = rng.integers(0, 3, size=(V, K_)).astype(np.float32) / 2  # ties and zeros
    idx = rng.integers(1, 40, size=(V, K_)).astype(np.int32)
    inf = Influences(idx, w)
    C = max(1, -(-K_ // 4))
    # the oracle: Python's sort, stable, on each row's slots by descending weight
    by_weight = np.array([sorted(range(K_), key=lambda k: -row[k]) for row in w.tolist()],
                         dtype=np.int64).reshape(V, K_)
    for order in ("weight", "input"):
        lay = inf.layout(device, order, blend=empty(float, device),
                         centers=empty(wp.vec4, device))
        got_i = lay.indices.numpy().reshape(V, 4 * C)
        got_w = lay.weights.numpy().reshape(V, 4 * C)
        assert not got_i[:, K_:].any() and not got_w[:, K_:].any()
        perm = by_weight if order == "weight" else np.tile(np.arange(K_), (V, 1))
        np.testing.assert_array_equal(got_i[:, :K_], np.take_along_axis(idx, perm, 1))
        np.testing.assert_array_equal(got_w[:, :K_], np.take_along_axis(w, perm, 1))
    np.testing.assert_array_equal(inf.indices.reshape(V, -1)[:, :K_],
                                  np.take_along_axis(idx, by_weight, 1))


def test_concatenation_offsets():
    a = (np.array([[0, 2], [1, 1]]), np.array([[0.5, 0.5], [1.0, 0.0]]))
    b = (np.array([[6, 0, 1, 2], [3, 3, 3, 3], [5, 4, 3, 2]]), np.full((3, 4), 0.25))
    c = (np.array([1]), np.array([1.0]))  # 1-D: one influence a vertex
    inf, slices = Influences.concatenate([a, b, c], [0, 3, 10], [3, 7, 2])
    assert slices == [slice(0, 2), slice(2, 5), slice(5, 6)]
    assert (inf.vertex_count, inf.influence_count) == (6, 4)
    idx, w = inf.given
    want_i = np.zeros((6, 4), np.int64)
    want_w = np.zeros((6, 4), np.float32)
    want_i[0:2, :2], want_w[0:2, :2] = a[0], a[1]
    want_i[2:5], want_w[2:5] = b[0] + 3, b[1]
    want_i[5, 0], want_w[5, 0] = 11, 1.0
    np.testing.assert_array_equal(idx, want_i)
    np.testing.assert_array_equal(w, want_w)
    assert inf.joint_count_min == 12


def test_concatenation_checks_each_mesh_against_its_own_joints():
    a = (np.array([[0, 2]]), np.array([[0.5, 0.5]]))
    with pytest.raises(InputError, match=r"arm: joint_indices: index 2 out of range for 2 "
                                         r"joints of its skeleton"):
        Influences.concatenate([a], [5], [2], ["arm"])
    with pytest.raises(InputError, match="leg: joint_indices: negative index -1"):
        Influences.concatenate([(np.array([[-1]]), np.array([[1.0]]))], [0], [3], ["leg"])


def test_one_joint_range_check():
    """The constructor's joint count, the skinning transforms' count and a direct call read
    alike: one check."""
    idx, w = np.array([[0, 4]]), np.array([[0.5, 0.5]], np.float32)
    msg = "joint_indices: index 4 out of range for 4 "
    with pytest.raises(InputError, match=msg + "joints"):
        check_influences(idx, w, joint_count=4)
    with pytest.raises(InputError, match=msg + "skinning transforms"):
        Influences(idx, w).check_joint_count(4)
    with pytest.raises(InputError, match=msg + "bones"):
        check_joint_range(4, 4, "bones")
    Influences(idx, w).check_joint_count(5)


def test_skinner_takes_a_built_layout():
    """A Skinner built on an :class:`Influences` (as MeshBatch builds one) skins as one built on
    its arrays; a layout of another vertex count is refused."""
    rng = np.random.default_rng(2)
    points, idx, w, M = rig(rng, 40, 3)
    inf = Influences(idx, w)
    got = dqskin.Skinner(points, inf, None, device="cpu").skin(M, "dqs")
    np.testing.assert_array_equal(got, dqskin.Skinner(points, idx, w, device="cpu").skin(M, "dqs"))
    with pytest.raises(InputError, match="joint_indices: 40 vertices for 39 points"):
        dqskin.Skinner(points[:39], inf, None, device="cpu")
    with pytest.raises(InputError, match="joint_weights: expected None with joint_indices an "
                       "Influences"):
        dqskin.Skinner(points, inf, w, device="cpu")
    with pytest.raises(InputError, match="joint_weights: required with joint_indices an array"):
        dqskin.Skinner(points, idx, None, device="cpu")
