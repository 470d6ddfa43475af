"""Degenerate and hostile numbers through the Python API: never a crash, never a silent wrong
number. Oracle: ``UsdSkel.SkinPoints`` (usd-core's C++ LBS and DQS, double precision)."""

import numpy as np
import pytest
from pxr import Gf, UsdSkel, Vt
from scipy.spatial.transform import Rotation

import dqskin
from dqskin.cli import default_asset
from dqskin.errors import LimitError
from dqskin.times import parse_frames, select_times


def usdskel(points, idx, w, xforms, method):
    """UsdSkel.SkinPoints on the same data (row-vector matrices at the boundary)."""
    pts = Vt.Vec3fArray.FromNumpy(np.asarray(points, np.float32))
    ok = UsdSkel.SkinPoints({"lbs": "classicLinear", "dqs": "dualQuaternion"}[method],
                            Gf.Matrix4d(1), Vt.Matrix4dArray([Gf.Matrix4d(m.T.tolist())
                                                              for m in xforms]),
                            Vt.IntArray.FromNumpy(np.asarray(idx, np.int32).ravel()),
                            Vt.FloatArray.FromNumpy(np.asarray(w, np.float32).ravel()),
                            idx.shape[1], pts)
    assert ok
    return np.asarray(pts, np.float64)


def rig(seed, V=64, J=5, K=3):
    rng = np.random.default_rng(seed)
    points = rng.normal(size=(V, 3))
    idx = rng.integers(0, J, size=(V, K))
    w = rng.random((V, K))
    w /= w.sum(1, keepdims=True)
    xf = np.tile(np.eye(4), (J, 1, 1))
    xf[:, :3, :3] = Rotation.random(J, random_state=seed).as_matrix()
    xf[:, :3, 3] = rng.normal(size=(J, 3))
    return points, idx, w, xf


@pytest.mark.parametrize("scale", [0.0, 1e-30, 1e-5, 1e-4, 3e-3, 1e-3, 1e6, 1e20, 1e30,
                                   (1.0, 1e-12, 1.0), (2.0, 0.0, 0.5), (1e20, 3e19, 1e18)])
@pytest.mark.parametrize("method", ["lbs", "dqs"])
def test_degenerate_and_huge_scales_match_usdskel(scale, method, device):
    """Zero, tiny and huge joint scales (uniform or per axis): DQS gives a zero dual quaternion
    to joints whose matrix GfMatrix4d::Factor cannot split (|det| < 1e-10), keeps huge scales, and
    LBS is the plain weighted sum; float32 agrees with UsdSkel's double to float32 precision of
    the largest coordinate."""
    points, idx, w, xf = rig(7)
    xf[[1, 3], :3, :3] = xf[[1, 3], :3, :3] @ np.diag(np.broadcast_to(scale, 3))
    ours = dqskin.skin_points(points, idx, w, xf, method, device=device).astype(np.float64)
    ref = usdskel(points, idx, w, xf, method)
    assert np.all(np.isfinite(ours))
    scale_of = max(1.0, np.abs(ref).max())
    assert np.abs(ours - ref).max() <= 2e-6 * scale_of, np.abs(ours - ref).max() / scale_of


def test_zero_scale_keeps_a_flat_symmetric_grid_flat(device):
    """A planar grid weighted half/half between the identity and a zero-scale joint: the
    zero-scale joint adds nothing to the DQ blend, so the grid stays in its plane (z = 0) and,
    with no other scale, where it was (UsdSkel's rule)."""
    x, y = np.meshgrid(np.linspace(-1, 1, 5), np.linspace(-1, 1, 5))
    grid = np.stack([x.ravel(), y.ravel(), np.zeros(25)], 1)
    xf = np.tile(np.eye(4), (2, 1, 1))
    xf[1, :3, :3] = 0.0
    xf[1, :3, 3] = (0.0, 0.0, 3.0)
    idx = np.tile([0, 1], (25, 1))
    ours = dqskin.skin_points(grid, idx, np.full((25, 2), 0.5), xf, "dqs", device=device)
    np.testing.assert_allclose(ours, grid, atol=1e-6)


@pytest.mark.parametrize("bad", [np.nan, np.inf, -np.inf, 1e39])
@pytest.mark.parametrize("method", ["lbs", "dqs", "blend"])
def test_non_finite_transforms_are_rejected_naming_frame_and_joint(bad, method, device):
    points, idx, w, xf = rig(3)
    frames = np.stack([xf] * 4)
    frames[2, 3, 1, 2] = bad
    with pytest.raises(ValueError, match=r"skinning_transforms: .*frame 2, joint 3"):
        dqskin.skin_points(points, idx, w, frames, method, device=device,
                           blend_weights=np.full(len(points), 0.5))


def test_no_influences_and_no_points(device):
    """K = 0 (no influence per point) no longer crashes the interpreter: LBS sums nothing (the
    origin), DQS blends nothing (points stay). V = 0 gives empty results of the right shape."""
    pts = np.arange(12.0).reshape(4, 3)
    none_i, none_w = np.zeros((4, 0), int), np.zeros((4, 0))
    xf = np.eye(4)[None]
    np.testing.assert_array_equal(dqskin.skin_points(pts, none_i, none_w, xf, "lbs",
                                                     device=device), np.zeros((4, 3)))
    np.testing.assert_array_equal(dqskin.skin_points(pts, none_i, none_w, xf, "dqs",
                                                     device=device), pts)
    empty = dqskin.skin_points(np.zeros((0, 3)), np.zeros((0, 2), int), np.zeros((0, 2)),
                               np.stack([xf] * 3), "dqs", device=device)
    assert empty.shape == (3, 0, 3)
    assert dqskin.skin_points(np.zeros((0, 3)), np.zeros((0, 2), int), np.zeros((0, 2)), xf,
                              "lbs", device=device).shape == (0, 3)


def test_complex_and_non_numeric_arrays_are_rejected():
    points, idx, w, xf = rig(1)
    for kwargs, name in ((dict(points=points + 1j), "points"),
                         (dict(joint_weights=w + 0j), "joint_weights"),
                         (dict(skinning_transforms=xf * (1 + 0j)), "skinning_transforms"),
                         (dict(points=np.full(points.shape, "x")), "points")):
        args = dict(points=points, joint_indices=idx, joint_weights=w, skinning_transforms=xf)
        args.update(kwargs)
        with pytest.raises(ValueError, match=name):
            dqskin.skin_points(**args, method="dqs", device="cpu")


def test_non_finite_points_and_times_are_rejected(device):
    points, idx, w, xf = rig(2)
    points[5, 1] = np.nan
    with pytest.raises(ValueError, match="points: NaN"):
        dqskin.skin_points(points, idx, w, xf, "dqs", device=device)
    scene = dqskin.load(default_asset())
    with pytest.raises(ValueError, match="finite times"):
        scene.skin([0.0, np.nan], device=device)


def test_frame_selections_are_exact_decimals_and_bounded():
    t = parse_frames("0:48:0.1")
    assert t[3] == 0.3 and t[-2] == 47.9 and t[-1] == 48.0
    assert parse_frames("1:500:0.1")[-1] == 500.0
    sub = select_times(np.arange(5.0), 24.0, frames="0:1:0.1", substeps=2)
    assert sub[1] == 0.05 and sub[3] == 0.15
    for kwargs, param in ((dict(frames="0:1e9"), "frames="), (dict(frames="0:10:1e-9"), "frames="),
                          (dict(fps=1e9), "fps="), (dict(substeps=1_000_000), "substeps=")):
        with pytest.raises(LimitError, match=f"^{param}.*limit of 100,000.*max_frames"):
            select_times(np.arange(49.0), 24.0, **kwargs)
    for kwargs in (dict(frames="nan:10"), dict(frames="0:inf"), dict(fps=np.nan),
                   dict(fps=np.inf)):
        with pytest.raises(ValueError, match="^f(rames|ps)="):
            select_times(np.arange(49.0), 24.0, **kwargs)
    assert select_times(np.arange(49.0), 24.0, frames="0:1e5", max_frames=200_000,
                        hold=True).size == 100_001
    # the limit on the animation's own times names them, not a --substeps 1 nobody passed
    with pytest.raises(ValueError, match="^the animation's time range selects 49 frames, "
                                         "more than the limit of 10"):
        select_times(np.arange(49.0), 24.0, max_frames=10)


def test_compare_refuses_huge_renders_before_writing(tmp_path):
    from dqskin.report.compare import run_compare

    out = tmp_path / "report"
    for kwargs in (dict(width=100_000), dict(supersample=64, width=512)):
        with pytest.raises(LimitError, match=r"raise max_rays"):
            run_compare(default_asset(), out, progress=False, sweeps_dir=None, **kwargs)
    assert not out.exists()


@pytest.mark.parametrize("method", ["lbs", "dqs", "blend"])
def test_device_arrays_are_used_unchecked_and_nan_propagates_alike(method, device):
    """Warp arrays are used in place (no host copy to check them): a NaN joint gives NaN points
    under every method, never plausible finite ones."""
    import warp as wp

    points, idx, w, xf = rig(4)
    xf[2, 0, 1] = np.nan
    sk = dqskin.Skinner(points, idx, w, blend_weights=np.full(len(points), 0.5), device=device)
    arr = wp.array(xf[None].astype(np.float32), dtype=wp.mat44, device=device)
    out = sk.skin(arr, method)[0]
    uses_2 = (idx == 2).any(axis=1)
    assert uses_2.any() and (~uses_2).any()
    assert np.isnan(out[uses_2]).any(axis=1).all()
    if method == "lbs":  # DQS may take the residual path for every point of the frame
        assert np.isfinite(out[~uses_2]).all()


def test_points_need_a_joint_and_singular_normals_stay_finite(device):
    pts = np.zeros((2, 3))
    with pytest.raises(ValueError, match="no joints"):
        dqskin.skin_points(pts, np.zeros((2, 0), int), np.zeros((2, 0)), np.zeros((0, 4, 4)),
                           "lbs", device=device)
    xf = np.tile(np.eye(4), (2, 1, 1))
    xf[1, :3, :3] = 0.0
    normals = np.tile([0.0, 0.0, 1.0], (2, 1))
    for method in ("lbs", "dqs"):
        out = dqskin.skin_normals(normals, [[0, 1], [1, 0]], [[0.5, 0.5], [1.0, 0.0]], xf,
                                  method, device=device)
        assert np.isfinite(out).all(), method


def test_mesh_arrays_are_frozen_without_freezing_the_callers():
    pts = np.zeros((3, 3), np.float32)
    mesh = dqskin.Mesh("m", pts, np.zeros((0, 3), np.int32), np.zeros((3, 1), np.int32),
                       np.ones((3, 1), np.float32))
    assert pts.flags.writeable and not mesh.points.flags.writeable
    with pytest.raises(ValueError):
        mesh.points[0, 0] = 1.0


def test_cli_limits_name_the_flag_and_write_nothing(tmp_path, capsys):
    from dqskin.cli import main

    asset = str(default_asset())
    cases = ((["skin", asset, "--out", str(tmp_path / "a" / "x.npz"), "--frames", "0:1e9"],
              "--max-frames"),
             (["skin", asset, "--out", str(tmp_path / "a" / "x.npz"), "--substeps", "1000000"],
              "--max-frames"),
             (["compare", asset, "--out", str(tmp_path / "a"), "--width", "100000"], "--max-rays"),
             (["compare", asset, "--out", str(tmp_path / "a"), "--supersample", "64"],
              "--max-rays"))
    for argv, flag in cases:
        assert main(argv) == 2, argv
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and flag in err[0], err
    assert not (tmp_path / "a").exists()
    out = tmp_path / "b" / "x.npz"
    assert main(["skin", asset, "--out", str(out), "--frames", "0:4:0.5", "--max-frames", "9",
                 "--device", "cpu"]) == 0
    assert out.is_file()
    assert main(["skin", asset, "--out", str(tmp_path / "c.npz"), "--frames", "0:4:0.5",
                 "--max-frames", "8"]) == 2


def test_algebra_refuses_complex_input():
    from dqskin import dq, quat

    with pytest.raises(ValueError, match="complex"):
        quat.normalize(np.array([1.0 + 1j, 0, 0, 0]))
    with pytest.raises(ValueError, match="complex"):
        dq.normalize(np.ones(8) * (1 + 0j))
