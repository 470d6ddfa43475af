"""The ``dqskin`` CLI end to end.

Outputs, and every bad-input case with its message and exit code.
"""

import hashlib
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

# Backslash-newlines inside GOOD only wrap long source lines; the text has no break there.
GOOD = """#usda 1.0
(
    defaultPrim = "Root"
    startTimeCode = 0
    endTimeCode = 2
    timeCodesPerSecond = 24
    upAxis = "Y"
)
def SkelRoot "Root" (
    prepend apiSchemas = ["SkelBindingAPI"]
)
{
    rel skel:skeleton = </Root/Skel>
    def Skeleton "Skel" (
        prepend apiSchemas = ["SkelBindingAPI"]
    )
    {
        uniform token[] joints = JOINTS
        uniform matrix4d[] bindTransforms = [((1,0,0,0),(0,1,0,0),(0,0,1,0),(0,0,0,1)), \
((1,0,0,0),(0,1,0,0),(0,0,1,0),(0,1,0,1))]
        uniform matrix4d[] restTransforms = [((1,0,0,0),(0,1,0,0),(0,0,1,0),(0,0,0,1)), \
((1,0,0,0),(0,1,0,0),(0,0,1,0),(0,1,0,1))]
        rel skel:animationSource = </Root/Skel/Anim>
        def SkelAnimation "Anim"
        {
            uniform token[] joints = ["a", "a/b"]
            float3[] translations = [(0,0,0), (0,1,0)]
            quatf[] rotations.timeSamples = {0: [(1,0,0,0), (1,0,0,0)], \
2: [(1,0,0,0), (0.70710678,0.70710678,0,0)]}
            half3[] scales = [(1,1,1), (1,1,1)]
        }
    }
    def Mesh "Mesh" (
        prepend apiSchemas = ["SkelBindingAPI"]
    )
    {
        int[] faceVertexCounts = [3, 3]
        int[] faceVertexIndices = [0, 1, 2, 0, 2, 3]
        point3f[] points = [(0,0,0), (1,0,0), (1,2,0), (0,2,0)]
        int[] primvars:skel:jointIndices = INDICES (
            interpolation = "vertex"
            elementSize = 2
        )
        float[] primvars:skel:jointWeights = WEIGHTS (
            interpolation = "vertex"
            elementSize = 2
        )
        rel skel:skeleton = </Root/Skel>
    }
}
"""
DEFAULTS = dict(JOINTS='["a", "a/b"]', INDICES="[0, 1, 0, 1, 1, 0, 1, 0]",
                WEIGHTS="[1, 0, 0.5, 0.5, 1, 0, 1, 0]")


def usda(tmp_path, name="rig.usda", **over):
    text = GOOD
    for key, value in {**DEFAULTS, **over}.items():
        text = text.replace(key, value)
    path = tmp_path / name
    path.write_text(text)
    return path


def run(*args):
    proc = subprocess.run([sys.executable, "-m", "dqskin.cli", *map(str, args)],
                          capture_output=True, text=True, timeout=300)
    return proc.returncode, proc.stdout, proc.stderr


def assert_clean_error(rc, err, *needles):
    assert rc == 2, err
    assert "Traceback" not in err
    lines = [ln for ln in err.splitlines() if ln.startswith("dqskin: error:")]
    assert len(lines) == 1, err
    for n in needles:
        assert n.lower() in lines[0].lower(), lines[0]


def test_skin_usd_to_npz_and_usd(tmp_path):
    src = usda(tmp_path)
    digest = hashlib.sha256(src.read_bytes()).hexdigest()
    rc, out, err = run("skin", src, "--out", tmp_path / "o.npz", "--method", "dqs")
    assert rc == 0, err
    data = np.load(tmp_path / "o.npz")
    pts = data["points_0"]
    assert pts.shape == (3, 4, 3)
    # closed form: vertex 0 and 1 at rest-bound joint a stay put; vertex 2, 3 bound to b rotate
    # 90° about x around b's origin (0, 1, 0) at t = 2
    np.testing.assert_allclose(pts[2, 0], [0, 0, 0], atol=1e-5)
    np.testing.assert_allclose(pts[2, 3], [0, 1, 1], atol=1e-5)
    np.testing.assert_allclose(pts[0], [[0, 0, 0], [1, 0, 0], [1, 2, 0], [0, 2, 0]], atol=1e-5)
    rc, out, err = run("skin", src, "--out", tmp_path / "o.usda", "--frames", "0:2")
    assert rc == 0, err
    assert (tmp_path / "o.usda").is_file()
    assert hashlib.sha256(src.read_bytes()).hexdigest() == digest  # input untouched


def test_skin_per_frame_mesh_files(tmp_path):
    src = usda(tmp_path)
    rc, out, err = run("skin", src, "--out", tmp_path / "f_{:03d}.ply", "--method", "lbs")
    assert rc == 0, err
    import trimesh
    for f in (0, 1, 2):
        m = trimesh.load(tmp_path / f"f_{f:03d}.ply", process=False)
        assert len(m.vertices) == 4 and len(m.faces) == 2


def test_info_lists_skeleton_and_meshes(tmp_path):
    rc, out, err = run("info", usda(tmp_path))
    assert rc == 0, err
    assert "2 joints" in out and "/Root/Mesh" in out and "problems" in out


def test_existing_output_needs_force(tmp_path):
    src = usda(tmp_path)
    out = tmp_path / "o.npz"
    out.write_bytes(b"precious")
    rc, _, err = run("skin", src, "--out", out)
    assert_clean_error(rc, err, "o.npz", "--force")
    assert out.read_bytes() == b"precious"
    rc, _, err = run("skin", src, "--out", out, "--force")
    assert rc == 0, err


def test_refuses_to_overwrite_input(tmp_path):
    src = usda(tmp_path)
    rc, _, err = run("skin", src, "--out", src, "--force")
    assert_clean_error(rc, err, "input")


@pytest.mark.parametrize("case,over,needles", [
    ("index_out_of_range", dict(INDICES="[0, 1, 0, 7, 1, 0, 1, 0]"), ["rig.usda", "out of range"]),
    ("nan_weight", dict(WEIGHTS="[1, 0, nan, 0.5, 1, 0, 1, 0]"), ["rig.usda", "nan"]),
    ("negative_weight", dict(WEIGHTS="[1, 0, -0.5, 0.5, 1, 0, 1, 0]"), ["rig.usda", "negative"]),
    ("mismatched_counts", dict(WEIGHTS="[1, 0, 0.5, 0.5, 1, 0]"), ["rig.usda", "/Root/Mesh"]),
    ("bad_joint_order", dict(JOINTS='["a/b", "a"]'), ["rig.usda", "/Root/Skel"]),
])
def test_bad_usd_input(tmp_path, case, over, needles):
    rc, _, err = run("skin", usda(tmp_path, **over), "--out", tmp_path / "o.npz")
    assert_clean_error(rc, err, *needles)
    assert not (tmp_path / "o.npz").exists()


def test_missing_file(tmp_path):
    rc, _, err = run("skin", tmp_path / "nope.usda", "--out", tmp_path / "o.npz")
    assert_clean_error(rc, err, "nope.usda")


@pytest.mark.parametrize("name", ["junk.usda", "junk.usdc", "junk.glb", "junk.gltf"])
def test_corrupt_file(tmp_path, name):
    path = tmp_path / name
    path.write_bytes(b"\x00\x01 this is not a valid file \xff" * 10)
    rc, _, err = run("info", path)
    assert_clean_error(rc, err, name)


def test_no_skeleton(tmp_path):
    path = tmp_path / "plain.usda"
    path.write_text('#usda 1.0\ndef Mesh "M"\n{\n    int[] faceVertexCounts = [3]\n'
                    '    int[] faceVertexIndices = [0, 1, 2]\n'
                    '    point3f[] points = [(0,0,0), (1,0,0), (0,1,0)]\n}\n')
    rc, _, err = run("skin", path, "--out", tmp_path / "o.npz")
    assert_clean_error(rc, err, "plain.usda")


def test_cycle_in_gltf_hierarchy(tmp_path):
    import pygltflib
    g = pygltflib.GLTF2()
    g.scenes = [pygltflib.Scene(nodes=[0])]
    g.nodes = [pygltflib.Node(children=[1]), pygltflib.Node(children=[0])]
    path = tmp_path / "cycle.gltf"
    g.save(str(path))
    rc, _, err = run("info", path)
    assert_clean_error(rc, err, "cycle.gltf")


def test_bad_arguments(tmp_path):
    src = usda(tmp_path)
    rc, _, err = run("skin", src, "--out", tmp_path / "o.npz", "--frames", "5:1")
    assert_clean_error(rc, err, "--frames")
    rc, _, err = run("skin", src, "--out", tmp_path / "o.xyz")
    assert_clean_error(rc, err, "unsupported")


def test_velocities_round_trip_in_units_per_second(tmp_path):
    """Velocities in the cache equal d(cached points)/dt × timeCodesPerSecond."""
    from pxr import Usd, UsdGeom
    asset = Path(__file__).resolve().parents[1] / "assets" / "twist_cylinder.usda"
    out = tmp_path / "twist.usdc"
    rc, _, err = run("skin", asset, "--out", out, "--method", "dqs", "--frames", "4:8",
                     "--substeps", "4")
    assert rc == 0, err
    stage = Usd.Stage.Open(str(out))
    tcps = stage.GetTimeCodesPerSecond()
    assert tcps == 24
    mesh = next(UsdGeom.Mesh(p) for p in stage.Traverse() if p.IsA(UsdGeom.Mesh))
    assert mesh.GetPointsAttr().GetTimeSamples() == [4 + k / 4 for k in range(17)]
    h = 0.25
    p0, p1 = (np.asarray(mesh.GetPointsAttr().Get(6 + s)) for s in (-h, h))
    v = np.asarray(mesh.GetVelocitiesAttr().Get(6))
    fd = (p1 - p0) / (2 * h) * tcps  # per second
    # a central difference over a 2·h·7.5° arc underestimates speed by sin(x)/x ≈ 1 − 3e-4
    scale = np.abs(fd).max()
    assert scale > 1.0
    np.testing.assert_allclose(v, fd, atol=2e-3 * scale)


@pytest.mark.parametrize("interp", ["sclerp", "dlb", "spline", "catmull-rom"])
def test_interp_keeps_key_poses(tmp_path, interp):
    """Every interpolation passes through the keys: integer frames equal the asset's own pose."""
    asset = Path(__file__).resolve().parents[1] / "assets" / "bending_arm.usda"
    base, other = tmp_path / "trs.npz", tmp_path / f"{interp}.npz"
    assert run("skin", asset, "--out", base, "--frames", "0:30:5")[0] == 0
    rc, _, err = run("skin", asset, "--out", other, "--frames", "0:30:5", "--interp", interp)
    assert rc == 0, err
    np.testing.assert_allclose(np.load(other)["points_0"], np.load(base)["points_0"], atol=1e-4)


def test_bad_chunk_and_device(tmp_path):
    src = usda(tmp_path)
    rc, _, err = run("skin", src, "--out", tmp_path / "o.npz", "--chunk", "0")
    assert_clean_error(rc, err, "--chunk")
    rc, _, err = run("skin", src, "--out", tmp_path / "o.npz", "--device", "cuda:7")
    assert_clean_error(rc, err, "cuda:7")


def test_sub_frame_times_cannot_share_file_names(tmp_path):
    src = usda(tmp_path)
    rc, _, err = run("skin", src, "--out", tmp_path / "f_{:03d}.obj", "--frames", "0:2:0.5")
    assert_clean_error(rc, err, "file names")
    assert not list(tmp_path.glob("f_*.obj"))


def test_blend_bakes_rigid_prims(shared_assets, tmp_path):
    """--method blend also covers prims skinned rigidly (baked as xformOp:transform)."""
    from pxr import Usd
    src = (shared_assets / "openusd/pxr/usd/usdSkel/testenv/testUsdSkelBakeSkinning/lbs.usda")
    out = tmp_path / "blend.usda"
    rc, _, err = run("skin", src, "--out", out, "--method", "blend", "--frames", "1:3")
    assert rc == 0, err
    stage = Usd.Stage.Open(str(out))
    rigid = [p for p in stage.Traverse() if p.HasAttribute("xformOp:transform")
             and p.GetAttribute("xformOp:transform").GetNumTimeSamples() == 3]
    assert rigid


def test_gltf_frame_files_follow_the_sample_rate(shared_assets, tmp_path):
    """glTF times are seconds: frames at --fps 30 are numbered at 30 per second."""
    src = shared_assets / "khronos-gltf" / "CesiumMan" / "CesiumMan.glb"
    rc, _, err = run("skin", src, "--out", tmp_path / "f_{:04d}.ply", "--frames", "2:16",
                     "--fps", "30")
    assert rc == 0, err
    assert sorted(p.name for p in tmp_path.glob("f_*.ply")) == [f"f_{k:04d}.ply"
                                                                 for k in range(2, 17)]
