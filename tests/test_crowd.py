"""Crowds: many characters in one FK launch and one skinning launch per method.

Oracles: usd-core's ``UsdSkel.BakeSkinning`` on the same crowd stage (references with layer
offsets and their own transforms, instanceable or not); float64 NumPy forward kinematics and LBS
written from the equations; ``UsdSkel.SkinPoints`` for DQS.
"""

import importlib.util
from pathlib import Path

import numpy as np
import pytest
from pxr import Gf, Usd, UsdGeom, UsdSkel, Vt
from scipy.spatial.transform import Rotation

import dqskin
from dqskin import Crowd
from dqskin.kernels import fk as FK
from dqskin.kernels import skin as K

ROOT = Path(__file__).resolve().parents[1]
ASSETS = [ROOT / "assets" / "humanoid.usda", ROOT / "assets" / "bending_arm.usda"]
TIMES = np.arange(0.0, 40.0)


def _make_crowd():
    spec = importlib.util.spec_from_file_location("make_crowd", ROOT / "tools" / "make_crowd.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


@pytest.fixture(scope="module")
def crowd_stage(tmp_path_factory):
    """Six instances of two bundled characters (every other instanceable), offsets up to 24
    time codes, placed and turned."""
    path = tmp_path_factory.mktemp("crowd") / "crowd.usda"
    paths = _make_crowd().write_crowd(path, ASSETS, 6, seed=3, spacing=50.0)
    return path, paths


def baked(path, names, times):
    """UsdSkel.BakeSkinning of the stage (instancing switched off in memory, so the instance
    proxies can be written), points and normals of ``names`` at ``times``. The bake interval
    reaches past the last time: BakeSkinning samples the animation's own (offset, fractional)
    key times inside the interval only."""
    stage = Usd.Stage.Open(str(path))
    for p in stage.Traverse():
        if p.IsInstance():
            p.SetInstanceable(False)
    assert UsdSkel.BakeSkinning(stage.Traverse(), Gf.Interval(times[0], times[-1] + 20))
    out = {}
    for n in names:
        mesh = UsdGeom.Mesh(stage.GetPrimAtPath(n))
        out[n] = np.stack([np.asarray(mesh.GetPointsAttr().Get(float(t)), np.float64)
                           for t in times])
    return out


def test_crowd_stage_skins_as_usdskel_bakes_it(crowd_stage, monkeypatch):
    path, instances = crowd_stage
    scene = dqskin.load(path)
    assert len(scene.skeletons) == 6 and len(scene.meshes) == 3 * 7 + 3
    assert {m.name.split("/")[2] for m in scene.meshes} == {p.split("/")[2] for p in instances}
    calls = {"fk": 0, "skin": 0}
    fk, skin = FK.forward_kinematics, K.skin_points

    def count(key, fn):
        def wrapped(**kw):
            calls[key] += 1
            return fn(**kw)
        return wrapped
    monkeypatch.setattr(FK, "forward_kinematics", count("fk", fk))
    monkeypatch.setattr(K, "skin_points", count("skin", skin))
    got = scene.skin(TIMES).points
    # one FK launch for the six skeletons; one skinning launch per method (every mesh is LBS)
    assert calls == {"fk": 1, "skin": 1}
    ref = baked(path, list(got), TIMES)
    moved = 0.0
    for name, pts in got.items():
        scale = np.abs(ref[name]).max()
        np.testing.assert_allclose(pts, ref[name], atol=2e-5 * scale, err_msg=name)
        moved = max(moved, np.abs(ref[name][-1] - ref[name][0]).max() / scale)
    assert moved > 0.05, "the crowd moves"


def test_crowd_stage_dqs_matches_usdskel(crowd_stage):
    path, _ = crowd_stage
    scene = dqskin.load(path)
    times = TIMES[::6]
    got = scene.skin(times, "dqs").points
    stage_copy = Usd.Stage.Open(str(path))
    for p in stage_copy.Traverse(Usd.TraverseInstanceProxies()):
        if p.IsInstance():
            p.SetInstanceable(False)
    for p in stage_copy.Traverse():
        if p.IsA(UsdGeom.Mesh) and p.HasAPI(UsdSkel.BindingAPI):
            UsdSkel.BindingAPI(p).CreateSkinningMethodAttr("dualQuaternion")
    tmp = Path(str(path) + ".dqs.usda")
    stage_copy.GetRootLayer().Export(str(tmp))
    # the references stay in the exported root layer: author the method on the meshes' overs
    ref = baked(tmp, list(got), times)
    for name, pts in got.items():
        np.testing.assert_allclose(pts, ref[name], atol=5e-5 * np.abs(ref[name]).max(),
                                   err_msg=name)


def test_skin_command_writes_the_crowd_cache(crowd_stage, tmp_path):
    path, _ = crowd_stage
    out = tmp_path / "cache.usdc"
    from dqskin.cli import main
    assert main(["skin", str(path), "--out", str(out), "--frames", "0:12"]) == 0
    scene = dqskin.load(path)
    names = [m.name for m in scene.meshes]
    times = np.arange(0.0, 13.0)
    ref = baked(path, names, times)
    cache = Usd.Stage.Open(str(out))
    for name in names:
        attr = UsdGeom.Mesh(cache.GetPrimAtPath(name)).GetPointsAttr()
        pts = np.stack([np.asarray(attr.Get(float(t))) for t in times])
        np.testing.assert_allclose(pts, ref[name], atol=2e-5 * np.abs(ref[name]).max(),
                                   err_msg=name)


# -- the Python API --------------------------------------------------------------------------


def fk64(parents, local):
    world = np.empty_like(local)
    for j, p in enumerate(parents):
        world[:, j] = local[:, j] if p < 0 else world[:, p] @ local[:, j]
    return world


def oracle_transforms(scene, s, times, root):
    """float64 bind-relative transforms of skeleton ``s`` at ``times``, the root transform
    composed onto the skeleton: ``root · W · B⁻¹``."""
    skel = scene.skeletons[s]
    local = np.asarray(scene.local_transforms(times, s), np.float64)
    return root @ fk64(skel.parents, local) @ np.linalg.inv(skel.bind_transforms)


def lbs64(mesh, M):
    g = mesh.geom_bind_transform
    p = np.asarray(mesh.points, np.float64) @ g[:3, :3].T + g[:3, 3]
    A = np.einsum("vk,fvkij->fvij", np.asarray(mesh.joint_weights, np.float64),
                  M[:, np.asarray(mesh.joint_indices)])
    return np.einsum("fvij,vj->fvi", A[..., :3, :3], p) + A[..., :3, 3]


def dqs_usd(mesh, M):
    g = mesh.geom_bind_transform
    K_ = np.asarray(mesh.joint_indices).shape[1]
    out = []
    for f in range(M.shape[0]):
        pts = Vt.Vec3fArray.FromNumpy(np.asarray(mesh.points, np.float32))
        UsdSkel.SkinPoints("dualQuaternion", Gf.Matrix4d(*g.T.ravel().tolist()),
                           Vt.Matrix4dArray.FromNumpy(np.ascontiguousarray(
                               M[f].transpose(0, 2, 1))),
                           Vt.IntArray.FromNumpy(np.ascontiguousarray(
                               np.asarray(mesh.joint_indices, np.int32).ravel())),
                           Vt.FloatArray.FromNumpy(np.ascontiguousarray(
                               np.asarray(mesh.joint_weights, np.float32).ravel())), K_, pts)
        out.append(np.asarray(pts, np.float64))
    return np.stack(out)


@pytest.fixture(scope="module")
def characters():
    return [dqskin.load(a) for a in ASSETS]


def placements(rng, n):
    roots = []
    for k in range(n):
        r = np.eye(4)
        r[:3, :3] = Rotation.random(random_state=rng).as_matrix() * (1.5 if k == 2 else 1.0)
        r[:3, 3] = rng.normal(size=3) * 30
        roots.append(r)
    return roots


@pytest.mark.parametrize("method", ["lbs", "dqs"])
def test_crowd_api_matches_float64_oracles(characters, method):
    rng = np.random.default_rng(11)
    crowd = Crowd()
    roots = placements(rng, 5)
    offsets = [0.0, 3.5, 10.0, 17.25, 30.0]
    for k, (root, off) in enumerate(zip(roots, offsets)):
        crowd.add(characters[k % 2], time_offset=off, root_transform=root)
    times = np.array([0.0, 5.0, 12.5, 33.0])
    got = crowd.skin(times, method)
    assert got.shape == (4, crowd.vertex_count, 3)
    parts = crowd.split(got)
    assert len(parts) == 3 * 7 + 2
    for k, (root, off) in enumerate(zip(roots, offsets)):
        scene = characters[k % 2]
        M = oracle_transforms(scene, 0, times - off, root)
        for m in scene.meshes:
            ref = lbs64(m, M) if method == "lbs" else dqs_usd(m, M)
            np.testing.assert_allclose(parts[f"i{k}/{m.name}"], ref,
                                       atol=3e-5 * np.abs(ref).max(), err_msg=f"i{k} {m.name}")


def test_crowd_instances_of_one_character_differ_by_offset(characters):
    crowd = Crowd()
    crowd.add(characters[0], name="a")
    crowd.add(characters[0], name="b", time_offset=5.0)
    t = np.array([10.0, 20.0])
    parts = crowd.split(crowd.skin(t, "lbs"))
    alone = Crowd()
    alone.add(characters[0])
    later = alone.split(alone.skin(t - 5.0, "lbs"))
    for m in characters[0].meshes:
        np.testing.assert_array_equal(parts[f"b/{m.name}"], later[f"i0/{m.name}"])
        assert np.abs(parts[f"a/{m.name}"] - parts[f"b/{m.name}"]).max() > 1e-3


def test_crowd_refuses_bad_input(characters):
    crowd = Crowd()
    with pytest.raises(ValueError, match="time_offset"):
        crowd.add(characters[0], time_offset=float("nan"))
    with pytest.raises(ValueError, match="root_transform"):
        crowd.add(characters[0], root_transform=np.full((4, 4), np.inf))
    with pytest.raises(ValueError, match="root_transform"):
        crowd.add(characters[0], root_transform=np.ones((4, 4)))
    crowd.add(characters[0], name="x")
    with pytest.raises(ValueError, match="used twice"):
        crowd.add(characters[1], name="x")
    with pytest.raises(ValueError, match="method"):
        crowd.skin([0.0], "cor")
    with pytest.raises(ValueError, match="no instances"):
        Crowd().skin([0.0])


def test_instances_added_and_skinners_dropped_while_other_threads_skin():
    """One thread adds instances to a Crowd (and drops a Scene's skinners) while two others skin
    them: no call fails, each result has the points of some whole set of instances, and the
    crowd is usable afterwards. (``add`` used to reset the batches while another thread built
    them: a crowd could stay broken for good; ``Scene.invalidate`` iterated the cache while
    other threads filled it.)"""
    import threading
    assets = Path(__file__).resolve().parents[1] / "assets"
    arm = dqskin.load(assets / "bending_arm.usda")
    scene = dqskin.load(assets / "humanoid.usda")  # several meshes: the batched path
    crowd = Crowd(device="cpu")
    crowd.add(arm)
    per_instance = sum(len(m.points) for m in arm.meshes)
    stop, errors, counts = threading.Event(), [], set()

    def change():
        try:
            for k in range(30):
                xf = np.eye(4)
                xf[:3, 3] = [k, 0.0, 0.0]
                crowd.add(arm, root_transform=xf)
                scene.invalidate()
                stop.wait(0.005)
        finally:
            stop.set()

    def skin():
        while not stop.is_set():
            try:
                points = crowd.skin([0.0, 0.5], "dqs")
                assert points.shape[1] % per_instance == 0, points.shape
                counts.add(points.shape[1] // per_instance)
                scene.skin(scene.times[:2], "lbs")
            except Exception as exc:  # noqa: BLE001  (reported below, not lost in the thread)
                errors.append(repr(exc))
    threads = [threading.Thread(target=change)] + [threading.Thread(target=skin)
                                                   for _ in range(2)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert not errors, errors[:3]
    assert len(counts) > 1  # the skinning threads saw the crowd grow
    assert crowd.skin([0.0], "dqs").shape == (1, 31 * per_instance, 3)
