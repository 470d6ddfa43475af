"""The eight-vertex packet snippets (``dqskin.kernels.packets``): the CPU's vector branch and the
scalar branch CUDA compiles (built for the CPU by ``packet_twin.py``) against float64 NumPy
written from the equations; tails of fewer than eight vertices, frames, the searched pivot's
ties, zero and NaN inputs. The launcher's use of them (chunks, frame blocks, layouts) is tested
through ``skin_points`` / ``Skinner`` against UsdSkel in ``test_skinning.py``."""

import numpy as np
import pytest
import warp as wp
from scipy.spatial.transform import Rotation
from test_skinning import numpy_dqs, numpy_lbs, rel_err  # tests/ is on the path of its tests

from dqskin._warp import init_warp

J = 9


def dual_quaternions(M):
    """float64 unit dual quaternions (w, x, y, z, dw, dx, dy, dz) of rigid (..., 4, 4)."""
    q = Rotation.from_matrix(M[..., :3, :3].reshape(-1, 3, 3)).as_quat()[:, [3, 0, 1, 2]]
    t = M[..., :3, 3].reshape(-1, 3)
    w, v = q[:, :1], q[:, 1:]
    dual = 0.5 * np.concatenate([-np.sum(t * v, 1, keepdims=True), w * t + np.cross(t, v)], 1)
    return np.concatenate([q, dual], 1).reshape(M.shape[:-2] + (8,))


PAD = 24  # output entries after the last frame: a sentinel that no lane may overwrite
SENTINEL = 7.0


def run_both(rule, points, idx, w, M, residuals=None, check=False):
    """(vector, scalar) outputs (F, V, 3) of the snippet of ``rule`` on (F, V, 3) points; DQS
    frames with ``residuals`` (F, J, 3, 3) blend the points through them first. Checks that the
    entries after the last frame kept their sentinel. With ``check``, also the two branches'
    input flags."""
    init_warp()
    from packet_twin import BOTH

    F, V = points.shape[:2]
    if rule == "lbs":
        arr = wp.array(M[..., :3, :].astype(np.float32).reshape(-1, 3, 4),
                       dtype=wp.types.matrix(shape=(3, 4), dtype=wp.float32), device="cpu")
    else:
        arr = wp.array(dual_quaternions(M).astype(np.float32).reshape(-1, 8),
                       dtype=wp.types.vector(8, wp.float32), device="cpu")
    scaled = np.zeros(F, np.int32) if residuals is None else np.ones(F, np.int32)
    res = np.tile(np.eye(3), (F, J, 1, 1)) if residuals is None else residuals
    flags = [wp.zeros(1, dtype=wp.int32, device="cpu") for _ in range(2)]
    outs = [wp.full(F * V + PAD, wp.vec3(SENTINEL, SENTINEL, SENTINEL), dtype=wp.vec3,
                    device="cpu") for _ in range(2)]
    wp.launch(BOTH[rule], dim=-(-V // 8),
              inputs=[wp.array(points.reshape(-1, 3), dtype=wp.vec3, device="cpu"),
                      wp.array(idx, dtype=wp.vec4i, device="cpu"),
                      wp.array(w, dtype=wp.vec4, device="cpu"), arr,
                      wp.array(res.reshape(-1, 3, 3).astype(np.float32), dtype=wp.mat33,
                               device="cpu"),
                      wp.array(scaled, dtype=int, device="cpu"), J, F, V, int(check), *outs,
                      *flags],
              device="cpu")
    got = [o.numpy() for o in outs]
    for g in got:
        assert (g[F * V:] == SENTINEL).all(), "a lane past the last vertex was stored"
    got = [g[:F * V].reshape(F, V, 3) for g in got]
    return (got, [int(f.numpy()[0]) for f in flags]) if check else got


def rig(rng, V, F=2):
    points = (rng.normal(size=(F, V, 3)) * 2).astype(np.float32)
    idx = rng.integers(0, J, size=(V, 4)).astype(np.int32)
    w = rng.random((V, 4)) + 0.05
    w = (w / w.sum(1, keepdims=True)).astype(np.float32)
    M = np.tile(np.eye(4), (F, J, 1, 1))
    M[..., :3, :3] = Rotation.random(F * J, random_state=rng).as_matrix().reshape(F, J, 3, 3)
    M[..., :3, 3] = rng.normal(size=(F, J, 3))
    return points, idx, w, M


def running_sum_dqs(points, idx, w, M):
    """float64 DQS of (V, 3) points with Blender's rule (test_sign_reference's oracle)."""
    from test_sign_reference import dqs_reference

    return dqs_reference(points.astype(np.float64), idx, w.astype(np.float64), M[None],
                         "running_sum")[0]


ORACLES = {"lbs": numpy_lbs, "sorted": numpy_dqs, "searched": numpy_dqs,
           "running": running_sum_dqs}


@pytest.mark.parametrize("V", [1, 7, 8, 9, 203])
@pytest.mark.parametrize("rule", ["lbs", "sorted", "searched", "running"])
def test_packets_match_float64(rule, V):
    """Both branches against the float64 oracles, every frame; the sorted rule gets weights in
    descending order (its pivot is slot 0), the others input order. Lanes past the last vertex
    are not stored (:func:`run_both`'s sentinel after the last frame)."""
    rng = np.random.default_rng(V + len(rule))
    points, idx, w, M = rig(rng, V)
    if rule == "sorted":
        order = np.argsort(-w, axis=1, kind="stable")
        idx, w = np.take_along_axis(idx, order, 1), np.take_along_axis(w, order, 1)
    vector, scalar = run_both(rule, points, idx, w, M)
    oracle = ORACLES[rule]
    for f in range(points.shape[0]):
        want = oracle(points[f], idx, w, M[f])
        assert rel_err(vector[f], want) <= 1e-5, f
        assert rel_err(scalar[f], want) <= 1e-5, f
    np.testing.assert_allclose(vector, scalar, rtol=0, atol=1e-5)


def test_searched_pivot_is_the_first_largest_weight():
    """Two equal largest weights on joints whose rotations lie on opposite hemispheres, a third
    joint between them: the signs differ with the pivot, and the first of the two must win (as
    UsdSkel's and the scalar kernels' search); joint 3 has weight zero."""
    half = Rotation.from_rotvec
    rots = [half([0, 0, 0.2 * np.pi]),  # between the two below
            half([0, 0, -0.75 * np.pi]),
            half([0, 0, 1.15 * np.pi]),  # q1 · q2 < 0, both on q0's side
            half([1.0, 0, 0])]
    q = np.array([r.as_quat()[[3, 0, 1, 2]] for r in rots])
    assert q[1] @ q[2] < 0 < min(q[0] @ q[1], q[0] @ q[2])
    M = np.tile(np.eye(4), (1, J, 1, 1))
    for j, r in enumerate(rots):
        M[0, j, :3, :3] = r.as_matrix()
        M[0, j, :3, 3] = [j, -j, 0.5 * j]
    points = np.array([[[0.3, 1.0, -2.0]]], np.float32).repeat(11, axis=1)
    w = np.array([[0.2, 0.4, 0.4, 0.0]], np.float32).repeat(11, axis=0)
    idx = np.array([[0, 1, 2, 3]], np.int32).repeat(11, axis=0)
    vector, scalar = run_both("searched", points, idx, w, M)
    first = numpy_dqs(points[0], idx, w, M[0])  # argmax: the first of equal weights
    swapped = numpy_dqs(points[0], idx[:, [0, 2, 1, 3]], w, M[0])  # the other one as pivot
    assert np.abs(first - swapped).max() > 0.1  # the pivot matters here
    for out in (vector, scalar):
        assert rel_err(out[0], first) <= 1e-5


@pytest.mark.parametrize("rule", ["lbs", "sorted", "searched", "running"])
def test_zero_weights_and_nan_joints(rule):
    """All-zero weights: DQS leaves the point where it was (a zero blend normalizes to the
    identity, as Gf), LBS gives the origin (Σ 0·M·p); a NaN joint makes only its vertices NaN."""
    rng = np.random.default_rng(3)
    points, idx, w, M = rig(rng, 13, F=1)
    w[2] = 0.0
    idx[5:] = np.where(idx[5:] == 4, 5, idx[5:])
    idx[5, 1] = 4
    M[0, 4, :3, 3] = np.nan
    for out in run_both(rule, points, idx, w, M):
        want = np.zeros(3) if rule == "lbs" else points[0, 2]
        np.testing.assert_allclose(out[0, 2], want, atol=1e-6)
        assert np.isnan(out[0, 5]).all()
        rest = np.delete(np.arange(13), [2, 5])
        assert np.isfinite(out[0, rest]).all()


@pytest.mark.parametrize("V", [5, 203])
@pytest.mark.parametrize("rule", ["sorted", "searched", "running"])
def test_scaled_frames_blend_through_residuals(rule, V):
    """A frame with scale/shear (UsdSkel's DQS): ``p_s = Σ wₖ·Sₖ·p``, then the rigid blend
    (rotation and translation of the polar split) applied to ``p_s``; float64 oracle."""
    rng = np.random.default_rng(40 + V)
    points, idx, w, M = rig(rng, V)
    if rule == "sorted":
        order = np.argsort(-w, axis=1, kind="stable")
        idx, w = np.take_along_axis(idx, order, 1), np.take_along_axis(w, order, 1)
    S = np.eye(3) + 0.2 * rng.normal(size=(2, J, 3, 3))
    vector, scalar = run_both(rule, points, idx, w, M, residuals=S)
    for f in range(2):
        blended = np.einsum("vk,vkij,vj->vi", w.astype(np.float64), S[f][idx], points[f])
        oracle = ORACLES[rule]
        want = oracle(blended, idx, w, M[f])
        assert rel_err(vector[f], want) <= 1e-5, f
        assert rel_err(scalar[f], want) <= 1e-5, f
        assert rel_err(vector[f], oracle(points[f], idx, w, M[f])) > 1e-2  # S mattered


@pytest.mark.parametrize("case,packet", [
    ("lbs", True), ("dqs", True), ("dqs scaled", True), ("dqs one-shot", True),
    ("dqs blender", True), ("dqs blender one-shot", True), ("dqs 5 influences", False),
    ("blend", False)])
def test_launcher_picks_packet_kernels(monkeypatch, case, packet):
    """On the CPU, LBS and DQS (the sorted layout, the one-shot's searched pivot, the running
    sum, frames with scale) of at most four influences launch the packet kernels; more
    influences and the other methods launch the one-vertex kernels. Results against UsdSkel are
    in ``test_skinning.py``."""
    import dqskin
    from dqskin.kernels import grid

    names = []
    real = grid._launch
    monkeypatch.setattr(grid, "_launch", lambda kernel, *a: (names.append(kernel.key),
                                                              real(kernel, *a)))
    rng = np.random.default_rng(5)
    K = 5 if "5" in case else 4
    points = rng.normal(size=(50, 3)).astype(np.float32)
    idx = rng.integers(0, J, size=(50, K))
    w = rng.random((50, K)) + 0.1
    M = np.tile(np.eye(4), (J, 1, 1))
    M[:, :3, :3] = Rotation.random(J, random_state=rng).as_matrix()
    if "scaled" in case:
        M[:, 0, 0] = 1.5
    method = case.split()[0]
    rule = "running_sum" if "blender" in case else "largest_weight"
    if "one-shot" in case:
        dqskin.skin_points(points, idx, w, M, method, sign_reference=rule, device="cpu")
    else:
        sk = dqskin.Skinner(points, idx, w, blend_weights=np.full(50, 0.5), device="cpu")
        sk.skin(M, method, sign_reference=rule)
    skins = [n for n in names if n.startswith("skin_")]
    assert skins and all(n.endswith("_packet") == packet for n in skins), skins


@pytest.mark.parametrize("V", [13, 16])
@pytest.mark.parametrize("rule", ["lbs", "sorted", "searched", "running"])
@pytest.mark.parametrize("bad", ["none", "nan point", "inf point", "index -1", "index J",
                                 "negative weight", "nan weight", "inf weight", "-0.0 weight"])
def test_checked_packets_flag_what_the_host_refuses(rule, bad, V):
    """``check``: a one-shot call's inputs, unchecked on the host, are checked by the snippets as
    the host would (points finite, ``0 <= index < J``, weights finite and non-negative; -0.0 is
    a valid weight); the bad value in the last vertex of a tail packet (V = 13), or of a full
    packet (V = 16). An index out of range then reads joint 0 (no read outside the joints), in
    both branches."""
    rng = np.random.default_rng(9)
    points, idx, w, M = rig(rng, V, F=1)
    where = (0, V - 1)
    if bad == "nan point":
        points[where + (0,)] = np.nan
    elif bad == "inf point":
        points[where + (2,)] = -np.inf
    elif bad.startswith("index"):
        idx[where[1], 3] = -1 if bad == "index -1" else J
    elif bad != "none":
        w[where[1], 2] = {"negative weight": -0.25, "nan weight": np.nan, "inf weight": np.inf,
                          "-0.0 weight": -0.0}[bad]
    outs, flagged = run_both(rule, points, idx, w, M, check=True)
    want = int(bad not in ("none", "-0.0 weight"))
    assert flagged == [want, want]
    if bad.startswith("index"):  # read as joint 0: the outputs are what joint 0 gives
        fixed = idx.copy()
        fixed[where[1], 3] = 0
        for a, b in zip(outs, run_both(rule, points, fixed, w, M)):
            np.testing.assert_array_equal(a, b)


@pytest.mark.parametrize("rule", ["lbs", "searched"])
def test_checked_packets_flag_a_bad_value_in_every_lane_and_slot(rule):
    """The input check of a packet covers each of its eight vertices and each coordinate, index
    and weight of a vertex (the check reduces them all to one test): one bad value at a time, in
    every position of a full packet and of the last vertex of a tail, is flagged by both
    branches; -0.0 in any weight slot is not."""
    rng = np.random.default_rng(5)
    points, idx, w, M = rig(rng, 11, F=1)
    cases = []
    for v in [*range(8), 10]:
        cases += [("point", v, c, [np.nan, np.inf, -np.inf][(v + c) % 3]) for c in range(3)]
        cases += [("index", v, k, [-1, J, 1 << 30][(v + k) % 3]) for k in range(4)]
        cases += [("weight", v, k, [-0.5, np.nan, np.inf, -0.0][(v + k) % 4]) for k in range(4)]
    for what, v, slot, value in cases:
        p, i, wt = points.copy(), idx.copy(), w.copy()
        if what == "point":
            p[0, v, slot] = value
        elif what == "index":
            i[v, slot] = value
        else:
            wt[v, slot] = value
        want = 0 if what == "weight" and value == 0.0 else 1
        _, flagged = run_both(rule, p, i, wt, M, check=True)
        assert flagged == [want, want], (what, v, slot, value)


def antipodal_rig(rng, V, F=2):
    """A :func:`rig` whose joints rotate about one axis by angles spread over ±π (many pairs of
    real parts on opposite hemispheres, the running sum's signs changing along the blend), one
    joint rotated by exactly π about x (a real-part dot of exactly 0 with the identity, joint
    0), zero weights (slot 0 too: a zero running sum) and scale on the second frame."""
    points, idx, w, M = rig(rng, V, F)
    angles = rng.uniform(-np.pi, np.pi, size=(F, J))
    M[..., :3, :3] = Rotation.from_rotvec(
        (angles[..., None] * np.array([0.3, -0.2, 0.93])).reshape(-1, 3)).as_matrix().reshape(
        F, J, 3, 3)
    M[:, 0, :3, :3] = np.eye(3)
    M[:, 1, :3, :3] = np.diag([1.0, -1.0, -1.0])
    idx[: V // 4, :2] = [0, 1]
    w[rng.random(w.shape) < 0.15] = 0.0
    w[::7, 0] = 0.0
    M[1, :, :3, :3] *= np.array([1.0, 1.3, 0.8])
    return points[0], idx, w, M


@pytest.mark.parametrize("V", [9, 203, 4096 + 5])
@pytest.mark.parametrize("rule", ["running_sum", "largest_weight"])
def test_packets_equal_one_vertex_kernels(monkeypatch, rule, V):
    """The packet kernels (Skinner and one-shot calls) give bit for bit what the one-vertex
    kernels give, with each sign rule: several frames (a rigid one, a scaled one), one frame,
    antipodal rigs; the packets within float64 of the oracle of the rule (rigid frame)."""
    import dqskin
    from dqskin.kernels import grid
    from dqskin.kernels import skin as KS

    rng = np.random.default_rng(V)
    points, idx, w, M = antipodal_rig(rng, V)
    names = []
    real_launch, real_takes = grid._launch, KS.takes_packets
    monkeypatch.setattr(grid, "_launch", lambda kernel, *a: (names.append(kernel.key),
                                                              real_launch(kernel, *a)))

    def both(packet):
        monkeypatch.setattr(KS, "takes_packets", real_takes if packet else lambda *a: False)
        names.clear()
        sk = dqskin.Skinner(points, idx, w, device="cpu")
        got = (sk.skin(M, "dqs", sign_reference=rule), sk.skin(M[0], "dqs", sign_reference=rule),
               dqskin.skin_points(points, idx, w, M, "dqs", sign_reference=rule, device="cpu"))
        skins = [n for n in names if n.startswith("skin_")]
        assert skins and all(n.endswith("_packet") == packet for n in skins), skins
        return got

    packet, one_vertex = both(True), both(False)
    for a, b in zip(packet, one_vertex):
        np.testing.assert_array_equal(a, b)
    oracle = running_sum_dqs if rule == "running_sum" else numpy_dqs
    live = w.sum(1) > 0  # (an all-zero blend leaves the point: not the oracle's business)
    assert rel_err(packet[1][live], oracle(points[live], idx[live], w[live], M[0])) <= 1e-5
