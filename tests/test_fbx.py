"""FBX input (dqskin.readers.fbx): parity with ufbx's own skinning and with the authoring tools'
OBJ exports of ../shared/assets/ufbx (README there), and damaged files as bad input."""

import io
import json
import signal
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from conftest import SHARED
from test_cli import assert_clean_error, run

import dqskin
from dqskin.errors import InputError, UnknownNameError
from dqskin.readers import fbx

DATA = SHARED / "assets" / "ufbx" / "data"
ORACLE = Path(__file__).with_name("fbx_oracle.py")
FILES = ["blender_279_sausage_7400_binary.fbx", "max_transformed_skin_7500_ascii.fbx",
         "max_transformed_skin_7500_binary.fbx", "maya_dual_quaternion_scale_7500_ascii.fbx",
         "maya_game_sausage_7500_binary_combined.fbx", "maya_slime_7500_ascii.fbx",
         "synthetic_bind_to_root_7700_ascii.fbx"]
TOLERANCE = 1e-5
"""Largest distance from the oracle, as a fraction of the character's size."""


def data(name):
    path = DATA / name
    if not path.is_file():  # fail, never skip: the parity tests are the point
        pytest.fail(f"{path}: missing (../shared/assets/ufbx is required)")
    return path


def ufbx_skinned(path, stack, seconds):
    """ufbx's skinned positions per skinned mesh: ``{"m<k>": (T, V, 3), "rest_<k>": (V, 3)}``."""
    done = subprocess.run([sys.executable, str(ORACLE), str(path), str(stack)]
                          + [repr(float(t)) for t in seconds], capture_output=True, check=True)
    with np.load(io.BytesIO(done.stdout)) as z:
        return {k: z[k] for k in z.files}


def size(points):
    return float(np.ptp(np.asarray(points).reshape(-1, 3), axis=0).max())


def skinned_meshes(scene):
    """The meshes with a skin deformer, in the file's order (the oracle's): not those rigid on
    their own node (one influence, the joint named as the mesh)."""
    def rigid(m):
        names = scene.skeletons[m.skeleton].joint_names
        return m.joint_indices.shape[1] == 1 and all(names[j] == m.name
                                                     for j in np.unique(m.joint_indices))
    return [m for m in scene.meshes if not rigid(m)]


@pytest.mark.parametrize("name", FILES)
def test_every_stack_matches_ufbx(name):
    """Every stack at five of its frames (first and last included): the points equal ufbx's
    evaluate_scene(..., evaluate_skinning=True) within 1e-5 of the character's size."""
    path = data(name)
    first = dqskin.load(path)
    for index, clip in enumerate(first.clips):
        scene = dqskin.load(path, clip=clip) if index else first
        assert scene.clip == clip
        t = scene.times[np.unique(np.linspace(0, len(scene.times) - 1, 5).round().astype(int))]
        ref = ufbx_skinned(path, index, t)
        res = scene.skin(t, space="world")
        for k, m in enumerate(skinned_meshes(scene)):
            want = ref[f"m{k}"]
            err = np.abs(res.points[m.name] - want).max() / size(want)
            assert err < TOLERANCE, (name, clip, m.name, err)


def read_obj(path):
    return np.array([[float(x) for x in line.split()[1:4]]
                     for line in Path(path).read_text().splitlines() if line.startswith("v ")])


def nearest(a, b):
    """Largest distance from a point of ``a`` to the nearest of ``b`` and back."""
    d = np.linalg.norm(a[:, None] - b[None], axis=-1)
    return max(d.min(1).max(), d.min(0).max())


# (fbx, clip, frame or None for the stored pose, obj, tolerance / size): Maya's and Blender's
# OBJs round to 6 decimals (4e-7 of the size); 3ds Max's OBJ exporter is off by up to 8e-5
# of the size from the FBX (ufbx's own tests allow it 0.01 file units)
OBJS = [("max_transformed_skin_7500_binary.fbx", 0, 5, "max_transformed_skin_5.obj", 1.5e-4),
        ("max_transformed_skin_7500_ascii.fbx", 0, 15, "max_transformed_skin_15.obj", 1.5e-4),
        ("synthetic_bind_to_root_7700_ascii.fbx", 0, None, "synthetic_bind_to_root.obj", 1e-5),
        ("maya_dual_quaternion_scale_7500_ascii.fbx", 0, 1, "maya_dual_quaternion_scale.obj",
         1e-5),
        ("blender_279_sausage_7400_binary.fbx", "Skeleton|Base", 0,
         "blender_279_sausage_base_0.obj", 1e-5),
        ("blender_279_sausage_7400_binary.fbx", "Skeleton|Spin", 15,
         "blender_279_sausage_spin_15.obj", 1e-5),
        ("blender_279_sausage_7400_binary.fbx", "Skeleton|Wiggle", 20,
         "blender_279_sausage_wiggle_20.obj", 1e-5),
        ("maya_game_sausage_7500_binary_combined.fbx", "wiggle", 10,
         "maya_game_sausage_wiggle_10.obj", 1e-5),
        ("maya_game_sausage_7500_binary_combined.fbx", "wiggle", 18,
         "maya_game_sausage_wiggle_18.obj", 1e-5),
        ("maya_game_sausage_7500_binary_combined.fbx", "spin", 27,
         "maya_game_sausage_spin_7.obj", 1e-5),
        ("maya_game_sausage_7500_binary_combined.fbx", "spin", 35,
         "maya_game_sausage_spin_15.obj", 1e-5),
        ("maya_game_sausage_7500_binary_combined.fbx", "deform", 48,
         "maya_game_sausage_deform_8.obj", 1e-5),
        ("maya_game_sausage_7500_binary_combined.fbx", "deform", 55,
         "maya_game_sausage_deform_15.obj", 1e-5)]


@pytest.mark.parametrize("name", sorted({o[0] for o in OBJS}))
def test_authoring_tools_obj_exports(name):
    """Each frame the authoring tool exported as OBJ (world space, the file's units), matched by
    position (3ds Max reorders vertices)."""
    cases = [o for o in OBJS if o[0] == name]
    scenes = {}
    for _, clip, frame, obj, tol in cases:
        scene = scenes.get(clip) or scenes.setdefault(clip, dqskin.load(data(name), clip=clip))
        want = read_obj(data(obj))
        if frame is None:  # the stored pose: no stack
            scene.skeletons = [s.with_animation(None) for s in scene.skeletons]
            frame = float(scene.times[0])
        else:
            frame /= scene.frame_rate  # seconds
        got = np.concatenate(list(scene.skin([frame], space="world").points.values()), 1)[0]
        err = nearest(got.astype(np.float64), want) / size(want)
        assert err < tol, (obj, err)


def test_scene_metadata_and_methods():
    max_ = dqskin.load(data("max_transformed_skin_7500_binary.fbx"))
    assert (max_.up_axis, max_.meters_per_unit, max_.time_codes_per_second,
            max_.frame_rate) == ("Z", 0.01, 1.0, 30.0)
    np.testing.assert_array_equal(max_.times, np.arange(101) / 30)  # seconds: 0 .. 3.333 s
    box = max_.meshes[0]
    assert box.skinning_method == "blend" and box.blend_weights is not None
    assert np.all(box.blend_weights == 0)  # the file's per-vertex DQ weights
    dq = dqskin.load(data("maya_dual_quaternion_scale_7500_ascii.fbx"))
    assert dq.meshes[0].skinning_method == "dqs" and dq.up_axis == "Y"
    sausage = dqskin.load(data("blender_279_sausage_7400_binary.fbx"), clip=2)
    assert sausage.clips == ["Skeleton|Base", "Skeleton|Spin", "Skeleton|Wiggle"]
    assert sausage.clip == "Skeleton|Wiggle" and sausage.meters_per_unit == 1.0
    m = sausage.meshes[0]
    assert len(m.face_vertex_counts) == len(m.faces) // 2  # quads, fanned into two triangles
    assert m.normals is not None and len(m.normal_vertex) == len(m.face_vertex_indices)
    with pytest.raises(UnknownNameError, match="Dance"):
        dqskin.load(data("blender_279_sausage_7400_binary.fbx"), clip="Dance")
    slime = dqskin.load(data("maya_slime_7500_ascii.fbx"))
    rigid = slime.mesh("Slime_002:Slime_Body_high")  # unskinned: rigid on its node
    assert rigid.joint_indices.shape[1] == 1 and rigid.uvs is not None


def damaged(tmp_path, source, seed):
    """Truncated and byte-flipped copies of ``source``."""
    raw = data(source).read_bytes()
    rng = np.random.default_rng(seed)
    out = []
    for k, cut in enumerate([0, 20, 27, 200, len(raw) // 3, len(raw) - 10]):
        p = tmp_path / f"cut{k}.fbx"
        p.write_bytes(raw[:cut])
        out.append(p)
    for k in range(8):
        b = bytearray(raw)
        at = rng.integers(0, len(b), size=int(rng.integers(1, 40)))
        b_at = rng.integers(0, 256, size=at.size)
        for i, v in zip(at.tolist(), b_at.tolist()):
            b[i] = v
        p = tmp_path / f"fuzz{k}.fbx"
        p.write_bytes(bytes(b))
        out.append(p)
    return out


@pytest.mark.parametrize("source", ["max_transformed_skin_7500_binary.fbx",
                                    "synthetic_bind_to_root_7700_ascii.fbx"])
def test_damaged_files_are_bad_input(tmp_path, source):
    """Truncated and fuzzed files load or raise InputError naming the file; nothing else."""
    for p in damaged(tmp_path, source, seed=len(source)):
        try:
            scene = dqskin.load(p)
        except InputError as exc:
            assert str(p) in str(exc) and "\n" not in str(exc)
        else:
            scene.skin(scene.times[:2])


def test_a_crash_of_ufbx_is_bad_input(tmp_path, monkeypatch):
    """ufbx dying on a file (here a stand-in that segfaults) is one InputError, and dqskin
    lives on."""
    crash = tmp_path / "crash.py"
    crash.write_text("import os, signal\nos.kill(os.getpid(), signal.SIGSEGV)\n")
    monkeypatch.setattr(fbx, "_EXTRACT", crash)
    with pytest.raises(InputError, match="ufbx crashed reading it .SIGSEGV."):
        dqskin.load(data("maya_dual_quaternion_scale_7500_ascii.fbx"))
    assert signal.SIGSEGV  # (still here)


def test_cli_damaged_file_one_line_exit_2(tmp_path):
    bad = tmp_path / "bad.fbx"
    bad.write_bytes(data("max_transformed_skin_7500_binary.fbx").read_bytes()[:5000])
    for command in (["info", bad], ["skin", bad, "--out", tmp_path / "o.npz"]):
        rc, _, err = run(*command)
        assert_clean_error(rc, err, "bad.fbx")


def test_cli_info_skin(tmp_path):
    """``info``, ``skin`` to npz (ufbx's points), per-frame OBJs (whole frame numbers) and a
    USD point cache (integer time codes at the file's rate, units and up axis stated)."""
    from pxr import Usd, UsdGeom

    src = data("maya_game_sausage_7500_binary_combined.fbx")
    rc, out, err = run("info", src, "--clip", "spin")
    assert rc == 0, err
    assert "clips: wiggle, spin, deform (loaded: spin)" in out
    assert "frames 20 .. 40 at 24 fps (0.8333 .. 1.667 s)" in out
    rc, out, err = run("skin", src, "--clip", "spin", "--frames", "27:35:8", "--out",
                       tmp_path / "o.npz")
    assert rc == 0, err
    with np.load(tmp_path / "o.npz") as z:
        pts = z["points_0"]
    ref = ufbx_skinned(src, 1, np.array([27.0, 35.0]) / 24)["m0"]
    assert np.abs(pts - ref).max() / size(ref) < TOLERANCE
    rc, out, err = run("skin", src, "--clip", "spin", "--frames", "27:28", "--out",
                       tmp_path / "f_{:04d}.obj")
    assert rc == 0, err
    assert {p.name for p in tmp_path.glob("f_*.obj")} == {"f_0027.obj", "f_0028.obj"}
    rc, out, err = run("skin", src, "--clip", "spin", "--frames", "27:35:8", "--out",
                       tmp_path / "c.usda")
    assert rc == 0, err
    stage = Usd.Stage.Open(str(tmp_path / "c.usda"))
    assert (stage.GetTimeCodesPerSecond(), stage.GetStartTimeCode(),
            stage.GetEndTimeCode()) == (24.0, 27.0, 35.0)
    assert UsdGeom.GetStageUpAxis(stage) == "Y" and UsdGeom.GetStageMetersPerUnit(stage) == 0.01
    mesh = next(UsdGeom.Mesh(p) for p in stage.Traverse() if p.IsA(UsdGeom.Mesh))
    got = np.array(mesh.GetPointsAttr().Get(35.0))
    assert np.abs(got - ref[1]).max() / size(ref) < TOLERANCE


def test_cli_rig_keeps_skeleton_and_weights(tmp_path):
    """``rig --out RIG.usda`` of an FBX: UsdSkel.BakeSkinning skins the rig to ufbx's points
    (stack "spin": its joints' local transforms have no shear, which UsdSkel's TRS cannot
    hold)."""
    from pxr import Usd, UsdGeom, UsdSkel

    src = data("maya_game_sausage_7500_binary_combined.fbx")
    rc, out, err = run("rig", src, "--clip", "spin", "--out", tmp_path / "rig.usda")
    assert rc == 0, err
    stage = Usd.Stage.Open(str(tmp_path / "rig.usda"))
    UsdSkel.BakeSkinning(stage.Traverse())
    mesh = next(UsdGeom.Mesh(p) for p in stage.Traverse() if p.IsA(UsdGeom.Mesh))
    xf = np.array(UsdGeom.Xformable(mesh).ComputeLocalToWorldTransform(35.0)).T
    local = np.array(mesh.GetPointsAttr().Get(35.0), np.float64)
    world = local @ xf[:3, :3].T + xf[:3, 3]
    ref = ufbx_skinned(src, 1, [35.0 / 24])["m0"][0]
    assert np.abs(world - ref).max() / size(ref) < TOLERANCE
    rc, out, err = run("rig", src, "--weights", "auto", "--out", tmp_path / "auto.usda")
    assert rc == 0, err


def test_extract_writes_no_pickles():
    """The reader's process answers in plain arrays and one JSON record."""
    done = subprocess.run([sys.executable, "-I", str(fbx._EXTRACT),
                           str(data("maya_dual_quaternion_scale_7500_ascii.fbx")), "-",
                           str(1 << 30)],
                          capture_output=True, check=True)
    with np.load(io.BytesIO(done.stdout), allow_pickle=False) as z:
        meta = json.loads(str(z["meta"]))
        assert z["world"].dtype == np.float64
    assert meta["clips"] == ["Take 001"] and meta["meshes"][0]["method"] == 2


def test_per_vertex_blend_everywhere(tmp_path):
    """A mesh's own blend weights: the asset's method "blend" mixes LBS and DQS per vertex in
    points and velocities; a UsdSkel rig keeps them as primvars:dqskin:blendWeights and reads
    back as "blend"; weights outside [0, 1] there are bad input."""
    import dataclasses

    from pxr import Usd, UsdGeom

    from dqskin.writers.usd_rig import write_rig

    scene = dqskin.load(data("blender_279_sausage_7400_binary.fbx"), clip="Skeleton|Wiggle")
    m = scene.meshes[0]
    b = np.random.default_rng(7).random(len(m.points)).astype(np.float32)
    scene.meshes = [dataclasses.replace(m, skinning_method="blend", blend_weights=b)]
    scene.invalidate()
    t = np.array([6.0, 11.5]) / 24  # seconds
    got = scene.skin(t, velocities=True, space="world")
    lbs, dqs = (scene.skin(t, meth, space="world").points[m.name] for meth in ("lbs", "dqs"))
    scale = size(lbs)
    assert np.abs(dqs - lbs).max() > 1e-3 * scale  # the two methods differ here
    want = (1 - b[:, None]) * lbs + b[:, None] * dqs
    assert np.abs(got.points[m.name] - want).max() < 1e-5 * scale
    h = 1e-2 / 24  # central differences of the points, per second, inside the frame
    ahead, behind = (scene.skin(t + d, space="world").points[m.name].astype(np.float64)
                     for d in (h, -h))
    rate = (ahead - behind) / (2 * h)
    assert np.abs(got.velocities[m.name] - rate).max() < 1e-3 * np.abs(rate).max()
    rig = tmp_path / "rig.usda"
    write_rig(scene, rig)
    back = dqskin.load(rig)
    assert back.meshes[0].skinning_method == "blend"
    np.testing.assert_array_equal(back.meshes[0].blend_weights, b)
    again = back.skin(t * back.time_codes_per_second,  # (the rig's time codes: frames)
                      space="world").points[back.meshes[0].name]
    assert np.abs(again - want).max() < 1e-5 * scale
    stage = Usd.Stage.Open(str(rig))
    prim = next(p for p in stage.Traverse() if p.IsA(UsdGeom.Mesh))
    UsdGeom.PrimvarsAPI(prim).GetPrimvar("dqskin:blendWeights").Set(
        [1.5] * len(b))
    stage.GetRootLayer().Export(str(tmp_path / "bad.usda"))
    with pytest.raises(InputError, match=r"blendWeights: values outside \[0, 1\]"):
        dqskin.load(tmp_path / "bad.usda")


def test_compare_report_names_the_assets_blend_weights(tmp_path):
    """``dqskin compare`` of an FBX "blended" skin labels its blend per-vertex, with each mesh's
    mean weight (3ds Max's file: every DQ weight 0)."""
    rc, out, err = run("compare", data("max_transformed_skin_7500_binary.fbx"), "--out",
                       tmp_path / "report", "--methods", "lbs,blend", "--frames", "5,15",
                       "--no-sweeps", "--viewer-frames", "2", "--quiet")
    assert rc == 0, err
    assert "Blend (per-vertex DQS)" in out
    result = json.loads((tmp_path / "report" / "metrics.json").read_text())
    assert result["blend_per_vertex"] == {"Box001": 0.0}
    page = (tmp_path / "report" / "report.html").read_text()
    assert "the asset's per-vertex DQS fractions: Box001 mean 0" in page


def test_blend_shape_deformer_closed_form():
    """Blend shapes (the reader's deformer): rest + Σ w_k(t)·offset_k with the in-between
    weights linear between whole frames, and their exact time derivative."""
    rest = np.array([[0.0, 0, 0], [1, 0, 0]])
    offsets = np.array([[[0.0, 1, 0], [0, 0, 0]], [[0, 0, 0], [0, 0, 2]]])
    frames = np.array([0.0, 1.0, 2.0])
    weights = np.array([[0.0, 0.0], [1.0, 0.5], [0.0, 1.0]])  # (frames, in-betweens)
    shapes = fbx._Shapes(rest, offsets, frames, weights)
    got = shapes.points_at([0.5, 1.5, 3.0])
    np.testing.assert_allclose(got[0], [[0, 0.5, 0], [1, 0, 0.5]])
    np.testing.assert_allclose(got[1], [[0, 0.5, 0], [1, 0, 1.5]])
    np.testing.assert_allclose(got[2], [[0, 0, 0], [1, 0, 2]])  # clamped past the last frame
    rates = shapes.point_velocities_at([0.5, 1.5])
    np.testing.assert_allclose(rates[0], [[0, 1, 0], [0, 0, 1]])
    np.testing.assert_allclose(rates[1], [[0, -1, 0], [0, 0, 1]])


def test_endless_stack_is_refused(tmp_path):
    """A stack whose end lies 160 years out (an edited ASCII file) is a LimitError, not a
    million evaluations; transforms beyond max_input_gib are refused before they are evaluated."""
    from dqskin.errors import LimitError

    text = data("maya_dual_quaternion_scale_7500_ascii.fbx").read_text()
    stop = '"LocalStop", "KTime", "Time", "",230930790000'
    assert stop + "\n" in text
    (tmp_path / "long.fbx").write_text(text.replace(stop + "\n", stop + "000000\n"))
    with pytest.raises(LimitError, match="spans 120000000 frames at 24 fps"):
        dqskin.load(tmp_path / "long.fbx")
    with pytest.raises(LimitError, match=r"'Take 001': 120 times of 2 nodes' transforms: needs "
                       r"2.86e-05 GiB, more than the limit of 1e-05 GiB; raise max_input_gib"):
        dqskin.load(data("maya_dual_quaternion_scale_7500_ascii.fbx"), max_input_gib=1e-5)


@pytest.mark.parametrize("name", ["maya_game_sausage_7500_binary_combined.fbx",
                                  "maya_slime_7500_ascii.fbx"])
def test_between_frames_follow_the_files_curves(name):
    """Quarter, half and odd fractions of frames are ufbx's evaluation of the file's curves at
    those times (interpolating the whole frames is off by up to 5e-2 of the size on the sausage
    and 4e-4 on the slime), with velocities (the keyed motion's) on the same call."""
    path = data(name)
    scene = dqskin.load(path)
    frames = np.round(scene.times * scene.frame_rate)[:6]
    t = np.concatenate([frames[:-1] + d for d in (0.25, 0.5, 0.37, 0.75)]) / scene.frame_rate
    ref = ufbx_skinned(path, 0, t)
    res = scene.skin(np.concatenate([scene.times[:6], t]), velocities=True, space="world")
    for k, m in enumerate(skinned_meshes(scene)):
        want = ref[f"m{k}"]
        err = np.abs(res.points[m.name][6:] - want).max() / size(want)
        assert err < TOLERANCE, (m.name, err)
        assert np.all(np.isfinite(res.velocities[m.name]))


def test_bake_api_and_value_clips(tmp_path):
    """``dqskin.bake`` of an FBX scene writes a USD cache through the generic path (time codes
    the file's frames at its rate, sub-frames as ufbx evaluates them); value clips of an FBX
    input are one line and exit 2."""
    from pxr import Usd, UsdGeom

    src = data("maya_game_sausage_7500_binary_combined.fbx")
    scene = dqskin.load(src, clip="spin")
    seconds = np.array([27.0, 27.5, 35.0]) / 24
    dqskin.bake(scene, tmp_path / "x.usdc", seconds)
    stage = Usd.Stage.Open(str(tmp_path / "x.usdc"))
    assert (stage.GetTimeCodesPerSecond(), stage.GetFramesPerSecond(), stage.GetStartTimeCode(),
            stage.GetEndTimeCode()) == (24.0, 24.0, 27.0, 35.0)
    mesh = next(UsdGeom.Mesh(p) for p in stage.Traverse() if p.IsA(UsdGeom.Mesh))
    ref = ufbx_skinned(src, 1, seconds)["m0"]
    for i, code in enumerate([27.0, 27.5, 35.0]):
        got = np.array(mesh.GetPointsAttr().Get(code))
        assert np.abs(got - ref[i]).max() / size(ref) < TOLERANCE, code
    for flag in (["--clips"], ["--workers", "2"]):
        rc, _, err = run("skin", src, "--out", tmp_path / "c.usd", *flag)
        assert_clean_error(rc, err, "value clips")


SHAPE_FBX = """\
; FBX 7.4.0 project file
FBXHeaderExtension:  {
    FBXHeaderVersion: 1003
    FBXVersion: 7400
    Creator: "dqskin test"
}
GlobalSettings:  {
    Version: 1000
    Properties70:  {
        P: "UpAxis", "int", "Integer", "",1
        P: "UpAxisSign", "int", "Integer", "",1
        P: "FrontAxis", "int", "Integer", "",2
        P: "FrontAxisSign", "int", "Integer", "",1
        P: "CoordAxis", "int", "Integer", "",0
        P: "CoordAxisSign", "int", "Integer", "",1
        P: "UnitScaleFactor", "double", "Number", "",1
        P: "TimeMode", "enum", "", "",11
    }
}
Objects:  {
    Geometry: 1000, "Geometry::Tri", "Mesh" {
        Vertices: *9 {
            a: 0,0,0,1,0,0,0,1,0
        }
        PolygonVertexIndex: *3 {
            a: 0,1,-3
        }
        GeometryVersion: 124
    }
    Model: 2000, "Model::Tri", "Mesh" {
        Version: 232
        Properties70:  {
            P: "Lcl Translation", "Lcl Translation", "", "A",5,0,0
            P: "Lcl Rotation", "Lcl Rotation", "", "A",0,0,90
        }
    }
    Deformer: 3000, "Deformer::Morpher", "BlendShape" {
        Version: 100
    }
    Deformer: 3100, "SubDeformer::Channel", "BlendShapeChannel" {
        Version: 100
        DeformPercent: 0
        FullWeights: *2 {
            a: 50,100
        }
    }
    Geometry: 4000, "Geometry::Half", "Shape" {
        Version: 100
        Indexes: *1 {
            a: 1
        }
        Vertices: *3 {
            a: 0,1,0
        }
    }
    Geometry: 4100, "Geometry::Full", "Shape" {
        Version: 100
        Indexes: *1 {
            a: 1
        }
        Vertices: *3 {
            a: 0,0,2
        }
    }
    AnimationStack: 5000, "AnimStack::Take 001", "" {
        Properties70:  {
            P: "LocalStart", "KTime", "Time", "",0
            P: "LocalStop", "KTime", "Time", "",46186158000
        }
    }
    AnimationLayer: 5100, "AnimLayer::BaseLayer", "" {
    }
    AnimationCurveNode: 5200, "AnimCurveNode::DeformPercent", "" {
        Properties70:  {
            P: "d|DeformPercent", "Number", "", "A",0
        }
    }
    AnimationCurve: 5300, "AnimCurve::", "" {
        Default: 0
        KeyVer: 4009
        KeyTime: *2 {
            a: 0,46186158000
        }
        KeyValueFloat: *2 {
            a: 0,100
        }
        KeyAttrFlags: *1 {
            a: 4
        }
        KeyAttrDataFloat: *4 {
            a: 0,0,0,0
        }
        KeyAttrRefCount: *1 {
            a: 2
        }
    }
}
Connections:  {
    C: "OO",2000,0
    C: "OO",1000,2000
    C: "OO",3000,1000
    C: "OO",3100,3000
    C: "OO",4000,3100
    C: "OO",4100,3100
    C: "OO",5100,5000
    C: "OO",5200,5100
    C: "OP",5200,3100, "DeformPercent"
    C: "OP",5300,5200, "d|DeformPercent"
}
"""
"""A triangle on a node (moved by 5 along x, turned 90° about z) with one blend-shape channel
whose DeformPercent goes linearly from 0 to 100 over one second at 24 fps: an in-between shape
at 50 (vertex 1 up by 1 along y) and the full shape at 100 (vertex 1 by 2 along z). FBX 7.4
ASCII written by hand: no shared FBX file has blend shapes."""


def test_blend_shape_with_in_between(tmp_path):
    """ufbx's blended points at whole frames and between them, and the closed form: at
    DeformPercent w the in-between weighs w/50 below 50 and (100 - w)/50 above, the full shape
    (w - 50)/50; velocities are their rates (w grows by 100 a second)."""
    path = tmp_path / "shape.fbx"
    path.write_text(SHAPE_FBX)
    scene = dqskin.load(path)
    assert scene.frame_rate == 24 and len(scene.times) == 25 and scene.meshes[0].deformer
    t = np.array([0.0, 7 / 24, 0.3, 0.5, 13.5 / 24, 0.8, 1.0])
    ref = ufbx_skinned(path, 0, t)["b0"]
    res = scene.skin(t, velocities=True, space="world")
    got = res.points["Tri"]
    assert np.abs(got - ref).max() < 1e-6 * size(ref)
    w = 100 * t
    half = np.where(w <= 50, w / 50, (100 - w) / 50)
    full = np.clip((w - 50) / 50, 0, None)
    turn = np.array([[0.0, -1, 0], [1, 0, 0], [0, 0, 1]])  # 90° about z
    want = (np.array([1.0, 0, 0]) + half[:, None] * [0, 1, 0] + full[:, None] * [0, 0, 2]) @ turn.T
    np.testing.assert_allclose(got[:, 1], want + [5, 0, 0], atol=1e-6)
    rate = np.array([[0.0, 2, 0], [0, -2, 4]]) @ turn.T  # per second, below and above 50
    np.testing.assert_allclose(res.velocities["Tri"][[2, 5], 1], rate, atol=1e-5)
