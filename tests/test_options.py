"""SkinOptions: defaults, validation, pickling; and every entry point (Scene.skin, skin_chunks,
bake, the compare report, Crowd, the clip workers) giving the same result for the same options,
checked against float64 NumPy skinning from the equations."""

import dataclasses
import pickle
import re
import sys
from pathlib import Path

import numpy as np
import pytest
import warp as wp

import dqskin
from dqskin import CorOptions, SkinOptions
from dqskin.animation import TransformTrack
from dqskin.errors import InputError

sys.path.insert(0, str(Path(__file__).resolve().parent))
from test_crowd import lbs64, oracle_transforms  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
HUMANOID = ROOT / "assets" / "humanoid.usda"  # seven meshes, one skeleton
ARM = ROOT / "assets" / "bending_arm.usda"  # one mesh


def test_defaults_are_the_documented_ones():
    o = SkinOptions()
    assert (o.method, o.sign_reference, o.interp, o.space, o.device) == (
        None, "largest_weight", "trs", "local", None)
    assert (o.normals, o.tangents, o.velocities, o.blend_shapes) == (False, False, False, True)
    assert o.cor == CorOptions() and (o.cor.sigma, o.cor.subdivide, o.cor.cluster) == (
        dqskin.options.SIGMA, None, "auto")
    b = SkinOptions.baking()
    assert b == o.replace(normals=True, velocities=True, space="world")
    assert SkinOptions.baking(method="dqs", velocities=False) == SkinOptions(
        method="dqs", normals=True, space="world")


def test_frozen_hashable_picklable():
    o = SkinOptions(method="cor", sign_reference="running_sum", interp="sclerp", normals=True,
                    space="skeleton", device=wp.get_device("cpu"),
                    cor=CorOptions(sigma=0.2, subdivide=0.1, cluster=None))
    assert o.device == "cpu"  # a wp.Device is kept by name (picklable)
    with pytest.raises(dataclasses.FrozenInstanceError):
        o.method = "lbs"
    assert pickle.loads(pickle.dumps(o)) == o
    assert hash(pickle.loads(pickle.dumps(o))) == hash(o)
    assert o.replace(method="dqs").method == "dqs" and o.method == "cor"
    assert SkinOptions.build(o, cor=CorOptions(cluster=0.01)).cor == CorOptions(cluster=0.01)
    with pytest.raises(InputError, match="cor="):  # one type for the settings, not a dict
        SkinOptions.build(o, cor={"cluster": 0.01})
    with pytest.raises(TypeError):  # fields by name only
        SkinOptions("dqs")  # type: ignore[misc]
    # NumPy scalars are numbers and bools like Python's
    numpy_made = SkinOptions(normals=np.True_, cor=CorOptions(sigma=np.float32(0.25)))
    assert numpy_made.normals is True and numpy_made.cor.sigma == 0.25
    with pytest.raises(TypeError):
        o.replace(colour="red")


@pytest.mark.parametrize("field, value", [
    ("method", "dq"), ("method", 3), ("sign_reference", "largest"), ("interp", "linear"),
    ("space", "output"), ("space", "world "), ("normals", "yes"), ("velocities", 1),
    ("tangents", None), ("blend_shapes", "False"), ("cor", {"sigma": 1})])
def test_each_field_is_checked_and_named(field, value):
    with pytest.raises(InputError, match=f"^{field}="):
        SkinOptions(**{field: value})


@pytest.mark.parametrize("field, value", [
    ("sigma", 0), ("sigma", -1.0), ("sigma", float("nan")), ("sigma", None), ("subdivide", 0),
    ("subdivide", float("inf")), ("cluster", "exact"), ("cluster", -0.5), ("cluster", True)])
def test_cor_fields_are_checked_and_named(field, value):
    with pytest.raises(InputError, match=f"^cor.{field}="):
        CorOptions(**{field: value})


def test_plan_keeps_the_earlier_keys():
    """A clip bake's plan records the same option keys as before SkinOptions (so an earlier
    bake's --resume still matches), plus the CoR settings only when not the defaults."""
    o = SkinOptions.baking(method="dqs")
    assert o.plan() == dict(method="dqs", interp="trs", sign_reference="largest_weight",
                            normals=True, velocities=True)
    assert o.replace(cor=CorOptions(cluster=None)).plan()["cor"] == dict(
        sigma=dqskin.options.SIGMA, subdivide=None, cluster=None)
    assert o.replace(blend_shapes=False).plan()["blend_shapes"] is False


def test_resume_refuses_clips_of_other_blend_shape_settings(tmp_path):
    """Clips skinned with the blend shapes applied are not kept by a resume without them."""
    from dqskin import BakeSettings
    shot = tmp_path / "shot.usdc"
    dqskin.bake(ARM, shot, settings=BakeSettings(clips=True, chunk=8))
    with pytest.raises(InputError, match=r"with blend_shapes=True \(now blend_shapes=False\)"):
        dqskin.bake(ARM, shot, blend_shapes=False, settings=BakeSettings(chunk=8, resume=True))


def _lbs_oracle(scene, times):
    """mesh → (F, V, 3) float64 LBS points in skeleton space, from the equations."""
    out = {}
    for m in scene.meshes:
        out[m.name] = lbs64(m, oracle_transforms(scene, m.skeleton, times, np.eye(4)))
    return out


def _assert_matches(got, want, what):
    for name, ref in want.items():
        np.testing.assert_allclose(got[name], ref, atol=3e-5 * np.abs(ref).max(),
                                   err_msg=f"{what}: {name}")


def test_every_entry_point_gives_the_same_points(tmp_path):
    """One SkinOptions (LBS, skeleton space, bind points) through Scene.skin, skin_chunks, bake
    (.npz), the compare report's skinning, a Crowd of one instance at the identity, and a clip
    worker (run_clip, into a clip layer): the same points, and the float64 oracle's."""
    from pxr import Usd

    from dqskin.baking import BakeSettings
    from dqskin.report.compare import _skin
    from dqskin.writers.usd_clips import clips_folder

    scene = dqskin.load(HUMANOID)
    times = np.asarray(scene.times[::7][:6], np.float64)
    opts = SkinOptions(method="lbs", space="skeleton", blend_shapes=False)
    want = _lbs_oracle(scene, times)
    direct = scene.skin(times, options=opts).points
    _assert_matches(direct, want, "Scene.skin")
    chunks = {n: np.concatenate([r.points[n] for _, r in scene.skin_chunks(times, 4,
                                                                           options=opts)])
              for n in direct}
    for n in direct:
        np.testing.assert_array_equal(chunks[n], direct[n], err_msg=f"skin_chunks {n}")
    dqskin.bake(scene, tmp_path / "a.npz", times, options=opts)
    with np.load(tmp_path / "a.npz") as z:
        for k, m in enumerate(scene.meshes):
            np.testing.assert_array_equal(z[f"points_{k}"], direct[m.name], err_msg=m.name)
    meshes, _, _ = _skin(scene, times, ["lbs"], opts)
    for sm in meshes:
        np.testing.assert_array_equal(sm.posed["lbs"], direct[sm.name], err_msg=sm.name)
    crowd = dqskin.Crowd()
    crowd.add(scene, name="c")
    parts = crowd.split(crowd.skin(times, options=opts))
    _assert_matches({k[2:]: v for k, v in parts.items()}, want, "Crowd")
    # a clip bake (the workers' run_clip path, in this process): local space, as written
    local = opts.replace(space="local")
    shot = tmp_path / "shot.usda"
    dqskin.bake(scene, shot, times, options=local,
                settings=BakeSettings(clips=True, chunk=3))
    assert clips_folder(shot).is_dir()
    ref = scene.skin(times, options=local).points
    stage = Usd.Stage.Open(str(shot))
    for m in scene.meshes:
        attr = stage.GetPrimAtPath(m.name).GetAttribute("points")
        got = np.stack([np.asarray(attr.Get(float(t)), np.float32) for t in times])
        np.testing.assert_array_equal(got, ref[m.name], err_msg=f"clip layer {m.name}")


def test_one_launch_and_per_mesh_batches_agree():
    """The pipeline's two kinds of batch: the seven meshes in one launch (largest-weight sign
    rule), or a batch per mesh (running sum, which never batches): both the float64 oracle's
    for LBS (the sign rule does not change LBS), with normals and velocities alike."""
    from dqskin.pipeline import one_launch
    scene = dqskin.load(HUMANOID)
    times = np.asarray(scene.times[:5], np.float64)
    one = SkinOptions(method="lbs", normals=True, velocities=True)
    per = one.replace(sign_reference="running_sum")
    assert one_launch(scene, one) and not one_launch(scene, per)
    a, b = scene.skin(times, options=one), scene.skin(times, options=per)
    for kind in ("points", "normals", "velocities"):
        da, db = getattr(a, kind), getattr(b, kind)
        assert set(da) == set(db) and da
        for n in da:
            np.testing.assert_allclose(da[n], db[n], atol=2e-5 * max(1, np.abs(db[n]).max()),
                                       err_msg=f"{kind} {n}")
    _assert_matches(scene.skin(times, options=one.replace(space="skeleton")).points,
                    _lbs_oracle(scene, times), "skeleton space")


class _Shift(TransformTrack):
    key_times = np.zeros(1)

    def with_derivative(self, times):
        t = np.atleast_1d(np.asarray(times, np.float64))
        m = np.tile(np.eye(4), (len(t), 1, 1))
        m[:, :3, 3] = [10.0, -2.0, 3.0]
        return m, np.zeros_like(m)


def test_spaces_pick_their_track():
    """"skeleton": no transform; "local": ``output_transforms``; "world": ``world_transforms``
    where the mesh has one, else as "local"."""
    scene = dqskin.load(ARM)
    (m,) = scene.meshes
    t = np.asarray(scene.times[:3], np.float64)
    skel = scene.skin(t, "dqs", space="skeleton").points[m.name]
    m.output_transforms = _Shift()
    local = scene.skin(t, "dqs", space="local").points[m.name]
    np.testing.assert_allclose(local, skel + np.float32([10, -2, 3]), atol=1e-4)
    np.testing.assert_array_equal(scene.skin(t, "dqs", space="world").points[m.name], local)
    m.output_transforms = None
    m.world_transforms = _Shift()  # what a loader giving world transforms sets
    np.testing.assert_array_equal(scene.skin(t, "dqs", space="local").points[m.name], skel)
    np.testing.assert_allclose(scene.skin(t, "dqs", space="world").points[m.name],
                               skel + np.float32([10, -2, 3]), atol=1e-4)


def test_crowd_refuses_what_it_cannot_skin():
    scene = dqskin.load(ARM)
    crowd = dqskin.Crowd()
    crowd.add(scene)
    for bad, named in ((dict(normals=True), "normals=True"),
                       (dict(sign_reference="running_sum"), "sign_reference='running_sum'"),
                       (dict(tangents=True, velocities=True), "tangents=True, velocities=True"),
                       (dict(method="cor"), "'cor'")):
        with pytest.raises(InputError, match=named):
            crowd.skin(scene.times[:2], **bad)


def test_a_usd_cache_holds_local_points_placed_by_its_prims(tmp_path):
    """A USD cache's points sit under the source's prims, whose transforms take them to the
    world: "world" (a bake's default) and "local" make the same cache, and skeleton space is
    refused before anything is written."""
    with pytest.raises(InputError, match="space='skeleton'"):
        dqskin.bake(ARM, tmp_path / "a.usda", space="skeleton")
    assert list(tmp_path.iterdir()) == []
    npz = tmp_path / "a.npz"
    dqskin.bake(ARM, npz, space="skeleton")  # other outputs take any space
    assert npz.is_file()
    dqskin.bake(ARM, tmp_path / "w.usda", space="world")
    dqskin.bake(ARM, tmp_path / "l.usda", space="local")
    assert (tmp_path / "w.usda").read_bytes() == (tmp_path / "l.usda").read_bytes()


@pytest.mark.parametrize("changes, named", [
    (dict(chunk="8"), "chunk='8'"), (dict(chunk=0), "chunk=0: must be at least 1"),
    (dict(workers=True), "workers=True"), (dict(force="yes"), "force='yes'"),
    (dict(clips=1), "clips=1"), (dict(inputs="a.bvh"), "inputs='a.bvh'"),
    (dict(inputs=[1, 2]), "inputs=[1, 2]"),
])
def test_bake_settings_are_checked_and_named(changes, named):
    from dqskin import BakeSettings
    with pytest.raises(InputError, match=re.escape(named)):
        BakeSettings(**changes)


def test_bake_settings_take_numpy_bools_and_any_sequence_of_paths():
    from dqskin import BakeSettings
    s = BakeSettings(force=np.True_, clips=np.False_, inputs=(p for p in ["a.bvh", Path("b")]))
    assert s.force is True and s.clips is False and s.inputs == ("a.bvh", Path("b"))


def test_bake_refuses_its_arguments_before_loading(tmp_path):
    """A refused argument is reported before the input is read: the missing file is never
    looked for."""
    missing = tmp_path / "missing.usda"
    with pytest.raises(InputError, match="chunk=0"):
        dqskin.bake(missing, tmp_path / "x.npz", chunk=0)
    with pytest.raises(InputError, match="settings="):
        dqskin.bake(missing, tmp_path / "x.npz", settings={"chunk": 8})
    with pytest.raises(InputError, match="no such file"):
        dqskin.bake(missing, tmp_path / "x.npz")


def test_bad_arguments_of_crowds_and_chunks_are_input_errors(monkeypatch):
    scene = dqskin.load(ARM)
    crowd = dqskin.Crowd(device="cpu")
    with pytest.raises(InputError, match="time_offset='x'"):
        crowd.add(scene, time_offset="x")
    crowd.add(scene)
    # a device the crowd was not built on (resolved as the CPU here, so any machine runs this)
    monkeypatch.setattr(dqskin.crowd, "resolve_device", lambda d: wp.get_device("cpu")
                        if d in (None, "cpu") else "elsewhere")
    with pytest.raises(InputError, match="a crowd skins points only.*device='cuda:0'"):
        crowd.skin(scene.times[:2], device="cuda:0")
    for chunk in ("a", 0, [2, 0], []):
        with pytest.raises(InputError, match="chunk="):
            next(scene.skin_chunks(scene.times[:4], chunk))
    with pytest.raises(InputError, match="add up to 3 frames, not 4"):
        next(scene.skin_chunks(scene.times[:4], [1, 2]))


def test_one_skinner_per_mesh_whatever_the_cor_settings_of_other_methods():
    """CoR settings change only "cor"'s centers: LBS and DQS with other settings reuse the
    mesh's one skinner."""
    scene = dqskin.load(ARM)
    t = scene.times[:2]
    exact = CorOptions(cluster=None)
    scene.skin(t, "lbs")
    scene.skin(t, "dqs", cor=exact)
    scene.skin(t, "lbs", cor=CorOptions(sigma=0.2))
    assert len(scene._skinners) == 1
    scene.skin(t, "cor", cor=exact)
    assert len(scene._skinners) == 2


def test_command_line_space(tmp_path):
    """dqskin skin writes world points (an .npz) by default, the same as the API's with
    ``space="world"``; ``--space local`` the prims' own; a USD cache refuses skeleton space,
    naming the flag."""
    from dqskin.cli import main
    src = tmp_path / "placed.usda"
    src.write_text(f'''#usda 1.0
def "Placed" (prepend references = @{HUMANOID}@)
{{
    double3 xformOp:translate = (100, 0, -5)
    uniform token[] xformOpOrder = ["xformOp:translate"]
}}
''')
    out = tmp_path / "w.npz"
    assert main(["skin", str(src), "--out", str(out), "--frames", "0:2", "--space", "world"]) == 0
    scene = dqskin.load(src)
    want = scene.skin([0.0, 1.0, 2.0], space="world")
    # the placement in closed form: the unplaced humanoid's world points moved by (100, 0, -5)
    unplaced = dqskin.load(HUMANOID).skin([0.0, 1.0, 2.0], space="world").points
    with np.load(out) as z:
        for k, m in enumerate(scene.meshes):
            np.testing.assert_array_equal(z[f"points_{k}"], want.points[m.name])
            ref = unplaced[m.name.replace("/Placed", "/Humanoid", 1)] + np.float32([100, 0, -5])
            np.testing.assert_allclose(z[f"points_{k}"], ref, atol=1e-4 * np.abs(ref).max())
    default = tmp_path / "d.npz"
    assert main(["skin", str(src), "--out", str(default), "--frames", "0:2"]) == 0
    local = tmp_path / "l.npz"
    assert main(["skin", str(src), "--out", str(local), "--frames", "0:2", "--space",
                 "local"]) == 0
    mine = scene.skin([0.0, 1.0, 2.0], space="local").points
    with np.load(out) as z, np.load(default) as d, np.load(local) as lo:
        assert str(d["space"]) == "world" and str(lo["space"]) == "local"
        for k, m in enumerate(scene.meshes):
            np.testing.assert_array_equal(d[f"points_{k}"], z[f"points_{k}"])
            np.testing.assert_array_equal(lo[f"points_{k}"], mine[m.name])
    assert main(["skin", str(src), "--out", str(tmp_path / "w.usda"), "--space", "world"]) == 0
    assert main(["skin", str(src), "--out", str(tmp_path / "s.usda"), "--space",
                 "skeleton"]) == 2
