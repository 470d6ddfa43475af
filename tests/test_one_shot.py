"""The one-shot API (``skin_points``) and small calls: the influence layout built on the device,
float32 uploads that skip an identity geom-bind transform, reused per-shape transform buffers and
replayed launches -- all against float64 NumPy written from the equations."""

import numpy as np
import pytest
import warp as wp
from scipy.spatial.transform import Rotation

import dqskin
from dqskin.influences import Influences

EMPTY_BLEND = wp.empty(0, dtype=float, device="cpu")
EMPTY_CENTERS = wp.empty(0, dtype=wp.vec4, device="cpu")


def lbs64(points, idx, w, M, geom_bind=np.eye(4)):
    """``Σ wᵢ·Mᵢ·G·p`` in float64."""
    p = np.asarray(points, np.float64) @ geom_bind[:3, :3].T + geom_bind[:3, 3]
    A = np.einsum("vk,vkij->vij", np.asarray(w, np.float64), M[idx])
    return np.einsum("vij,vj->vi", A[:, :3, :3], p) + A[:, :3, 3]


def rig(rng, V=500, J=12, K=4):
    points = rng.normal(size=(V, 3)).astype(np.float32)
    idx = rng.integers(0, J, size=(V, K)).astype(np.int32)
    w = rng.random((V, K)).astype(np.float32)
    w /= w.sum(1, keepdims=True)
    M = np.tile(np.eye(4), (J, 1, 1))
    M[:, :3, :3] = Rotation.random(J, random_state=rng).as_matrix()
    M[:, :3, 3] = rng.normal(size=(J, 3))
    return points, idx, w, M


@pytest.mark.parametrize("K", [1, 3, 4, 5, 8, 9])
def test_device_layout_is_the_stable_descending_sort(K):
    """The layout kernel ranks each vertex's influences as NumPy's stable argsort of -w does,
    ties included (first input first), zero-padded to groups of four."""
    rng = np.random.default_rng(K)
    V = 300
    w = rng.integers(0, 4, size=(V, K)).astype(np.float32) / 4  # many ties and zeros
    idx = rng.integers(0, 50, size=(V, K))
    inf = Influences(idx, w)
    dev = inf.layout("cpu", blend=EMPTY_BLEND, centers=EMPTY_CENTERS)
    order = np.argsort(-w, axis=1, kind="stable")
    C = -(-K // 4)
    want_i = np.zeros((V, 4 * C), np.int32)
    want_w = np.zeros((V, 4 * C), np.float32)
    want_i[:, :K] = np.take_along_axis(idx, order, 1)
    want_w[:, :K] = np.take_along_axis(w, order, 1)
    np.testing.assert_array_equal(dev.indices.numpy().reshape(V, -1), want_i)
    np.testing.assert_array_equal(dev.weights.numpy().reshape(V, -1), want_w)
    # and the host layout (what metrics read) agrees
    np.testing.assert_array_equal(inf.indices.reshape(V, -1), want_i)
    np.testing.assert_array_equal(inf.order, order)


def test_no_influences_layout():
    inf = Influences(np.zeros((5, 0), np.int32), np.zeros((5, 0), np.float32))
    dev = inf.layout("cpu", blend=EMPTY_BLEND, centers=EMPTY_CENTERS)
    assert dev.indices.shape == (5,) and dev.groups == 1
    assert not dev.weights.numpy().any()


@pytest.mark.parametrize("geom_bind", ["identity", "affine"])
def test_skin_points_matches_float64_lbs(geom_bind):
    rng = np.random.default_rng(3)
    points, idx, w, M = rig(rng)
    G = np.eye(4)
    if geom_bind == "affine":
        G[:3, :3] = Rotation.random(random_state=rng).as_matrix() * 1.7
        G[:3, 3] = [0.5, -2.0, 3.0]
    got = dqskin.skin_points(points, idx, w, M, "lbs", geom_bind_transform=G)
    assert got.dtype == np.float32
    np.testing.assert_allclose(got, lbs64(points, idx, w, M, G), atol=2e-5)


def test_skin_points_accepts_float64_and_integer_points():
    rng = np.random.default_rng(4)
    points, idx, w, M = rig(rng, V=50)
    pi = np.round(points * 10).astype(np.int64)
    np.testing.assert_allclose(dqskin.skin_points(pi, idx, w, M, "lbs"),
                               lbs64(pi, idx, w, M), atol=1e-4)
    np.testing.assert_allclose(dqskin.skin_points(points.astype(np.float64), idx, w, M, "lbs"),
                               lbs64(points, idx, w, M), atol=2e-5)


def test_repeated_calls_reuse_buffers_without_aliasing_results():
    """Each call refills the same transform buffer and replays the same launches: results of
    earlier calls stay as they were, every call sees its own transforms."""
    rng = np.random.default_rng(5)
    points, idx, w, _ = rig(rng, V=64)
    sk = dqskin.Skinner(points, idx, w)
    poses = [rig(rng, V=1)[3] for _ in range(4)]
    results = [sk.skin(M, "lbs") for M in poses]
    for M, got in zip(poses, results):
        np.testing.assert_allclose(got, lbs64(points, idx, w, M), atol=2e-5)
    batch = np.stack(poses)
    np.testing.assert_allclose(sk.skin(batch, "lbs"),
                               np.stack([lbs64(points, idx, w, M) for M in poses]), atol=2e-5)


@pytest.mark.parametrize("bad", [np.nan, np.inf, 1e39])
def test_bad_transforms_still_named_by_frame_and_joint(bad):
    rng = np.random.default_rng(6)
    points, idx, w, M = rig(rng, V=8)
    F = np.stack([M, M, M])
    F[2, 7, 0, 3] = bad
    sk = dqskin.Skinner(points, idx, w)
    with pytest.raises(ValueError, match="skinning_transforms: .*frame 2, joint 7"):
        sk.skin(F, "lbs")
    sk.skin(M, "lbs")  # the skinner is still usable


def test_points_not_finite_rejected():
    rng = np.random.default_rng(7)
    points, idx, w, M = rig(rng, V=8)
    points[3, 1] = np.nan
    with pytest.raises(ValueError, match="points: NaN or infinite"):
        dqskin.skin_points(points, idx, w, M)


def test_warp_array_input_on_device_used_in_place():
    rng = np.random.default_rng(8)
    points, idx, w, M = rig(rng, V=32)
    sk = dqskin.Skinner(points, idx, w, device="cpu")
    x = wp.array(M[None].astype(np.float32), dtype=wp.mat44, device="cpu")
    np.testing.assert_allclose(sk.skin(x, "lbs")[0], lbs64(points, idx, w, M), atol=2e-5)


@pytest.mark.skipif(wp.get_cuda_device_count() > 0, reason="a CUDA device is present: "
                    "tools/gpu_check.py would run its full check")
def test_gpu_check_without_cuda_says_so_and_exits_0():
    import subprocess
    import sys
    from pathlib import Path

    tool = Path(__file__).resolve().parents[1] / "tools" / "gpu_check.py"
    proc = subprocess.run([sys.executable, str(tool)], capture_output=True, text=True,
                          timeout=120)
    assert proc.returncode == 0, proc.stderr
    assert "no CUDA device" in proc.stdout


def test_strided_inputs_used_in_place_give_the_same_result():
    """The one-shot path reads the caller's arrays in place on the CPU: strided views too."""
    rng = np.random.default_rng(9)
    points, idx, w, M = rig(rng, V=40)
    p4 = np.concatenate([points, np.ones((40, 1), np.float32)], 1)
    w8 = np.repeat(w, 2, axis=1)
    got = dqskin.skin_points(p4[:, :3], idx, w8[:, ::2], M, "lbs")
    np.testing.assert_allclose(got, lbs64(points, idx, w, M), atol=2e-5)


def dqs64(points, idx, w, M):
    """Float64 DQS from the equations: quaternions of each rotation, signs against the vertex's
    largest weight (first on ties, as UsdSkel), normalized blend applied to the points."""
    q = Rotation.from_matrix(M[:, :3, :3]).as_quat()[:, [3, 0, 1, 2]]  # (w, x, y, z)
    t = M[:, :3, 3]
    out = np.empty((len(points), 3))
    for v in range(len(points)):
        qs, ts = q[idx[v]], t[idx[v]]
        pivot = qs[np.argmax(w[v])]
        s = np.where(qs @ pivot < 0, -1.0, 1.0) * w[v]
        r = s @ qs
        # dual part of each joint, d = ½·(0, t)·q, blended with the same signs
        tq = np.stack([-np.einsum("ki,ki->k", ts, qs[:, 1:]),
                       *(ts * qs[:, :1] + np.cross(ts, qs[:, 1:])).T], 1) * 0.5
        d = s @ tq
        n = np.linalg.norm(r)
        r, d = r / n, d / n
        rot = Rotation.from_quat(r[[1, 2, 3, 0]])
        trans = 2.0 * (r[0] * d[1:] - d[0] * r[1:] + np.cross(r[1:], d[1:]))
        out[v] = rot.apply(points[v]) + trans
    return out


@pytest.mark.parametrize("K", [3, 4, 8])
def test_one_shot_dqs_finds_the_pivot_in_input_order(K):
    """One-shot calls keep the influences in input order (read in place for (V, 4k) int32) and
    the kernels search the largest weight: here it is never in the first slot, some are tied."""
    rng = np.random.default_rng(21)
    points, idx, w, M = rig(rng, V=300, J=12, K=K)
    idx = idx.astype(np.int32)
    w[:, 0] = 0.01
    w[::5, 1] = w[::5, -1] = 2.0  # ties: the first of them is the pivot
    got = dqskin.skin_points(points, idx, w, M, "dqs")
    np.testing.assert_allclose(got, dqs64(points, idx, w, M), atol=5e-5)


def residual_dqs64(points, idx, w, M):
    """UsdSkel's DQS of transforms with scale: ``p_s = Σ wᵢ·Sᵢ·p`` (``Sᵢ = Rᵢᵀ·Aᵢ``, polar
    rotation from the SVD), then the DQS of the rotations and translations (:func:`dqs64`)."""
    u, _, vt = np.linalg.svd(M[:, :3, :3])
    R = u @ vt
    S = np.transpose(R, (0, 2, 1)) @ M[:, :3, :3]
    ps = np.einsum("vk,vkij,vj->vi", np.asarray(w, np.float64), S[idx], points)
    rt = M.copy()
    rt[:, :3, :3] = R
    return dqs64(ps, idx, w, rt)


def test_replayed_launches_follow_every_call():
    """Small calls replay recorded launches with prebuilt argument blocks: each call still sees
    its own transforms, method and sign rule, frames with scale (the residual kernel) and
    without alternate, two skinners of one shape (the same recorded launches, other arrays) keep
    their own data, and results already returned are never overwritten."""
    rng = np.random.default_rng(30)
    points, idx, w, _ = rig(rng, V=40, J=10)
    points2, idx2, w2, _ = rig(rng, V=40, J=10)
    a, b = dqskin.Skinner(points, idx, w), dqskin.Skinner(points2, idx2, w2)
    kept = []
    for call in range(12):
        M = rig(rng, V=1, J=10)[3]
        scaled = call % 3 == 2
        if scaled:  # some joints scaled: the DQS residual path
            M[::2, :3, :3] *= 1.5
        for sk, (p, i, ww) in ((a, (points, idx, w)), (b, (points2, idx2, w2))):
            got = sk.skin(M, "lbs")
            np.testing.assert_allclose(got, lbs64(p, i, ww, M), atol=5e-5)
            kept.append((got, lbs64(p, i, ww, M)))
            want = (residual_dqs64 if scaled else dqs64)(p, i, ww, M)
            np.testing.assert_allclose(sk.skin(M, "dqs"), want, atol=5e-5)
    for got, want in kept:
        np.testing.assert_allclose(got, want, atol=5e-5)
    # other shapes, per-call points and output transforms between the same launches
    F = np.stack([rig(rng, V=1, J=10)[3] for _ in range(3)])
    np.testing.assert_allclose(a.skin(F, "lbs"), [lbs64(points, idx, w, m) for m in F],
                               atol=5e-5)
    moved = points + 1.0
    np.testing.assert_allclose(a.skin(F[0], "lbs", points=moved), lbs64(moved, idx, w, F[0]),
                               atol=5e-5)
    shift = np.eye(4)
    shift[:3, 3] = [1.0, 2.0, 3.0]
    np.testing.assert_allclose(a.skin(F[0], "lbs", output_transforms=shift),
                               lbs64(points, idx, w, F[0]) + [1.0, 2.0, 3.0], atol=5e-5)


def test_first_calls_from_threads_at_once_initialize_warp_once():
    """Four threads making a fresh process's first dqskin calls at the same moment (a pipeline's
    worker threads, a ``dask worker --nthreads 4``) make one Warp runtime, and every call
    succeeds. Warp's own ``wp.init`` is not thread-safe: each thread created a runtime, which
    cleared the module hashes another thread was loading kernels with (a ``KeyError`` in
    ``Module.load``, 7 runs in 30 of four threads skinning a scene). Runtime creation is slowed
    here so that every thread arrives while the first is still inside it."""
    import subprocess
    import sys
    script = """if True:
        import threading, time, traceback
        import numpy as np
        import warp as wp
        import warp._src.context as context
        wp.config.log_level = wp.LOG_ERROR
        made = []
        real = context.Runtime.__init__
        def slow(self, *args, **kwargs):
            made.append(threading.current_thread().name)
            time.sleep(0.3)
            real(self, *args, **kwargs)
        context.Runtime.__init__ = slow
        import dqskin
        points = np.random.default_rng(0).normal(size=(50, 3))
        idx, w = np.zeros((50, 1), np.int32), np.ones((50, 1), np.float32)
        M = np.tile(np.eye(4), (2, 1, 1))
        barrier, errors = threading.Barrier(4), []
        def work():
            barrier.wait()
            try:
                dqskin.forward_kinematics([-1, 0], M, device="cpu")
                out = dqskin.skin_points(points, idx, w, M, "dqs", device="cpu")
                assert np.allclose(out, points, atol=1e-5)
            except Exception:
                errors.append(traceback.format_exc())
        threads = [threading.Thread(target=work) for _ in range(4)]
        for t in threads: t.start()
        for t in threads: t.join()
        print("RUNTIMES", len(made), "ERRORS", len(errors))
        print(errors[0] if errors else "")
    """
    proc = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True,
                          timeout=300)
    assert proc.returncode == 0, proc.stderr
    assert "RUNTIMES 1 ERRORS 0" in proc.stdout, proc.stdout


def test_replayed_launches_from_two_threads():
    """Skinners replaying their launches on two threads at once (recorded launches are per
    thread); any exception in a thread fails the test."""
    import threading

    rng = np.random.default_rng(31)
    rigs = [rig(rng, V=30, J=8) for _ in range(2)]
    poses = [rig(rng, V=1, J=8)[3] for _ in range(20)]
    errors = []

    def work(points, idx, w, _):
        sk = dqskin.Skinner(points, idx, w)
        try:
            for M in poses:
                np.testing.assert_allclose(sk.skin(M, "dqs"), dqs64(points, idx, w, M),
                                           atol=5e-5)
        except Exception as exc:  # noqa: BLE001  (reported below, not lost in the thread)
            errors.append(exc)

    threads = [threading.Thread(target=work, args=r) for r in rigs]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert not errors, errors[0]


@pytest.mark.parametrize("dtype", [np.float32, np.float64, np.int32, np.int64])
def test_one_pass_checks_agree_with_elementwise_numpy(dtype):
    """``nonnegative_max`` (one pass over the bits) and ``within_float32`` (one sum of squares)
    against element-wise NumPy: every bad value is found wherever it is, -0.0 is non-negative,
    float32-range values in float64 pass, values beyond it do not."""
    from dqskin.validation import FLOAT32_MAX, nonnegative_max, within_float32

    rng = np.random.default_rng(32)
    a = (rng.random(1000) * 100).astype(dtype)
    assert nonnegative_max(a) == a.max() and within_float32(a) is None
    assert nonnegative_max(a[::2]) == a[::2].max()  # strided: min and max
    floats = np.dtype(dtype).kind == "f"
    bads = [-1, -0.5, np.nan, -np.nan, np.inf, -np.inf] if floats else [-1, -2**30]
    for where in (0, 517, a.size - 1):
        for bad in bads:
            b = a.copy()
            b[where] = bad
            assert nonnegative_max(b) is None, (bad, where)
            if floats:
                want = None if np.isfinite(bad) else "NaN or infinite"
                assert within_float32(b) == want, (bad, where)
    if floats:
        b = a.copy()
        b[3] = -0.0
        assert nonnegative_max(b) is None  # "look closer": the caller's min says -0.0 >= 0
        big = a.copy()
        big[:4] = FLOAT32_MAX  # in range, but the sum of squares overflows: min and max decide
        assert within_float32(big) is None
        if dtype == np.float64:
            big[5] = -np.nextafter(FLOAT32_MAX, np.inf)
            assert within_float32(big) == "beyond float32 range"
    long = rng.normal(size=20000).astype(dtype)  # past the one-thread BLAS length
    assert within_float32(long) is None
    for bad, want in ((np.nan, "NaN or infinite"), (1e39, "beyond float32 range")):
        if floats and (dtype == np.float64 or not np.isfinite(bad)):
            b = long.copy()
            b[12345] = bad
            assert within_float32(b) == want


def test_points_beyond_float32_refused():
    rng = np.random.default_rng(33)
    points, idx, w, M = rig(rng, V=8)
    p64 = points.astype(np.float64)
    p64[2, 0] = 1e39
    with pytest.raises(ValueError, match="points: beyond float32 range"):
        dqskin.skin_points(p64, idx, w, M)
    w[5, 1] = -0.0  # a negative zero weight is a zero weight
    np.testing.assert_allclose(dqskin.skin_points(points, idx, w, M, "lbs"),
                               lbs64(points, idx, w, M), atol=2e-5)


def test_recorded_launch_repacks_changed_arrays_and_mutated_structs():
    """The launch replay (kernels.grid) with its prebuilt argument block: a different array is
    packed again, a struct changed in place is copied again, scalars follow each call."""
    from dqskin.kernels import grid

    @wp.struct
    class Pair:
        src: wp.array(dtype=float)
        scale: float

    @wp.kernel
    def scaled_copy(pair: Pair, offset: float, row_offset: int, out: wp.array(dtype=float)):
        i = wp.tid() + row_offset
        out[i] = pair.src[i] * pair.scale + offset

    a = wp.array(np.arange(8, dtype=np.float32), dtype=float, device="cpu")
    b = wp.array(np.full(8, 10.0, np.float32), dtype=float, device="cpu")
    out = wp.zeros(8, dtype=float, device="cpu")
    pair = Pair()
    pair.src, pair.scale = a, 2.0
    for step, (src, scale, offset) in enumerate([(a, 2.0, 0.0), (a, 3.0, 0.0), (b, 3.0, 1.0),
                                                 (a, 3.0, 5.0), (b, 0.5, 5.0)]):
        pair.src, pair.scale = src, scale  # the same struct object, changed in place
        other = wp.zeros(8, dtype=float, device="cpu") if step == 3 else out
        grid.launch_rows(scaled_copy, 8, [pair, offset], [other], "cpu")
        want = src.numpy() * scale + offset
        np.testing.assert_array_equal(other.numpy(), want)


def test_recorded_launch_keeps_no_array_alive_and_repacks_a_new_one():
    """A replayed launch holds its arguments weakly: arrays the caller drops are freed (a long
    Dask worker must not keep the last call's buffers), and a new array at a reused address is
    packed again, giving the right result."""
    import gc
    import weakref

    from dqskin.kernels import grid

    @wp.kernel
    def add_one(src: wp.array(dtype=float), row_offset: int, out: wp.array(dtype=float)):
        i = wp.tid() + row_offset
        out[i] = src[i] + 1.0

    refs = []
    for step in range(3):
        src = wp.array(np.full(16, float(step), np.float32), dtype=float, device="cpu")
        out = wp.zeros(16, dtype=float, device="cpu")
        grid.launch_rows(add_one, 16, [src], [out], "cpu")
        np.testing.assert_array_equal(out.numpy(), np.full(16, step + 1.0, np.float32))
        refs += [weakref.ref(src), weakref.ref(out)]
        del src, out
        gc.collect()
        assert all(r() is None for r in refs), f"step {step}: a launch kept an array alive"


def test_large_inputs_checked_on_two_threads_report_errors_in_order():
    """Above the size where points, indices and weights are checked on two threads, the errors
    are those of the one-thread order: points first, then indices, then weights."""
    V = 100_000
    rng = np.random.default_rng(34)
    points = rng.normal(size=(V, 3)).astype(np.float32)
    idx = rng.integers(0, 8, size=(V, 4)).astype(np.int32)
    w = np.full((V, 4), 0.25, np.float32)
    M = np.tile(np.eye(4), (8, 1, 1))
    bad_p, bad_i, bad_w = points.copy(), idx.copy(), w.copy()
    bad_p[V - 3, 2], bad_i[V - 2, 1], bad_w[V - 1, 3] = np.nan, -4, np.inf
    cases = [((bad_p, bad_i, bad_w), "points: NaN or infinite"),
             ((points, bad_i, bad_w), "joint_indices: negative index -4"),
             ((points, idx, bad_w), "joint_weights: NaN or infinite"),
             ((points, idx, -w), "joint_weights: negative weight -0.25")]
    for (p, i, ww), message in cases:
        with pytest.raises(ValueError, match=message):
            dqskin.skin_points(p, i, ww, M, "lbs")
    got = dqskin.skin_points(points, idx, w, M, "lbs")
    np.testing.assert_allclose(got, points, atol=1e-6)


def test_beside_runs_inline_on_a_pool_thread_and_raises_in_order():
    from dqskin.kernels import grid

    assert grid.beside(lambda: 1, lambda: 2) == (1, 2)
    # from inside the pool: inline, no waiting on the pool's own threads
    assert grid._get_pool().submit(grid.beside, lambda: 3, lambda: 4).result(timeout=30) == (3, 4)

    def fail(msg):
        raise ValueError(msg)

    with pytest.raises(ValueError, match="main"):
        grid.beside(lambda: fail("other"), lambda: fail("main"))
    with pytest.raises(ValueError, match="other"):
        grid.beside(lambda: fail("other"), lambda: 5)


def test_one_shot_calls_share_work_buffers_not_results():
    """One-shot calls on a thread reuse their work buffers: results of earlier calls (other
    vertex, joint and frame counts in between) are never overwritten."""
    rng = np.random.default_rng(35)
    kept = []
    for V, J, F in [(30, 6, 0), (50, 6, 0), (30, 9, 2), (30, 6, 0), (30, 6, 3)]:
        points, idx, w, _ = rig(rng, V=V, J=J)
        Ms = [rig(rng, V=1, J=J)[3] for _ in range(max(F, 1))]
        got = dqskin.skin_points(points, idx, w, np.stack(Ms) if F else Ms[0], "dqs")
        want = np.stack([dqs64(points, idx, w, M) for M in Ms])
        kept.append((got, want if F else want[0]))
    for got, want in kept:
        np.testing.assert_allclose(got, want, atol=5e-5)


@pytest.mark.parametrize("method", ["lbs", "dqs"])
@pytest.mark.parametrize("bad", ["nan point", "inf point", "negative index", "index J",
                                 "negative weight", "nan weight", "inf weight", "none"])
def test_values_checked_by_the_kernel_raise_as_the_host_does(monkeypatch, method, bad):
    """float32 points, (V, 4) int32 indices and float32 weights are read in place and their
    values checked by the packet kernel (no host pass): a bad value, in the last vertex of a
    tail packet, raises the ValueError the host checks raise for the same values given as
    float64 / int64; nothing is modified; good values give the float64 result."""
    from dqskin.kernels import skin as K

    rng = np.random.default_rng(31)
    points, idx, w, M = rig(rng, V=205)
    J = M.shape[0]
    if bad.endswith("point"):
        points[204, 0 if bad == "nan point" else 1] = np.nan if bad == "nan point" else np.inf
    elif bad.endswith("index") or bad == "index J":
        idx[204, 2] = -1 if bad == "negative index" else J
    elif bad != "none":
        w[204, 3] = {"negative weight": -0.5, "nan weight": np.nan, "inf weight": np.inf}[bad]
    given = [a.copy() for a in (points, idx, w)]
    checked = []
    real = K.skin_points
    monkeypatch.setattr(K, "skin_points", lambda **kw: (checked.append(kw["flags"] is not None),
                                                        real(**kw))[1])
    if bad == "none":
        got = dqskin.skin_points(points, idx, w, M, method, device="cpu")
        if method == "lbs":
            np.testing.assert_allclose(got, lbs64(points, idx, w, M), atol=2e-5)
        assert checked == [True]
        return
    with pytest.raises(ValueError) as kernel_checked:
        dqskin.skin_points(points, idx, w, M, method, device="cpu")
    assert checked == [True]  # the packet kernel checked them
    with pytest.raises(ValueError) as host_checked:
        dqskin.skin_points(points.astype(np.float64), idx.astype(np.int64), w.astype(np.float64),
                           M, method, device="cpu")
    assert checked == [True]  # the host's checks raised before any launch
    assert str(kernel_checked.value) == str(host_checked.value)
    assert str(kernel_checked.value).split(":")[0] in ("points", "joint_indices", "joint_weights")
    for a, b in zip((points, idx, w), given):
        np.testing.assert_array_equal(a, b)


@pytest.mark.parametrize("point", ["nan", "fine"])
@pytest.mark.parametrize("transforms", ["nan", "too few joints", "no joints"])
def test_several_bad_inputs_name_the_same_one_whatever_checks_them(transforms, point):
    """Bad transforms, with or without a bad point, in one call: the kernel-checked call
    (float32 in place) names what the host-checked call names (a bad point first, as the
    constructor does; then the transforms; then the index range they leave), not the transforms
    it uploads first nor its own joint-count message."""
    rng = np.random.default_rng(8)
    points, idx, w, M = rig(rng, V=64)
    if point == "nan":
        points[5, 1] = np.nan
    M = M.copy()
    if transforms == "nan":
        M[1, 0, 3] = np.nan
    else:
        M = M[:1] if transforms == "too few joints" else M[:0]
    with pytest.raises(ValueError) as kernel_checked:
        dqskin.skin_points(points, idx, w, M, "lbs", device="cpu")
    with pytest.raises(ValueError) as host_checked:
        dqskin.skin_points(points.astype(np.float64), idx.astype(np.int64),
                           w.astype(np.float64), M, "lbs", device="cpu")
    assert str(kernel_checked.value) == str(host_checked.value)
    first = {"nan": "points:"}.get(point) or {"nan": "skinning_transforms:"}.get(transforms,
                                                                               "joint_indices:")
    assert str(kernel_checked.value).startswith(first)


@pytest.mark.parametrize("method", ["lbs", "dqs"])
def test_zero_frames_give_an_empty_result(method):
    """(0, J, 4, 4) transforms: an empty (0, V, 3) result from the one-shot call and a Skinner
    (the frame-block launch once divided by the frame count)."""
    points, idx, w, M = rig(np.random.default_rng(2), V=20)
    none = np.zeros((0,) + M.shape)
    assert dqskin.skin_points(points, idx, w, none, method, device="cpu").shape == (0, 20, 3)
    sk = dqskin.Skinner(points, idx, w, device="cpu")
    assert sk.skin(none, method).shape == (0, 20, 3)


@pytest.mark.parametrize("count, min_chunk", [(8 * 4096, 4096), (125_000, 4096),
                                              (409_125, 256), (40_913, 256), (9 * 4096 + 7, 4096)])
def test_launch_rows_covers_every_row_once_in_pieces_that_shrink(monkeypatch, count, min_chunk):
    """Two threads take the pieces of a launch: every row runs exactly once; a launch of up to
    four minimum chunks a piece runs in equal pieces (4 a thread: a 1M-point frame as before);
    a larger one ends in pieces of at most 5 minimum chunks, so no thread waits long on the
    other's last piece (fixed pieces were an eighth of the launch each)."""
    from dqskin.kernels import grid

    @wp.kernel
    def count_rows(row_offset: int, out: wp.array(dtype=wp.int32)):
        i = wp.tid() + row_offset
        out[i] = out[i] + 1

    monkeypatch.setenv("DQSKIN_THREADS", "2")
    pieces = []
    launch = grid._launch

    def recorded(kernel, dim, args, device):
        pieces.append((args[0], dim[0]))
        launch(kernel, dim, args, device)

    monkeypatch.setattr(grid, "_launch", recorded)
    out = wp.zeros(count, dtype=wp.int32, device="cpu")
    grid.launch_rows(count_rows, count, [], [out], "cpu", min_chunk=min_chunk)
    np.testing.assert_array_equal(out.numpy(), np.ones(count, np.int32))
    starts = sorted(pieces)
    assert starts[0][0] == 0 and all(a + n == b for (a, n), (b, _) in zip(starts, starts[1:]))
    sizes = [n for _, n in starts]
    if count // 8 <= 4 * min_chunk:
        assert len(sizes) == 8 and max(sizes) - min(sizes) < min_chunk, sizes
    else:
        assert sizes[-1] <= 5 * min_chunk and len(sizes) <= 64, sizes


@pytest.mark.parametrize("rule", ["largest_weight", "running_sum"])
def test_one_shot_views_follow_the_callers_memory_and_keep_nothing_alive(rule):
    """A one-shot call reads the caller's float32 / int32 arrays in place through views kept by
    address and shape: later calls read values changed in place, a new array of points,
    indices or weights (the others the same objects), or arrays of another length at the same
    address, each give their own result, and no caller array outlives its last reference."""
    import gc
    import weakref

    from test_sign_reference import dqs_reference

    def want(points, idx, w, M):
        if rule == "largest_weight":
            return dqs64(points, idx, w, M)
        return dqs_reference(points.astype(np.float64), idx, w.astype(np.float64), M[None],
                             rule)[0]

    rng = np.random.default_rng(41)
    points, idx, w, M = rig(rng, V=45)
    store = np.zeros((45, 3), np.float32)  # views of 37 and 45 rows at one address
    calls = [lambda: (points, idx, w), lambda: (points * 1.5, idx, w),
             lambda: (points, idx[:, ::-1].copy(), w), lambda: (points, idx, w[:, ::-1].copy()),
             lambda: (store[:37], idx[:37], w[:37]), lambda: (store, idx, w)]
    for change in range(2):
        if change:  # in place
            points[:] = rng.normal(size=points.shape)
            idx[:] = rng.integers(0, 12, size=idx.shape)
            store[:] = rng.normal(size=store.shape)
        for i, call in enumerate(calls):
            p, ix, wt = call()
            got = dqskin.skin_points(p, ix, wt, M, "dqs", sign_reference=rule, device="cpu")
            np.testing.assert_allclose(got, want(p, ix, wt, M), atol=5e-5,
                                       err_msg=f"call {i}, change {change}")
    refs = []
    for V in (20, 20, 33):
        p, ix, wt, M = rig(rng, V=V)
        dqskin.skin_points(p, ix, wt, M, "dqs", sign_reference=rule, device="cpu")
        refs += [weakref.ref(a) for a in (p, ix, wt)]
        del p, ix, wt
        gc.collect()
        assert all(r() is None for r in refs), "a one-shot call kept a caller's array alive"
