"""A plain mesh rigged to a BVH: ``dqskin skin MESH --skeleton X.bvh``, ``--weights FILE.npz``,
``dqskin rig`` (the written UsdSkel rig skinned by usd-core's ``UsdSkel.BakeSkinning`` equals
dqskin's skinning), and the errors for meshes that do not fit their skeleton.

Oracles: the FK of tests/test_bvh.py (written from the format) and linear blend skinning in
float64 NumPy from its equation ``p' = Σ w_j · W_j · B_j⁻¹ · p``; usd-core's UsdSkel."""

import re

import numpy as np
import pytest
import trimesh
from pxr import Gf, Sdf, Usd, UsdGeom, UsdSkel
from test_autoweights import capsule_body
from test_bvh import _offsets, oracle

from dqskin import readers
from dqskin.cli import main
from dqskin.readers import bvh
from dqskin.readers.mesh import load_mesh
from dqskin.rigging import read_weights, replace_weights, rig_mesh
from dqskin.writers.usd_rig import write_rig

FRAMES = 12


@pytest.fixture(scope="module")
def capture(shared_assets, tmp_path_factory):
    """The first frames of a CMU capture, a capsule body in its rest pose as an OBJ, and the
    weights bone heat gives it."""
    folder = tmp_path_factory.mktemp("rig")
    lines = (shared_assets / "cmu-mocap" / "131_01.bvh").read_text().splitlines()
    at = lines.index("MOTION")
    short = lines[:at + 1] + [f"Frames: {FRAMES}", lines[at + 2]] + lines[at + 3:at + 3 + FRAMES]
    path = folder / "walk.bvh"
    path.write_text("\n".join(short) + "\n")
    motion = bvh.read_bvh(path)
    pts, faces = capsule_body(motion.skeleton(), motion.end_sites, count=(8, 8))
    mesh = folder / "body.obj"
    trimesh.Trimesh(pts, faces, process=False).export(mesh)
    return path, mesh, motion


def lbs_oracle(bvh_path, points, indices, weights):
    """(F, V, 3) float64 linear blend skinning from the independent FK."""
    names, parents, rot, pos, F = oracle(bvh_path)
    world = np.zeros((F, len(names), 4, 4))
    world[..., :3, :3], world[..., :3, 3], world[..., 3, 3] = rot, pos, 1.0
    bind = np.tile(np.eye(4), (len(names), 1, 1))  # rest: every channel zero, i.e. joints at
    offsets = _offsets(bvh_path)
    for j, p in enumerate(parents):  # their summed OFFSETs (read from the text)
        bind[j, :3, 3] = offsets[j] + (bind[p, :3, 3] if p >= 0 else 0)
    skin = world @ np.linalg.inv(bind)  # (F, J, 4, 4)
    p = np.concatenate([points, np.ones((len(points), 1))], 1)
    out = np.zeros((F, len(points), 3))
    for k in range(indices.shape[1]):
        out += weights[None, :, k, None] * np.einsum("fvij,vj->fvi", skin[:, indices[:, k]],
                                                     p)[..., :3]
    return out


def _skin_cli(mesh, bvh_path, out, *extra):
    """``dqskin skin MESH --skeleton BVH ... --out OUT.npz``; the (F, V, 3) points written."""
    assert main(["skin", str(mesh), "--skeleton", str(bvh_path), "--as-is",
                                                      *extra, "--out", str(out)]) == 0
    with np.load(out) as z:
        return z[[k for k in z.files if k.startswith("points")][0]]


def test_cli_skin_with_skeleton_and_weights_file(capture, tmp_path, monkeypatch, capsys):
    monkeypatch.setenv("DQSKIN_CACHE_DIR", str(tmp_path / "cache"))
    path, mesh, motion = capture
    got = _skin_cli(mesh, path, tmp_path / "auto.npz")
    assert "1 mesh × 12 frames" in capsys.readouterr().out
    pts, _ = load_mesh(mesh)
    scene = rig_mesh(mesh, path, as_is=True)
    (m,) = scene.meshes
    ref = lbs_oracle(path, pts.astype(np.float64), m.joint_indices, m.joint_weights)
    np.testing.assert_allclose(got, ref, atol=1e-4 * np.abs(ref).max())
    assert list((tmp_path / "cache" / "weights").glob("*.npz")), "automatic weights cached"
    # the same weights from a file whose joints are listed in another order
    order = np.random.default_rng(0).permutation(len(motion.joint_names))
    inverse = np.argsort(order)
    wfile = tmp_path / "w.npz"
    np.savez(wfile, joint_indices=inverse[m.joint_indices], joint_weights=m.joint_weights,
             joint_names=np.array(motion.joint_names)[order])
    got2 = _skin_cli(mesh, path, tmp_path / "file.npz", "--weights", str(wfile))
    np.testing.assert_allclose(got2, got, atol=1e-6 * np.abs(ref).max())


def test_rig_round_trip_through_usdskel(capture, tmp_path, monkeypatch, capsys):
    """UsdSkel.BakeSkinning of the written rig equals dqskin's skinning, LBS and DQS."""
    monkeypatch.setenv("DQSKIN_CACHE_DIR", str(tmp_path / "cache"))
    path, mesh, motion = capture
    rig = tmp_path / "rig.usda"
    assert main(["rig", str(mesh), "--skeleton", str(path), "--as-is", "--out", str(rig)]) == 0
    assert "UsdSkel rig" in capsys.readouterr().out
    scene = rig_mesh(mesh, path, as_is=True)
    (m,) = scene.meshes
    for method in ("lbs", "dqs"):
        stage = Usd.Stage.Open(Sdf.Layer.OpenAsAnonymous(str(rig)))  # a fresh copy each time
        prim = stage.GetPrimAtPath("/Root/body")
        UsdSkel.BindingAPI(prim).CreateSkinningMethodAttr(
            "classicLinear" if method == "lbs" else "dualQuaternion")
        # BVH frame times are rounded reciprocals: the rate is the whole number they mean
        assert stage.GetTimeCodesPerSecond() == round(1 / motion.frame_time)
        assert stage.GetFramesPerSecond() == round(1 / motion.frame_time)
        assert UsdSkel.BakeSkinning(stage.Traverse(), Gf.Interval(0, FRAMES - 1))
        points = UsdGeom.Mesh(prim).GetPointsAttr()
        ref = np.stack([np.asarray(points.Get(float(t)), np.float64) for t in range(FRAMES)])
        got = scene.skin(np.arange(FRAMES), method=method).points[m.name]
        np.testing.assert_allclose(got, ref, atol=2e-5 * np.abs(ref).max(), err_msg=method)
        assert np.abs(ref[-1] - ref[0]).max() > 0.1, "the capture moves the mesh"
    # dqskin reads its own rig back: same skeleton, weights and motion
    back = readers.load(rig)
    np.testing.assert_allclose(back.skin(np.arange(FRAMES), method="lbs").points["/Root/body"],
                               scene.skin(np.arange(FRAMES), method="lbs").points[m.name],
                               atol=1e-5 * np.abs(ref).max())


def test_rig_of_a_gltf_character_with_auto_weights(shared_assets, tmp_path, capsys):
    scene = readers.load(shared_assets / "khronos-gltf" / "RiggedSimple" / "RiggedSimple.glb")
    out = tmp_path / "simple.usda"
    assert main(["rig", str(shared_assets / "khronos-gltf" / "RiggedSimple" /
                             "RiggedSimple.glb"), "--weights", "auto", "--out", str(out)]) == 0
    said = capsys.readouterr().out
    assert "automatic weights vs the asset's on" in said and "95th percentile" in said
    stage = Usd.Stage.Open(Sdf.Layer.OpenAsAnonymous(str(out)))
    # glTF seconds become frames at 24 fps: every frame of the clip, whole time codes
    assert stage.GetTimeCodesPerSecond() == 24 == stage.GetFramesPerSecond()
    rig = readers.load(out)
    first, last = np.ceil(24 * scene.times[0] - 1e-4), np.floor(24 * scene.times[-1] + 1e-4)
    np.testing.assert_array_equal(rig.times, np.arange(first, last + 1))
    frame = float(rig.times[len(rig.times) // 2])
    t = frame / 24
    assert UsdSkel.BakeSkinning(stage.Traverse(), Gf.Interval(frame, frame))
    (prim,) = [p for p in stage.Traverse() if p.IsA(UsdGeom.Mesh)]
    ref = np.asarray(UsdGeom.Mesh(prim).GetPointsAttr().Get(frame), np.float64)
    got = rig.skin([frame], method="lbs", space="local").points[str(prim.GetPath())]
    np.testing.assert_allclose(got[0], ref, atol=1e-5 * np.abs(ref).max())
    # the glTF character's own skinning at t, with the automatic weights: the same motion
    auto = replace_weights(scene, "auto")
    mine = auto.skin([t], method="lbs", space="local").points[auto.meshes[0].name]
    np.testing.assert_allclose(mine[0], ref, atol=1e-4 * np.abs(ref).max())


def test_misfits_are_explained(capture, tmp_path, capsys):
    path, mesh, motion = capture
    pts, faces = load_mesh(mesh)
    far = tmp_path / "far.obj"
    trimesh.Trimesh(pts + [100, 0, 0], faces, process=False).export(far)
    metres = tmp_path / "metres.obj"
    trimesh.Trimesh(pts * 0.0254, faces, process=False).export(metres)
    cases = [
        (["skin", str(far), "--skeleton", str(path), "--as-is", "--out", str(tmp_path / "a.npz")],
         "far from its skeleton"),
        (["skin", str(metres), "--skeleton", str(path), "--as-is",
                                                 "--out", str(tmp_path / "a.npz")],
         "--scale 0.0"),
        (["skin", str(mesh), "--scale", "2", "--out", str(tmp_path / "a.npz")],
         "needs --skeleton"),
        (["rig", str(path), "--skeleton", str(path), "--as-is", "--out", str(tmp_path / "r.usda")],
         "cannot read mesh"),
        (["skin", str(path), "--out", str(tmp_path / "a.npz")], "no mesh to skin"),
    ]
    for argv, message in cases:
        assert main(argv) == 2, argv
        err = capsys.readouterr().err
        assert message in err and "Traceback" not in err, (argv, err)
    assert not list(tmp_path.glob("a.*")) and not (tmp_path / "r.usda").exists()
    # the suggested scale fixes the units
    assert main(["skin", str(metres), "--skeleton", str(path), "--as-is",
                                                        "--scale", "0.0254", "--out",
                 str(tmp_path / "ok.npz")]) == 0


def test_bad_weight_files_are_named(capture, tmp_path):
    path, mesh, motion = capture
    V = len(load_mesh(mesh)[0])
    J = motion.joint_names
    bad = {
        "missing": (dict(joint_indices=np.zeros((V, 1), int)), "missing joint_weights"),
        "names": (dict(joint_indices=np.zeros((V, 1), int), joint_weights=np.ones((V, 1)),
                       joint_names=np.array(["Nope"])), "'Nope' not in the skeleton"),
        "count": (dict(joint_indices=np.zeros((3, 1), int), joint_weights=np.ones((3, 1)),
                       joint_names=np.array(J)), f"the mesh has {V} points"),
        "negative": (dict(joint_indices=np.zeros((V, 1), int), joint_weights=-np.ones((V, 1)),
                          joint_names=np.array(J)), "negative weight"),
    }
    for name, (arrays, message) in bad.items():
        f = tmp_path / f"{name}.npz"
        np.savez(f, **arrays)
        with pytest.raises(ValueError, match=message) as err:
            read_weights(f, J, V)
        assert str(f) in str(err.value)
    (tmp_path / "junk.npz").write_bytes(b"junk")
    with pytest.raises(ValueError, match="cannot read weights"):
        read_weights(tmp_path / "junk.npz", J, V)


def test_write_rig_refuses_other_suffixes(capture, tmp_path):
    path, mesh, motion = capture
    scene = rig_mesh(mesh, path, as_is=True, cache=False)
    with pytest.raises(ValueError, match="a rig is written as"):
        write_rig(scene, tmp_path / "x.npz")


def test_cli_compare_on_a_rigged_mesh(capture, tmp_path, monkeypatch, capsys):
    import json
    monkeypatch.setenv("DQSKIN_CACHE_DIR", str(tmp_path / "cache"))
    path, mesh, motion = capture
    out = tmp_path / "report"
    assert main(["compare", str(mesh), "--skeleton", str(path), "--as-is",
                                                         "--out", str(out), "--frames",
                 "0,11", "--width", "48", "--supersample", "1", "--no-sweeps", "--quiet"]) == 0
    assert "report.html" in capsys.readouterr().out
    metrics = json.loads((out / "metrics.json").read_text())
    assert "body" in metrics["meshes"] and (out / "report.html").stat().st_size > 1000


def test_damaged_weight_files_are_named(capture, tmp_path, capsys):
    path, mesh, motion = capture
    V, J = len(load_mesh(mesh)[0]), motion.joint_names
    good = tmp_path / "good.npz"
    np.savez(good, joint_indices=np.zeros((V, 1), int), joint_weights=np.ones((V, 1)),
             joint_names=np.array(J))
    whole = good.read_bytes()
    for name, data in {"empty": b"", "truncated": whole[:len(whole) // 2],
                       "cut": whole[:-10]}.items():
        f = tmp_path / f"{name}.npz"
        f.write_bytes(data)
        with pytest.raises(ValueError, match=re.escape(f"{f}: cannot read weights: ")):
            read_weights(f, J, V)
        argv = ["skin", str(mesh), "--skeleton", str(path), "--as-is", "--weights", str(f), "--out",
                str(tmp_path / "x.npz")]
        assert main(argv) == 2, name
        err = capsys.readouterr().err
        assert f"{f}: cannot read weights" in err and "Traceback" not in err, err


def test_a_weight_file_error_without_a_message_names_its_type(tmp_path, monkeypatch):
    def read_array(*args, **kwargs):
        raise EOFError()  # (what a reader may raise with no text)

    f = tmp_path / "w.npz"
    np.savez(f, joint_indices=np.zeros((1, 1), int), joint_weights=np.ones((1, 1)),
             joint_names=np.array(["root"]))
    monkeypatch.setattr(np.lib.format, "read_array", read_array)
    with pytest.raises(ValueError, match=re.escape(f"{f}: cannot read weights: joint_indices: "
                                                   "EOFError")):
        read_weights(f, ["root"], 1)


def test_outputs_never_replace_an_input(capture, tmp_path, capsys):
    """``--force`` replaces outputs, never the mesh, skeleton or weights a command reads."""
    path, mesh, motion = capture
    body = tmp_path / "f_0000.obj"  # also what the pattern f_{:04d}.obj names frame 0
    body.write_bytes(mesh.read_bytes())
    walk = tmp_path / "walk.bvh"
    walk.write_bytes(path.read_bytes())
    scene = rig_mesh(mesh, path, as_is=True)
    (m,) = scene.meshes
    arrays = dict(joint_indices=m.joint_indices, joint_weights=m.joint_weights,
                  joint_names=np.array(motion.joint_names))
    wfile, wusd = tmp_path / "w.npz", tmp_path / "w.usda"  # np.load reads either by content
    np.savez(wfile, **arrays)
    wusd.write_bytes(wfile.read_bytes())
    report = tmp_path / "report"
    (report / "frames").mkdir(parents=True)
    in_report = report / "metrics.json"
    in_report.write_bytes(wfile.read_bytes())
    skin = ["skin", str(body), "--skeleton", str(walk), "--as-is",
                                                 "--frames", "0", "--force", "--out"]
    cases = [skin + [str(body)], skin + [str(wfile), "--weights", str(wfile)],
             skin + [str(tmp_path / "f_{:04d}.obj")],
             ["rig", str(body), "--skeleton", str(walk), "--as-is",
                                                  "--weights", str(wusd), "--force",
              "--out", str(wusd)],
             ["compare", str(body), "--skeleton", str(walk), "--as-is", "--weights", str(in_report),
              "--force", "--quiet", "--no-sweeps", "--out", str(report)]]
    before = {p: p.read_bytes() for p in (body, walk, wfile, wusd, in_report)}
    for argv in cases:
        assert main(argv) == 2, argv
        err = capsys.readouterr().err
        assert "refusing to" in err and "input" in err and "Traceback" not in err, (argv, err)
    for p, data in before.items():
        assert p.read_bytes() == data, p


def test_weights_refused_with_clip_workers_or_resume(tmp_path, capsys, monkeypatch):
    """Clip workers reload INPUT from its file (without the new weights), and the resume check
    does not know them: refused before anything is loaded."""
    from dqskin.cli import default_asset
    monkeypatch.setattr("dqskin.readers.load", lambda *a, **k: 1 / 0)
    for extra in (["--workers", "1"], ["--scheduler", "tcp://127.0.0.1:1"], ["--resume"]):
        argv = ["skin", str(default_asset()), "--weights", "auto", "--out",
                str(tmp_path / "x.usdc"), *extra]
        assert main(argv) == 2, extra
        err = capsys.readouterr().err
        assert "cannot be combined with --workers, --scheduler or --resume" in err, err
    assert not list(tmp_path.iterdir())


def test_bad_scale_and_influence_count_named_up_front(capture, tmp_path, capsys, monkeypatch):
    path, mesh, motion = capture
    monkeypatch.setattr("dqskin.rigging.automatic_weights", lambda *a, **k: 1 / 0)
    for flag, value in (("--scale", "0"), ("--scale", "-2"), ("--scale", "nan"),
                        ("--max-influences", "0")):
        argv = ["skin", str(mesh), "--skeleton", str(path), "--as-is", flag, value, "--out",
                str(tmp_path / "x.npz")]
        assert main(argv) == 2, (flag, value)
        err = capsys.readouterr().err
        assert f"{flag} {float(value):g}: must be" in err and "Traceback" not in err, err


def _world_skinned(path, times):
    """``{mesh leaf name: (F, V, 3) float64}``: UsdSkel.BakeSkinning of the stage at ``path``,
    taken to the world by each mesh's local-to-world at each time."""
    stage = Usd.Stage.Open(str(path))
    stage.SetEditTarget(stage.GetSessionLayer())  # a .usdz is read-only
    assert UsdSkel.BakeSkinning(stage.Traverse(), Gf.Interval(min(times), max(times)))
    out = {}
    for prim in stage.Traverse():
        if prim.IsA(UsdGeom.Mesh):
            frames = []
            for t in times:
                p = np.asarray(UsdGeom.Mesh(prim).GetPointsAttr().Get(t), np.float64)
                m = np.asarray(UsdGeom.Xformable(prim).ComputeLocalToWorldTransform(t)).T
                frames.append(p @ m[:3, :3].T + m[:3, 3])
            out[prim.GetName()] = np.stack(frames)
    return out


@pytest.mark.parametrize("moving", [False, True])
def test_rig_of_a_usd_character_keeps_its_world_placement(shared_assets, tmp_path, moving):
    """usd-wg CesiumMan stands in a ``Z_UP`` group (a rotation); moved about over time by a
    parent in the second case. The rig skinned by UsdSkel is where the source is, in the world."""
    src = shared_assets / "usd-wg" / "CesiumMan" / "CesiumMan.usdz"
    if moving:
        wrapper = tmp_path / "moving.usda"
        wrapper.write_text(f"""#usda 1.0
(
    defaultPrim = "World"
    startTimeCode = 1
    endTimeCode = 48
    timeCodesPerSecond = 24
    upAxis = "Y"
)
def Xform "World"
{{
    double3 xformOp:translate.timeSamples = {{1: (0, 0, 0), 48: (1.5, -0.5, 2)}}
    float xformOp:rotateY.timeSamples = {{1: 0, 48: 120}}
    uniform token[] xformOpOrder = ["xformOp:translate", "xformOp:rotateY"]
    def "Man" (references = @{src}@)
    {{
    }}
}}
""")
        src = wrapper
    rig = tmp_path / "rig.usda"
    assert main(["rig", str(src), "--out", str(rig)]) == 0
    times = [1.0, 17.0, 33.0, 48.0]
    ref, got = _world_skinned(src, times), _world_skinned(rig, times)
    assert sorted(ref) == sorted(got) and ref
    for name in ref:
        scale = np.abs(ref[name]).max()
        np.testing.assert_allclose(got[name], ref[name], atol=1e-5 * scale, err_msg=name)
        up = np.ptp(ref[name][0], axis=0)
        assert up[1] == up.max(), "the man stands along +Y in the world"


def test_cli_skin_with_skeleton_to_a_usd_cache(capture, tmp_path, capsys):
    """OBJ + BVH → a USD point cache (through a temporary UsdSkel rig): its time-sampled points
    are the float64 LBS oracle's, nothing of the rig is left bound or behind."""
    path, mesh, motion = capture
    out = tmp_path / "walk.usdc"
    assert main(["skin", str(mesh), "--skeleton", str(path), "--as-is", "--out", str(out)]) == 0
    assert "1 mesh × 12 frames" in capsys.readouterr().out
    pts, _ = load_mesh(mesh)
    (m,) = rig_mesh(mesh, path, as_is=True).meshes
    ref = lbs_oracle(path, pts.astype(np.float64), m.joint_indices, m.joint_weights)
    stage = Usd.Stage.Open(str(out))
    assert stage.GetTimeCodesPerSecond() == round(1 / motion.frame_time)
    assert stage.GetFramesPerSecond() == round(1 / motion.frame_time)
    prim = stage.GetPrimAtPath("/Root/body")
    assert not prim.HasAPI(UsdSkel.BindingAPI), "the cache is not skinned again"
    attr = UsdGeom.Mesh(prim).GetPointsAttr()
    got = np.stack([np.asarray(attr.Get(float(t)), np.float64) for t in range(FRAMES)])
    np.testing.assert_allclose(got, ref, atol=1e-4 * np.abs(ref).max())
    assert sorted(p.name for p in tmp_path.iterdir()) == ["walk.usdc"]
