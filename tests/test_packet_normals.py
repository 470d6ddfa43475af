"""Normals and tangents eight rows a thread (``dqskin.kernels.packet_normals``), LBS and DQS of
each sign rule: bit for bit the one-vertex kernel (per-vertex and face-varying rows, tails of
fewer than eight, one frame and frame blocks, rigid and scaled frames, zero weights); LBS's
both branches (the CPU's vector one and the scalar one CUDA compiles, built here for the CPU)
within float32 of float64 NumPy written from the equation ``normalize((Σ wₖ·Mₖ)·n)``,
``Mₖ = Aₖ⁻ᵀ`` for normals and ``Aₖ`` for tangents; DQS of rigid frames within float32 of the
float64 rotation of the sign-aligned quaternion blend."""

import numpy as np
import pytest
import warp as wp
from scipy.spatial.transform import Rotation

from dqskin._warp import init_warp
from dqskin.kernels import packet_normals as PN

wp.set_module_options({"enable_backward": False})


@wp.func_native(PN.vector_packet_source(scalar_on_cpu=True))
def scalar_vector_packet(vectors: wp.array(dtype=wp.vec3), vector_base: wp.int64,
                         vector_vertex: wp.array(dtype=wp.int32),
                         indices: wp.array(dtype=wp.vec4i), weights: wp.array(dtype=wp.vec4),
                         linears: wp.array(dtype=wp.mat33), o: int, n0: int, count: int,
                         out: wp.array(dtype=wp.vec3), out_base: wp.int64) -> int:
    ...


@wp.func_native(PN.dqs_vector_packet_source(scalar_on_cpu=True))
def scalar_dqs_packet(vectors: wp.array(dtype=wp.vec3), vector_base: wp.int64,
                      vector_vertex: wp.array(dtype=wp.int32),
                      indices: wp.array(dtype=wp.vec4i), weights: wp.array(dtype=wp.vec4),
                      rotations: wp.array(dtype=wp.quat), residuals: wp.array(dtype=wp.mat33),
                      scaled: int, rule: int, o: int, n0: int, count: int,
                      out: wp.array(dtype=wp.vec3), out_base: wp.int64) -> int:
    ...


@wp.kernel
def both_dqs_branches(vectors: wp.array(dtype=wp.vec3), vector_vertex: wp.array(dtype=wp.int32),
                      indices: wp.array(dtype=wp.vec4i), weights: wp.array(dtype=wp.vec4),
                      rotations: wp.array(dtype=wp.quat), residuals: wp.array(dtype=wp.mat33),
                      rule: int, rows: int, out_vector: wp.array(dtype=wp.vec3),
                      out_scalar: wp.array(dtype=wp.vec3)):
    """Packet ``tid`` of one rigid frame through both DQS branches."""
    n0 = wp.tid() * 8
    PN.dqs_vector_packet(vectors, wp.int64(0), vector_vertex, indices, weights, rotations,
                         residuals, 0, rule, 0, n0, rows, out_vector, wp.int64(0))
    scalar_dqs_packet(vectors, wp.int64(0), vector_vertex, indices, weights, rotations,
                      residuals, 0, rule, 0, n0, rows, out_scalar, wp.int64(0))


@wp.kernel
def both_branches(vectors: wp.array(dtype=wp.vec3), vector_vertex: wp.array(dtype=wp.int32),
                  indices: wp.array(dtype=wp.vec4i), weights: wp.array(dtype=wp.vec4),
                  linears: wp.array(dtype=wp.mat33), joint_count: int, rows: int,
                  out_vector: wp.array(dtype=wp.vec3), out_scalar: wp.array(dtype=wp.vec3)):
    """Packet ``tid`` of frame 0 through both branches."""
    n0 = wp.tid() * 8
    PN.lbs_vector_packet(vectors, wp.int64(0), vector_vertex, indices, weights, linears, 0, n0,
                         rows, out_vector, wp.int64(0))
    scalar_vector_packet(vectors, wp.int64(0), vector_vertex, indices, weights, linears, 0, n0,
                         rows, out_scalar, wp.int64(0))


def rig(rng, V, J=7, F=3):
    idx = rng.integers(0, J, size=(V, 4)).astype(np.int32)
    w = rng.random((V, 4)) + 0.05
    w[rng.random(w.shape) < 0.2] = 0.0
    w = (w / np.maximum(w.sum(1, keepdims=True), 1e-9)).astype(np.float32)
    M = np.tile(np.eye(4), (F, J, 1, 1))
    M[..., :3, :3] = Rotation.random(F * J, random_state=rng).as_matrix().reshape(F, J, 3, 3)
    M[..., :3, :3] *= rng.uniform(0.5, 1.6, size=(F, J, 1, 3))  # scale: A⁻ᵀ ≠ A
    M[..., :3, 3] = rng.normal(size=(F, J, 3))
    return idx, w, M


def oracle(vectors, vertex, idx, w, M, kind):
    """float64 ``normalize((Σ wₖ·Mₖ)·x)`` of (N, 3) directions, one frame's (J, 4, 4) ``M``."""
    A = M[:, :3, :3]
    mats = np.linalg.inv(A).transpose(0, 2, 1) if kind == "normal" else A
    blend = np.einsum("nk,nkij->nij", w[vertex].astype(np.float64), mats[idx[vertex]])
    y = np.einsum("nij,nj->ni", blend, vectors.astype(np.float64))
    return y / np.linalg.norm(y, axis=1, keepdims=True)


@pytest.mark.parametrize("N", [1, 7, 8, 9, 203])
def test_both_branches_match_float64(N):
    init_warp()
    rng = np.random.default_rng(N)
    V = max(N // 2, 1)
    idx, w, M = rig(rng, V)
    w[0] = [1.0, 0.0, 0.0, 0.0]  # a row of one joint
    vertex = rng.integers(0, V, size=N).astype(np.int32)  # face-varying: rows share vertices
    vectors = rng.normal(size=(N, 3)).astype(np.float32)
    mats = np.linalg.inv(M[0, :, :3, :3]).transpose(0, 2, 1).astype(np.float32)
    outs = [wp.full(N + 8, wp.vec3(7.0, 7.0, 7.0), dtype=wp.vec3, device="cpu")
            for _ in range(2)]
    wp.launch(both_branches, dim=-(-N // 8), device="cpu",
              inputs=[wp.array(vectors, dtype=wp.vec3, device="cpu"),
                      wp.array(vertex, dtype=wp.int32, device="cpu"),
                      wp.array(idx, dtype=wp.vec4i, device="cpu"),
                      wp.array(w, dtype=wp.vec4, device="cpu"),
                      wp.array(mats, dtype=wp.mat33, device="cpu"), mats.shape[0], N, *outs])
    want = oracle(vectors, vertex, idx, w, M[0], "normal")
    for out in outs:
        got = out.numpy()
        assert (got[N:] == 7.0).all(), "a lane past the last row was stored"
        assert np.abs(got[:N] - want).max() <= 2e-6


def launches(monkeypatch):
    """``(names, packets)``: the keys of the kernels launched since ``packets(on)`` last
    cleared them, ``on`` False making :func:`dqskin.kernels.skin.skin_vectors` take the
    one-vertex kernel (it sees no CPU)."""
    from dqskin.kernels import grid
    from dqskin.kernels import skin as KS
    names = []
    real_launch, real_is_cpu = grid._launch, KS.is_cpu
    monkeypatch.setattr(grid, "_launch", lambda kernel, *a: (names.append(kernel.key),
                                                              real_launch(kernel, *a)))

    def packets(on):
        monkeypatch.setattr(KS, "is_cpu", real_is_cpu if on else lambda device: False)
        names.clear()
    return names, packets


@pytest.mark.parametrize("kind", ["normal", "tangent"])
@pytest.mark.parametrize("V", [9, 203, 4096 + 5])
def test_packets_equal_one_vertex_kernel(monkeypatch, kind, V):
    """Skinner.skin_vectors with LBS runs the packet kernel on the CPU and gives bit for bit
    what the one-vertex kernel gives: frame blocks, one frame, face-varying rows."""
    import dqskin

    rng = np.random.default_rng(V)
    idx, w, M = rig(rng, V, F=20)
    points = rng.normal(size=(V, 3)).astype(np.float32)
    vectors = rng.normal(size=(V, 3)).astype(np.float32)
    fv = rng.integers(0, V, size=V + 13)
    names, packets = launches(monkeypatch)

    def run(packet):
        packets(packet)
        sk = dqskin.Skinner(points, idx, w, device="cpu")
        got = (sk.skin_vectors(M, vectors, "lbs", kind=kind),
               sk.skin_vectors(M[0], vectors, "lbs", kind=kind),
               sk.skin_vectors(M, vectors[fv], "lbs", kind=kind, vector_vertex=fv))
        assert ("skin_vectors_lbs_packet_kernel" in names) == packet, names
        return got

    packet, one_vertex = run(True), run(False)
    for a, b in zip(packet, one_vertex):
        np.testing.assert_array_equal(a, b)
    live = w.sum(1) > 0  # an all-zero blend gives a zero vector (not the oracle's business)
    assert (packet[0][:, ~live] == 0).all()
    for f in (0, 19):
        want = oracle(vectors[live], np.arange(live.sum()), idx[live], w[live], M[f], kind)
        assert np.abs(packet[0][f, live] - want).max() <= 2e-6


def quaternion_oracle(vectors, idx, w, M, rule):
    """float64 DQS of (V, 3) directions at one rigid frame: the sign-aligned blend of the
    joints' (w, x, y, z) rotations (against the first largest weight's, or the running sum in
    input order), normalized, rotating each direction."""
    q = Rotation.from_matrix(M[:, :3, :3]).as_quat()[:, [3, 0, 1, 2]]
    out = np.empty((len(vectors), 3))
    for v in range(len(vectors)):
        qs, ws = q[idx[v]], w[v].astype(np.float64)
        ref = qs[int(np.argmax(ws))]  # the first largest weight's (slot 0 once sorted)
        b = np.zeros(4)
        for k in range(4):
            if rule == "running":
                ref = b
            b = b + qs[k] * (ws[k] * (-1.0 if qs[k] @ ref < 0 else 1.0))
        out[v] = Rotation.from_quat(b[[1, 2, 3, 0]]).apply(vectors[v].astype(np.float64))
    return out / np.linalg.norm(out, axis=1, keepdims=True)


@pytest.mark.parametrize("kind,rule", [("normal", "sorted"), ("tangent", "sorted"),
                                       ("normal", "searched"), ("normal", "running"),
                                       ("tangent", "running")])
@pytest.mark.parametrize("V", [9, 4096 + 5])
def test_dqs_packets_equal_one_vertex_kernel(monkeypatch, kind, rule, V):
    """DQS directions: the packet kernel gives bit for bit what the one-vertex kernel gives with
    each sign rule (a Skinner's sorted layout, a one-shot call's searched pivot, Blender's
    running sum), on rigid and scaled frames, one frame, face-varying rows; rigid frames within
    float32 of the float64 quaternion blend."""
    import dqskin

    rng = np.random.default_rng(V + len(rule))
    idx, w, M = rig(rng, V, F=20)
    M[:10, :, :3, :3] /= np.linalg.norm(M[:10, :, :3, :3], axis=-2, keepdims=True)  # rigid
    points = rng.normal(size=(V, 3)).astype(np.float32)
    vectors = rng.normal(size=(V, 3)).astype(np.float32)
    fv = rng.integers(0, V, size=V + 13)
    sign = "running_sum" if rule == "running" else "largest_weight"
    names, packets = launches(monkeypatch)

    def run(packet):
        packets(packet)
        if rule == "searched":  # a one-shot call (normals): input order, pivot searched
            got = (dqskin.skin_normals(vectors, idx, w, M, "dqs", device="cpu"),
                   dqskin.skin_normals(vectors, idx, w, M[0], "dqs", device="cpu"),
                   dqskin.skin_normals(vectors[fv], idx, w, M, "dqs", normal_vertex=fv,
                                       device="cpu"))
        else:
            sk = dqskin.Skinner(points, idx, w, device="cpu")
            got = (sk.skin_vectors(M, vectors, "dqs", kind=kind, sign_reference=sign),
                   sk.skin_vectors(M[0], vectors, "dqs", kind=kind, sign_reference=sign),
                   sk.skin_vectors(M, vectors[fv], "dqs", kind=kind, vector_vertex=fv,
                                   sign_reference=sign))
        assert ("skin_vectors_dqs_packet_kernel" in names) == packet, names
        return got

    packet, one_vertex = run(True), run(False)
    for a, b in zip(packet, one_vertex):
        np.testing.assert_array_equal(a, b)
    live = w.sum(1) > 0
    for f in (0, 9):
        want = quaternion_oracle(vectors[live], idx[live], w[live], M[f], rule)
        assert np.abs(packet[0][f, live] - want).max() <= 5e-6


@pytest.mark.parametrize("rule", ["sorted", "searched", "running"])
@pytest.mark.parametrize("N", [1, 9, 203])
def test_both_dqs_branches_match_float64(rule, N):
    """The DQS snippet's vector and scalar branches against the float64 quaternion blend of
    each sign rule (one rigid frame; input-order slots, the pivot searched or, for the sorted
    rule, the weights sorted so that slot 0 is the largest)."""
    init_warp()
    rng = np.random.default_rng(N + len(rule))
    V = max(N // 2, 1)
    idx, w, M = rig(rng, V)
    M[0, :, :3, :3] /= np.linalg.norm(M[0, :, :3, :3], axis=-2, keepdims=True)  # rigid
    if rule == "sorted":
        order = np.argsort(-w, axis=1, kind="stable")
        idx, w = np.take_along_axis(idx, order, 1), np.take_along_axis(w, order, 1)
    vertex = rng.integers(0, V, size=N).astype(np.int32)
    vectors = rng.normal(size=(N, 3)).astype(np.float32)
    quats = Rotation.from_matrix(M[0, :, :3, :3]).as_quat().astype(np.float32)  # (x, y, z, w)
    outs = [wp.full(N + 8, wp.vec3(7.0, 7.0, 7.0), dtype=wp.vec3, device="cpu")
            for _ in range(2)]
    wp.launch(both_dqs_branches, dim=-(-N // 8), device="cpu",
              inputs=[wp.array(vectors, dtype=wp.vec3, device="cpu"),
                      wp.array(vertex, dtype=wp.int32, device="cpu"),
                      wp.array(idx, dtype=wp.vec4i, device="cpu"),
                      wp.array(w, dtype=wp.vec4, device="cpu"),
                      wp.array(quats, dtype=wp.quat, device="cpu"),
                      wp.array(np.tile(np.eye(3, dtype=np.float32), (len(quats), 1, 1)),
                               dtype=wp.mat33, device="cpu"),
                      ["sorted", "searched", "running"].index(rule), N, *outs])
    live = w[vertex].sum(1) > 0
    want = quaternion_oracle(vectors[live], idx[vertex][live], w[vertex][live], M[0], rule)
    for out in outs:
        got = out.numpy()
        assert (got[N:] == 7.0).all(), "a lane past the last row was stored"
        assert np.abs(got[:N][live] - want).max() <= 5e-6
