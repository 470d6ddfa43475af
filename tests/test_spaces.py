"""``Scene.skin(space=...)``: world space against UsdSkel on every USD asset, and what each space
means for glTF and rigged meshes.

Oracle: ``UsdSkel.BakeSkinning`` on a flattened in-memory copy of each stage (points and normals
in each prim's space, at the times it bakes), taken to the world by the prim's
``UsdGeom.Xformable.ComputeLocalToWorldTransform`` in float64 NumPy (USD's row-vector matrices
transposed here). Velocities: the central difference of the world points, per second.
"""

from pathlib import Path

import numpy as np
import pytest
from pxr import Gf, Usd, UsdGeom, UsdSkel
from test_usd import ASSETS, BAKE, JOINT_INFLUENCES, POPULATE, build_rig

import dqskin
from dqskin.errors import InputError
from dqskin.readers.bvh import read_bvh
from dqskin.spaces import space_track

BUNDLED = sorted((Path(__file__).resolve().parents[1] / "assets").glob("*.usda"))
REFUSED = {  # shared USD files that are no UsdSkel asset dqskin loads (tests/test_usd.py)
    f"{BAKE}/baseline/{m}.{k}.usda" for m in ("lbs", "dqs") for k in ("baked", "bakedInterval")
} | {JOINT_INFLUENCES, POPULATE}
TOLERANCE = 1e-5  # of the largest coordinate: float32 skinning against UsdSkel's


def _matrix(gf):
    """A Gf (row-vector) matrix as a float64 column-vector (4, 4) array."""
    return np.array(gf, dtype=np.float64).T


def baked_world(path, scene):
    """``(times, {prim path: (F, V, 3) points}, {prim path: (F, N, 3) unit normals})`` of the
    meshes of ``scene`` (loaded from ``path``): UsdSkel.BakeSkinning of a flattened in-memory
    copy of the stage, at the times it bakes (the default time of a static stage: the scene's
    first time), moved to the world by each prim's local-to-world at each time."""
    stage = Usd.Stage.Open(Usd.Stage.Open(str(path)).Flatten())
    assert UsdSkel.BakeSkinning(stage.Traverse())
    sampled = set()
    for m in scene.meshes:
        sampled.update(stage.GetPrimAtPath(m.name).GetAttribute("points").GetTimeSamples())
    times = np.array(sorted(sampled) or scene.times[:1], np.float64)
    points, normals = {}, {}
    for m in scene.meshes:
        prim = stage.GetPrimAtPath(m.name)
        n_attr = next((a for a in (prim.GetAttribute("normals"),
                                   prim.GetAttribute("primvars:normals"))
                       if a and a.GetNumTimeSamples()), None)  # what UsdSkel baked
        pts, nrm = [], []
        for t in times:
            world = _matrix(UsdGeom.Xformable(prim).ComputeLocalToWorldTransform(t))
            p = np.asarray(prim.GetAttribute("points").Get(t), np.float64)
            pts.append(p @ world[:3, :3].T + world[:3, 3])
            if n_attr is not None:
                n = np.asarray(n_attr.Get(t), np.float64) @ np.linalg.inv(world[:3, :3])
                length = np.linalg.norm(n, axis=1, keepdims=True)
                # a normal blended down to (near) nothing (LBS candy wrapper) has no direction
                with np.errstate(invalid="ignore", divide="ignore"):
                    nrm.append(np.where(length > 0.1 * np.median(length), n / length, np.nan))
        points[m.name] = np.stack(pts)
        if nrm:
            normals[m.name] = np.stack(nrm)
    return times, points, normals


def _error(ours, ref):
    """Largest difference relative to the largest reference coordinate."""
    return float(np.abs(np.asarray(ours, np.float64) - ref).max() / max(np.abs(ref).max(), 1e-30))


def check_world(path, device):
    """Scene.skin(space="world") against :func:`baked_world` (points, normals), and its
    velocities against the central difference of its points; returns the largest errors."""
    scene = dqskin.load(path)
    times, points, normals = baked_world(path, scene)
    got = scene.skin(times, space="world", normals=True, device=device)
    errors = {"points": 0.0, "normals": 0.0, "velocities": 0.0}
    for m in scene.meshes:
        err = _error(got.points[m.name], points[m.name])
        assert err < TOLERANCE, f"{path}: {m.name}: world points off by {err:.2e}"
        errors["points"] = max(errors["points"], err)
        if m.name in normals:
            err = float(np.nanmax(np.abs(got.normals[m.name] - normals[m.name])))
            assert err < TOLERANCE * 10, f"{path}: {m.name}: world normals off by {err:.2e}"
            errors["normals"] = max(errors["normals"], err)
    if len(scene.times) > 1:
        errors["velocities"] = check_velocities(scene, device)
    return errors


def check_velocities(scene, device):
    """World velocities equal the fourth-order central difference of world points, per second,
    in the middle of the intervals between time codes (away from the kinks at keys), within
    1e-3 of the top speed plus the float32 rounding of the points the difference divides."""
    t = scene.times[:-1][:: max(1, len(scene.times) // 4)] + 0.5
    h = 0.1  # time codes: t ± 2h stays inside the interval
    vel = scene.skin(t, space="world", velocities=True, device=device).velocities
    at = {k: scene.skin(t + k * h, space="world", device=device).points for k in (-2, -1, 1, 2)}
    worst = 0.0
    for name, v in vel.items():
        p = {k: a[name].astype(np.float64) for k, a in at.items()}
        fd = (p[-2] - 8 * p[-1] + 8 * p[1] - p[2]) / (12 * h) * scene.time_codes_per_second
        speed = np.linalg.norm(fd, axis=-1).max()
        rounding = 8 * np.finfo(np.float32).eps * np.abs(p[1]).max() / h
        err = float(np.abs(v - fd).max())
        assert err <= 1e-3 * speed + rounding * scene.time_codes_per_second, (
            f"{scene.path}: {name}: world velocities off by {err:.3g} (top speed {speed:.3g})")
        worst = max(worst, err / max(speed, 1e-30))
    return worst


# -- every USD asset ---------------------------------------------------------------------------

def test_every_shared_usd_file_is_compared_or_refused(shared_assets):
    """A USD file added to ../shared/assets fails here until it is in ASSETS (compared below) or
    REFUSED (not a UsdSkel asset dqskin loads)."""
    found = {str(p.relative_to(shared_assets)) for p in shared_assets.rglob("*")
             if p.suffix.lower() in (".usd", ".usda", ".usdc", ".usdz")}
    assert found == set(ASSETS) | REFUSED
    for name in REFUSED:
        with pytest.raises(ValueError):
            dqskin.load(shared_assets / name)


@pytest.mark.parametrize("name", ASSETS)
def test_world_points_equal_usdskel_bake_on_shared_assets(shared_assets, name, device):
    check_world(shared_assets / name, device)


@pytest.mark.parametrize("path", BUNDLED, ids=lambda p: p.name)
def test_world_points_equal_usdskel_bake_on_bundled_assets(path, device):
    check_world(path, device)


def placed(path, tmp_path):
    """A stage referencing the asset at ``path`` under ``/World`` (rotating about two axes,
    scaled non-uniformly over time) with its own translating, turning ``/World/Character``
    (keys on whole time codes, as the velocity check expects)."""
    src = Usd.Stage.Open(str(path))
    stage = Usd.Stage.CreateNew(str(tmp_path / f"placed_{Path(path).stem}.usda"))
    for key in ("startTimeCode", "endTimeCode", "timeCodesPerSecond", "upAxis", "metersPerUnit"):
        stage.SetMetadata(key, src.GetMetadata(key))
    world = UsdGeom.Xform.Define(stage, "/World")
    end = max(src.GetEndTimeCode(), src.GetStartTimeCode() + 1)
    rot, scale = world.AddRotateXYZOp(), world.AddScaleOp()
    for t in (src.GetStartTimeCode(), end):
        u = (t - src.GetStartTimeCode()) / (end - src.GetStartTimeCode())
        rot.Set(Gf.Vec3f(30.0 * u, -20.0 + 90.0 * u, 10.0), t)
        scale.Set(Gf.Vec3f(1.0 + u, 0.5, 2.0 - u), t)
    prim = stage.DefinePrim("/World/Character")  # typeless: the referenced SkelRoot's type
    root = src.GetDefaultPrim() or next(iter(src.GetPseudoRoot().GetChildren()))
    prim.GetReferences().AddReference(str(path), root.GetPath())
    char = UsdGeom.Xformable(prim)
    move, turn = char.AddTranslateOp(), char.AddOrientOp()
    for k, t in enumerate(np.round(np.linspace(src.GetStartTimeCode(), end, 4))):  # keys
        move.Set(Gf.Vec3d(3.0 * k, -1.0, 0.5 * k * k), float(t))
        a = np.radians(25.0 * k)
        turn.Set(Gf.Quatf(float(np.cos(a)), 0.0, float(np.sin(a)), 0.0), float(t))
    stage.GetRootLayer().Save()
    return stage.GetRootLayer().realPath


@pytest.mark.parametrize("path", BUNDLED, ids=lambda p: p.name)
def test_world_follows_animated_scaled_rotated_ancestors(path, tmp_path, device):
    """A bundled asset placed by reference under animated, rotated, non-uniformly scaled Xforms:
    world points and normals equal UsdSkel's bake taken to the world, velocities the central
    difference, and world is not the prim's local space."""
    placed_path = placed(path, tmp_path)
    errors = check_world(placed_path, device)
    assert errors["velocities"] > 0
    scene = dqskin.load(placed_path)
    t = scene.times[::8]
    world = scene.skin(t, space="world", device=device).points
    local = scene.skin(t, space="local", device=device).points
    for m in scene.meshes:
        assert m.world_transforms is not None
        assert np.abs(world[m.name] - local[m.name]).max() > 1.0


def test_world_through_animated_skeleton_and_gprim_parents(tmp_path, device):
    """The rig of tests/test_usd.py (blend shapes, the skeleton's and the mesh's parents
    animated: skeleton and prim spaces differ at every time) under the animated placement."""
    rig = build_rig(tmp_path / "rig.usda", normal_offsets=True)
    for path in (rig, placed(rig, tmp_path)):
        check_world(path, device)


def crowd(tmp_path, count=4):
    """``count`` references to the bundled humanoid: the first under an Xform without ops, the
    others moved and turned (the last animated); in the second, the mesh Arm_L resets its xform
    stack to a translation of its own (its space then differs from its skeleton's)."""
    humanoid = Path(__file__).resolve().parents[1] / "assets" / "humanoid.usda"
    src = Usd.Stage.Open(str(humanoid))
    stage = Usd.Stage.CreateNew(str(tmp_path / "crowd.usda"))
    for key in ("startTimeCode", "endTimeCode", "timeCodesPerSecond", "upAxis", "metersPerUnit"):
        stage.SetMetadata(key, src.GetMetadata(key))
    for i in range(count):
        place = UsdGeom.Xform.Define(stage, f"/Crowd/P{i}")
        if i:
            move, turn = place.AddTranslateOp(), place.AddRotateYOp()
            move.Set(Gf.Vec3d(150.0 * i, 0.0, -40.0 * i))
            turn.Set(30.0 * i)
            if i == count - 1:
                move.Set(Gf.Vec3d(0.0, 0.0, 0.0), 0.0)
                move.Set(Gf.Vec3d(200.0, 10.0, 50.0), 48.0)
        stage.DefinePrim(f"/Crowd/P{i}/H").GetReferences().AddReference(str(humanoid))
    arm = UsdGeom.Xformable(stage.OverridePrim("/Crowd/P1/H/Arm_L"))
    arm.SetResetXformStack(True)
    arm.AddTranslateOp().Set(Gf.Vec3d(5.0, -3.0, 2.0))
    stage.GetRootLayer().Save()
    return Path(stage.GetRootLayer().realPath)


def test_a_crowd_reads_each_xform_op_once_and_matches_usdskel(tmp_path, device, monkeypatch):
    """Many characters' meshes share their ancestors' transforms: each xform op of the stage is
    read once at load (not once a mesh), and world points still equal UsdSkel's bake taken to
    the world; the meshes of the unmoved character have no world track (world is their space)."""
    from dqskin.readers import usd_xform
    path = crowd(tmp_path)
    stage = Usd.Stage.Open(str(path))
    authored = sum(len(UsdGeom.Xformable(p).GetOrderedXformOps())
                   for p in stage.Traverse() if p.IsA(UsdGeom.Xformable))
    assert authored == 2 * 3 + 1
    reads = []
    op = usd_xform._Op.__init__
    monkeypatch.setattr(usd_xform._Op, "__init__", lambda self, o: reads.append(o) or op(self, o))
    scene = dqskin.load(path)
    assert len(scene.meshes) == 4 * 7
    assert len(reads) == authored
    monkeypatch.undo()
    for m in scene.meshes:
        assert (m.world_transforms is None) == m.name.startswith("/Crowd/P0/"), m.name
        assert (m.output_transforms is None) == (m.name != "/Crowd/P1/H/Arm_L"), m.name
    check_world(path, device)


def test_space_tracks_and_unknown_spaces_are_refused(shared_assets):
    scene = dqskin.load(shared_assets / "usd-wg/CesiumMan/CesiumMan.usdz")
    (m,) = scene.meshes
    assert space_track(m, "local") is m.output_transforms
    assert space_track(m, "world") is m.world_transforms is not None
    assert space_track(m, "skeleton") is None
    t = scene.times[:3]
    a = scene.skin(t, space="local").points[m.name]
    assert np.abs(a - scene.skin(t, space="world").points[m.name]).max() > 0.1
    for bad in ("prim", "output"):
        with pytest.raises(InputError, match=f"space={bad!r}"):
            scene.skin(t, space=bad)


# -- glTF and rigged meshes: their local space is the world ------------------------------------

GLTF_SUFFIXES = (".gltf", ".glb")


def test_gltf_world_is_local(shared_assets, device):
    """On every shared glTF asset: world and local are the same results."""
    files = sorted(p for p in shared_assets.rglob("*") if p.suffix.lower() in GLTF_SUFFIXES)
    assert len(files) >= 5
    for path in files:
        scene = dqskin.load(path)
        t = scene.times[:: max(1, len(scene.times) // 5)]
        kw = {"normals": True, "velocities": True, "device": device}
        out = scene.skin(t, space="local", **kw)
        got = scene.skin(t, space="world", **kw)
        for m in scene.meshes:
            assert m.world_transforms is None
            for kind in ("points", "normals", "velocities"):
                if m.name in getattr(out, kind):
                    assert np.array_equal(getattr(got, kind)[m.name],
                                          getattr(out, kind)[m.name]), (path, m.name, kind)


def test_rigged_mesh_world_is_local(shared_assets, tmp_path):
    """A plain mesh rigged to a BVH skeleton: world is its (the skeleton's) space."""
    motion = read_bvh(shared_assets / "cmu-mocap/131_01.bvh")
    skel = motion.skeleton()
    joints = skel.bind_transforms[:, :3, 3]
    points = (joints[:, None] + np.float64([[0, 0, 0], [1, 0, 0], [0, 1, 0]])).reshape(-1, 3)
    faces = np.arange(len(points)).reshape(-1, 3)
    weights = tmp_path / "w.npz"
    np.savez(weights, joint_indices=np.repeat(np.arange(len(joints)), 3)[:, None],
             joint_weights=np.ones((len(points), 1), np.float32),
             joint_names=np.array(skel.joint_names))
    scene = dqskin.rig_mesh((points, faces), motion, weights=weights, as_is=True)
    t = scene.times[:4]
    world = scene.skin(t, space="world").points
    assert scene.meshes[0].world_transforms is None
    for name, p in scene.skin(t, space="local").points.items():
        assert np.array_equal(world[name], p)
