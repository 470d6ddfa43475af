"""Skinning kernels against references.

UsdSkel's C++ (SkinPoints / SkinNormals), float64 NumPy and closed forms.
"""

import numpy as np
import pytest
import warp as wp
from pxr import Gf, UsdSkel, Vt
from scipy.spatial.transform import Rotation

import dqskin
from dqskin.kernels import grid
from dqskin.kernels import skin as K
from dqskin.kernels.dqmath import vec8

TOKENS = {"lbs": "classicLinear", "dqs": "dualQuaternion"}


def random_rig(rng, V=600, K=4, J=12, F=3, nonrigid=False):
    points = rng.normal(size=(V, 3)) * 2.0
    idx = rng.integers(0, J, size=(V, K))
    w = rng.random((V, K)) + 0.05
    w /= w.sum(1, keepdims=True)
    M = np.tile(np.eye(4), (F, J, 1, 1))
    M[..., :3, :3] = Rotation.random(F * J, random_state=rng).as_matrix().reshape(F, J, 3, 3)
    if nonrigid:
        M[..., :3, :3] = M[..., :3, :3] @ (np.eye(3) + 0.3 * rng.normal(size=(F, J, 3, 3)))
    M[..., :3, 3] = rng.normal(size=(F, J, 3))
    G = np.eye(4)
    G[:3, :3] = Rotation.random(random_state=rng).as_matrix() * 1.5
    G[:3, 3] = rng.normal(size=3)
    return points.astype(np.float32), idx.astype(np.int32), w.astype(np.float32), M, G


def usd_skin_points(method, G, M, idx, w, points):
    """UsdSkel.SkinPoints for one frame (row-vector matrices: transpose at the boundary)."""
    vp = Vt.Vec3fArray.FromNumpy(np.ascontiguousarray(points, dtype=np.float32))
    ok = UsdSkel.SkinPoints(TOKENS[method], Gf.Matrix4d(G.T.tolist()),
                            Vt.Matrix4dArray.FromNumpy(np.ascontiguousarray(M.transpose(0, 2, 1))),
                            Vt.IntArray.FromNumpy(idx.ravel()), Vt.FloatArray.FromNumpy(w.ravel()),
                            idx.shape[1], vp)
    assert ok
    return np.asarray(vp, dtype=np.float64)


def usd_skin_normals(method, G, M, idx, w, normals):
    """UsdSkel.SkinNormals with inverse-transpose 3×3s, as UsdSkel's own skinning query builds."""
    vn = Vt.Vec3fArray.FromNumpy(np.ascontiguousarray(normals, dtype=np.float32))
    inv_t = np.linalg.inv(M[:, :3, :3]).transpose(0, 2, 1)
    g = np.linalg.inv(G[:3, :3]).T
    ok = UsdSkel.SkinNormals(TOKENS[method], Gf.Matrix3d(g.T.tolist()),
                             Vt.Matrix3dArray.FromNumpy(
                                 np.ascontiguousarray(inv_t.transpose(0, 2, 1))),
                             Vt.IntArray.FromNumpy(idx.ravel()), Vt.FloatArray.FromNumpy(w.ravel()),
                             idx.shape[1], vn)
    assert ok
    return np.asarray(vn, dtype=np.float64)


def rel_err(a, b):
    return np.abs(np.asarray(a, np.float64) - b).max() / max(np.abs(b).max(), 1e-12)


@pytest.mark.parametrize("F", [1, 3], ids=["one_frame", "frames"])
@pytest.mark.parametrize("nonrigid", [False, True], ids=["rigid", "nonrigid"])
@pytest.mark.parametrize("K", [1, 4, 8, 11])
@pytest.mark.parametrize("method", ["lbs", "dqs"])
def test_points_match_usdskel(device, method, K, nonrigid, F):
    """One frame (the one-frame kernels) and several (frame blocks); one to three influence
    groups (the blends' straight-line group 0 and their loop over the others); the one-shot
    call (input order, pivot searched) and a Skinner (sorted layout: DQS's plain kernels)."""
    rng = np.random.default_rng(100 + K + 10 * nonrigid + 100 * F)
    points, idx, w, M, G = random_rig(rng, K=K, nonrigid=nonrigid, F=F)
    ours = dqskin.skin_points(points, idx, w, M, method, geom_bind_transform=G, device=device)
    assert ours.shape == (M.shape[0], points.shape[0], 3) and ours.dtype == np.float32
    skinner = dqskin.Skinner(points, idx, w, geom_bind_transform=G, device=device)
    sorted_layout = skinner.skin(M, method)
    for f in range(M.shape[0]):
        usd = usd_skin_points(method, G, M[f], idx, w, points)
        assert rel_err(ours[f], usd) <= 1e-5
        assert rel_err(sorted_layout[f], usd) <= 1e-5


@pytest.mark.parametrize("nonrigid", [False, True], ids=["rigid", "nonrigid"])
@pytest.mark.parametrize("K", [1, 4, 8])
@pytest.mark.parametrize("method", ["lbs", "dqs"])
def test_normals_match_usdskel(device, method, K, nonrigid):
    rng = np.random.default_rng(200 + K + 10 * nonrigid)
    points, idx, w, M, G = random_rig(rng, K=K, nonrigid=nonrigid)
    n = rng.normal(size=points.shape)
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    ours = dqskin.skin_normals(n, idx, w, M, method, geom_bind_transform=G, device=device)
    for f in range(M.shape[0]):
        assert np.abs(ours[f] - usd_skin_normals(method, G, M[f], idx, w, n)).max() <= 1e-5


def numpy_lbs(points, idx, w, M):
    """float64 LBS straight from the equation p' = Σ wᵢ Mᵢ p."""
    ph = np.concatenate([points, np.ones((len(points), 1))], 1).astype(np.float64)
    return np.einsum("vk,vkij,vj->vi", w.astype(np.float64), M[idx], ph)[:, :3]


def numpy_dqs(points, idx, w, M):
    """float64 DQS of rigid transforms: DLB with pivot = largest weight, then rotate+translate."""
    q = Rotation.from_matrix(M[:, :3, :3]).as_quat()[:, [3, 0, 1, 2]]  # (w, x, y, z)
    t = M[:, :3, 3]

    def qmul(a, b):
        aw, ax, ay, az = np.moveaxis(a, -1, 0)
        bw, bx, by, bz = np.moveaxis(b, -1, 0)
        return np.stack([aw * bw - ax * bx - ay * by - az * bz,
                         aw * bx + ax * bw + ay * bz - az * by,
                         aw * by - ax * bz + ay * bw + az * bx,
                         aw * bz + ax * by - ay * bx + az * bw], -1)

    d = 0.5 * qmul(np.concatenate([np.zeros((len(t), 1)), t], 1), q)
    qr, qd = q[idx], d[idx]  # (V, K, 4)
    pivot = qr[np.arange(len(idx)), np.argmax(w, axis=1)]
    sign = np.where(np.einsum("vki,vi->vk", qr, pivot) < 0, -1.0, 1.0) * w
    br, bd = np.einsum("vk,vki->vi", sign, qr), np.einsum("vk,vki->vi", sign, qd)
    n = np.linalg.norm(br, axis=1, keepdims=True)
    br, bd = br / n, bd / n
    bd -= np.sum(br * bd, 1, keepdims=True) * br
    conj = br * np.array([1, -1, -1, -1])
    rotated = qmul(qmul(br, np.concatenate([np.zeros((len(points), 1)), points], 1)), conj)[:, 1:]
    trans = 2 * qmul(bd, conj)[:, 1:]
    return rotated + trans


@pytest.mark.parametrize("method,oracle", [("lbs", numpy_lbs), ("dqs", numpy_dqs)])
def test_points_match_numpy_float64(device, method, oracle):
    rng = np.random.default_rng(7)
    points, idx, w, M, _ = random_rig(rng, K=4, F=2)
    ours = dqskin.skin_points(points, idx, w, M, method, device=device)
    for f in range(2):
        assert rel_err(ours[f], oracle(points, idx, w, M[f])) <= 1e-5


def test_identity_pose_returns_rest(device):
    rng = np.random.default_rng(1)
    points, idx, w, _, _ = random_rig(rng)
    eye = np.tile(np.eye(4), (12, 1, 1))
    for method in ("lbs", "dqs"):
        np.testing.assert_allclose(dqskin.skin_points(points, idx, w, eye, method, device=device),
                                   points, atol=1e-5)


def test_single_joint_vertex_moves_rigidly(device):
    rng = np.random.default_rng(2)
    points, idx, w, M, _ = random_rig(rng, K=4, F=1)
    idx[:, :] = 3
    for method in ("lbs", "dqs"):
        out = dqskin.skin_points(points, idx, w, M[0], method, device=device)
        np.testing.assert_allclose(out, points @ M[0, 3, :3, :3].T + M[0, 3, :3, 3], atol=2e-5)


def twist_ring(theta, n=64):
    """A unit ring at the joint of a two-joint chain along x, weights ½/½; child twisted by θ."""
    a = np.linspace(0, 2 * np.pi, n, endpoint=False)
    ring = np.stack([np.zeros(n), np.cos(a), np.sin(a)], 1)
    idx = np.tile([0, 1], (n, 1))
    w = np.full((n, 2), 0.5)
    M = np.tile(np.eye(4), (2, 1, 1))
    M[1, :3, :3] = Rotation.from_rotvec([theta, 0, 0]).as_matrix()
    return ring, idx, w, M


@pytest.mark.parametrize("theta", [np.pi / 2, np.pi * 0.999, np.pi])
def test_twist_keeps_radius_with_dqs_and_collapses_with_lbs(device, theta):
    ring, idx, w, M = twist_ring(theta)
    dqs = dqskin.skin_points(ring, idx, w, M, "dqs", device=device)
    lbs = dqskin.skin_points(ring, idx, w, M, "lbs", device=device)
    np.testing.assert_allclose(np.linalg.norm(dqs[:, 1:], axis=1), 1.0, atol=1e-5)
    # closed form for LBS with w = ½: r = √(1 − 2w(1−w)(1−cos θ)) = |cos(θ/2)|
    np.testing.assert_allclose(np.linalg.norm(lbs[:, 1:], axis=1), abs(np.cos(theta / 2)),
                               atol=1e-5)


def _launch_dqs(prep, sk):
    """The general one-vertex DQS kernel (residual path compiled in; not the CPU's packets)."""
    j = prep["joints"]
    F, V = j.dqs.shape[0], sk.vertex_count
    out = wp.empty((F, V), dtype=wp.vec3, device=sk.device)
    kernel = K.SKIN_POINTS_KERNELS[(K.DQS, True, F == 1, "sorted", False)]
    K.launch_frames(kernel, V, F, [*K.frame_rows_array(sk._points, V), sk._inf,
                                   K._flat(j.affines), K._flat(j.dqs), K._flat(j.residuals),
                                   j.has_residual, j.affines.shape[1], F, 0],
                    [out, wp.empty(0, dtype=wp.int32, device=sk.device)], sk.device)
    return out.numpy()


def test_flipping_joint_dq_sign_changes_nothing(device):
    rng = np.random.default_rng(3)
    points, idx, w, M, _ = random_rig(rng, F=2)
    sk = dqskin.Skinner(points, idx, w, device=device)
    prep, _, _ = sk._prepare(M)
    ref = _launch_dqs(prep, sk)
    dq = prep["joints"].dqs.numpy()
    flip = rng.random(dq.shape[:2]) < 0.5
    dq[flip] *= -1
    prep["joints"].dqs = wp.array(dq, dtype=vec8, device=device)
    assert flip.any()
    np.testing.assert_allclose(_launch_dqs(prep, sk), ref, atol=1e-5)


def test_blend_mixes_lbs_and_dqs(device):
    rng = np.random.default_rng(4)
    points, idx, w, M, _ = random_rig(rng, F=2)
    b = rng.random(len(points))
    lbs = dqskin.skin_points(points, idx, w, M, "lbs", device=device)
    dqs = dqskin.skin_points(points, idx, w, M, "dqs", device=device)
    mix = dqskin.skin_points(points, idx, w, M, "blend", blend_weights=b, device=device)
    np.testing.assert_allclose(mix, (1 - b[:, None]) * lbs + b[:, None] * dqs, atol=1e-4)


def test_tangents_follow_linear_part(device):
    rng = np.random.default_rng(5)
    points, idx, w, M, _ = random_rig(rng, K=1, F=1, nonrigid=True)
    t = rng.normal(size=points.shape)
    sk = dqskin.Skinner(points, idx, w, device=device)
    ours = sk.skin_vectors(M[0], t, "lbs", kind="tangent")
    ref = np.einsum("vij,vj->vi", M[0][idx[:, 0], :3, :3], t)
    np.testing.assert_allclose(ours, ref / np.linalg.norm(ref, axis=1, keepdims=True), atol=1e-5)


def test_face_varying_normals_use_their_vertex(device):
    rng = np.random.default_rng(6)
    points, idx, w, M, _ = random_rig(rng, F=1)
    n = rng.normal(size=points.shape)
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    fv = rng.integers(0, len(points), size=50)
    per_vertex = dqskin.skin_normals(n, idx, w, M[0], "dqs", device=device)
    face_varying = dqskin.skin_normals(n[fv], idx, w, M[0], "dqs", normal_vertex=fv, device=device)
    np.testing.assert_allclose(face_varying, per_vertex[fv], atol=1e-6)


def test_skinner_reuses_upload_and_accepts_warp_arrays(device):
    rng = np.random.default_rng(8)
    points, idx, w, M, _ = random_rig(rng, F=3)
    sk = dqskin.Skinner(points, idx, w, device=device)
    xw = wp.array(M.astype(np.float32), dtype=wp.mat44, device=device)
    out = sk.skin(xw, "dqs", as_warp=True)
    assert isinstance(out, wp.array) and out.shape == (3, len(points))
    np.testing.assert_allclose(out.numpy(), np.stack([sk.skin(m, "dqs") for m in M]), atol=1e-6)


def test_per_frame_rest_points(device):
    rng = np.random.default_rng(9)
    points, idx, w, M, _ = random_rig(rng, F=2)
    shapes = points[None] + rng.normal(size=(2,) + points.shape).astype(np.float32) * 0.1
    sk = dqskin.Skinner(points, idx, w, device=device)
    out = sk.skin(M, "lbs", points=shapes)
    for f in range(2):
        assert rel_err(out[f], numpy_lbs(shapes[f], idx, w, M[f])) <= 1e-5


@pytest.mark.parametrize("kwargs,match", [
    (dict(idx_hi=True), "out of range"),
    (dict(nan=True), "NaN"),
    (dict(neg=True), "negative weight"),
    (dict(shape=True), "skinning_transforms"),
    (dict(method="cubic"), "method must be one of"),
])
def test_bad_input_raises(kwargs, match):
    rng = np.random.default_rng(10)
    points, idx, w, M, _ = random_rig(rng, F=1)
    if kwargs.get("idx_hi"):
        idx[0, 0] = 99
    if kwargs.get("nan"):
        w[1, 1] = np.nan
    if kwargs.get("neg"):
        w[2, 0] = -0.5
    xf = M[0, :, :3, :] if kwargs.get("shape") else M[0]
    with pytest.raises(ValueError, match=match):
        dqskin.skin_points(points, idx, w, xf, kwargs.get("method", "dqs"), device="cpu")


def test_inputs_not_modified():
    rng = np.random.default_rng(11)
    points, idx, w, M, G = random_rig(rng, F=2)
    copies = [a.copy() for a in (points, idx, w, M, G)]
    dqskin.skin_points(points, idx, w, M, "dqs", geom_bind_transform=G, device="cpu")
    for a, c in zip((points, idx, w, M, G), copies):
        np.testing.assert_array_equal(a, c)


@pytest.mark.parametrize("V,F", [(50, 2000), (300, 370), (40000, 3), (100003, 2)],
                         ids=["frames", "mixed", "rows", "pieces"])
@pytest.mark.parametrize("method", ["lbs", "dqs"])
def test_frame_blocks_and_threads_cover_the_grid(device, monkeypatch, V, F, method):
    """Every (frame, vertex) is skinned once whichever way the grid is split: many frames and few
    vertices (split by frame blocks, a partial last block), few frames and many vertices (split
    by vertices), with 3 worker threads; a grid large enough for more pieces than threads
    (:data:`~dqskin.kernels.grid.PIECES_PER_THREAD`, taken in turn: ragged last pieces)."""
    monkeypatch.setenv("DQSKIN_THREADS", "3")
    calls, pieces = [], []
    real, launch = grid._pool_map, grid._launch
    monkeypatch.setattr(grid, "_pool_map", lambda tasks: (calls.append(len(tasks)), real(tasks)))
    monkeypatch.setattr(grid, "_launch", lambda k, dim, *a: (
        pieces.append(dim[0]) if k.key.startswith("skin_") else None, launch(k, dim, *a)))
    rng = np.random.default_rng(V + F)
    points, idx, w, M, _ = random_rig(rng, V=V, K=4, J=6, F=F)
    ours = dqskin.skin_points(points, idx, w, M, method, device=device)
    if device == "cpu":
        assert calls and calls[-1] == 3  # the grid really was split three ways
        assert (len(pieces) > 3) == (V > 50000), pieces  # in more pieces where it is large
    oracle = numpy_lbs if method == "lbs" else numpy_dqs
    for f in range(F):
        assert rel_err(ours[f], oracle(points, idx, w, M[f])) <= 1e-5, f


def test_rigid_fast_path_is_taken_and_equals_the_general_kernel(device, monkeypatch):
    """Launches without scale/shear use skin_dqs_rigid_kernel (on the CPU the packet kernel,
    which skips the residual blend by the frame's flag); it gives the float64 DQS of the
    equations, as the general one-vertex kernel (residual path compiled in) does."""
    rng = np.random.default_rng(12)
    points, idx, w, M, _ = random_rig(rng, F=2)
    sk = dqskin.Skinner(points, idx, w, device=device)
    launched = []
    real = grid._launch  # every launch goes through it (replayed or not)
    monkeypatch.setattr(grid, "_launch",
                        lambda k, *a, **kw: (launched.append(k.key), real(k, *a, **kw)))
    fast = sk.skin(M, "dqs")
    fast_kernel = "_packet" if wp.get_device(device).is_cpu else "skin_dqs_rigid_kernel"
    assert any(fast_kernel in name for name in launched)
    monkeypatch.setattr(grid, "_launch", real)
    prep, _, _ = sk._prepare(M)
    general = _launch_dqs(prep, sk)
    for f in range(M.shape[0]):
        want = numpy_dqs(points, idx, w, M[f])
        assert rel_err(fast[f], want) <= 1e-5, f
        assert rel_err(general[f], want) <= 1e-5, f


@pytest.mark.parametrize("layout", ["per_frame", "strided", "broadcast"])
@pytest.mark.parametrize("method", ["lbs", "dqs"])
def test_point_launcher_reads_any_frame_layout(device, layout, method):
    """The flat point kernels over two frame blocks (F = 20, one partial) with (F, V) rest points
    contiguous, strided (every other row of a wider array: copied) or one row broadcast to every
    frame (stride 0: the row read for every frame; copied, as it is strided here), against the
    float64 oracles. V = 37: the packet kernels' last packet of every frame has five vertices."""
    rng = np.random.default_rng(21)
    F, V = 20, 37
    points, idx, w, M, _ = random_rig(rng, V=V, F=F)
    shapes = (points[None] + rng.normal(size=(F, V, 3)) * 0.1).astype(np.float32)
    if layout == "broadcast":
        shapes[:] = shapes[0]
    sk = dqskin.Skinner(points, idx, w, device=device)
    prep, _, _ = sk._prepare(M)
    wide = wp.array(np.repeat(shapes, 2, axis=1), dtype=wp.vec3, device=device)  # (F, 2V)
    src = {"per_frame": wp.array(shapes, dtype=wp.vec3, device=device),
           "strided": wp.array(ptr=wide.ptr, shape=(F, V), strides=(24 * V, 24), dtype=wp.vec3,
                               device=device),
           "broadcast": wp.array(ptr=wide.ptr, shape=(F, V), strides=(0, 24), dtype=wp.vec3,
                                 device=device)}[layout]
    out = wp.empty((F, V), dtype=wp.vec3, device=device)
    K.skin_points(method=K.LBS if method == "lbs" else K.DQS, points=src, influences=sk._inf,
                  joints=prep["joints"], rigid=True, out=out, device=device)
    oracle = numpy_lbs if method == "lbs" else numpy_dqs
    got = out.numpy()
    for f in range(F):
        assert rel_err(got[f], oracle(shapes[f], idx, w, M[f])) <= 1e-5, f


@pytest.mark.parametrize("method", ["lbs", "dqs"])
def test_joint_preparation_split_across_threads(device, monkeypatch, method):
    """Many (frame, joint) transforms (a crowd's) are prepared in chunks on several threads; one
    scaled joint in one frame sets that frame's residual flag only (DQS then takes the residual
    kernel for it), whichever chunk it falls in. Against UsdSkel's C++ SkinPoints per frame."""
    monkeypatch.setenv("DQSKIN_THREADS", "3")
    tasks = []
    real = grid._pool_map
    monkeypatch.setattr(grid, "_pool_map", lambda t: (tasks.append(len(t)), real(t)))
    rng = np.random.default_rng(31)
    F, J = 4, 4000
    points, idx, w, M, G = random_rig(rng, V=3000, K=4, J=J, F=F)
    M[2, 1234, :3, :3] *= 1.5  # frame 2 has a residual, in the middle chunk
    idx[:50, 0] = 1234
    skinner = dqskin.Skinner(points, idx, w, geom_bind_transform=G, device=device)
    ours = skinner.skin(M, method)
    if device == "cpu":
        assert tasks[:1] == [3]  # the preparation (16,000 rows) was split three ways
    for f in range(F):
        assert rel_err(ours[f], usd_skin_points(method, G, M[f], idx, w, points)) <= 1e-5, f
    if method == "dqs":
        flags = skinner._cache[("has_residual", F, J)]
        flags = flags if isinstance(flags, np.ndarray) else flags.numpy()
        assert list(np.asarray(flags) != 0) == [False, False, True, False]
