"""dqskin.usd against UsdSkel's C++ and Pixar's baked baselines, on every shared USD asset."""

import numpy as np
import pytest
from pxr import Gf, Sdf, Usd, UsdGeom, UsdSkel, Vt

from dqskin.options import SkinOptions
from dqskin.pipeline import rigid_transforms
from dqskin.readers.usd import load_rigid_prims, load_usd

TOKENS = {"lbs": "classicLinear", "dqs": "dualQuaternion"}
BAKE = "openusd/pxr/usd/usdSkel/testenv/testUsdSkelBakeSkinning"
JOINT_INFLUENCES = "openusd/pxr/usd/usdSkel/testenv/testUsdSkelSkinningQuery/jointInfluences.usda"
POPULATE = "openusd/pxr/usd/usdSkel/testenv/testUsdSkelCache/populate.usda"
ASSETS = [
    "openusd/pxr/usd/usdSkel/doxygen/skinnedArm.usda",
    f"{BAKE}/lbs.usda",
    f"{BAKE}/dqs.usda",
    "openusd/pxr/usdImaging/usdImagingGL/testenv/testUsdImagingGLSkelSkinning/test_lbs.usda",
    "openusd/pxr/usdImaging/usdImagingGL/testenv/testUsdImagingGLSkelSkinning/test_dqs.usda",
    "openusd/pxr/usdImaging/usdImagingGL/testenv/testUsdImagingGLUsdSkel/twoBends.usda",
    "tinyusdz/simple-skin-test.usda",
    "tinyusdz/skintest.usda",
    "tinyusdz/skintest.usdc",
    "tinyusdz/synthetic-skin-8influences.usda",
    "usd-wg/CesiumMan/CesiumMan.usdz",
    "usd-wg/RiggedFigure/RiggedFigure.usdz",
    "usd-wg/RiggedSimple/RiggedSimple.usdz",
]
ERROR_PRIMS = {  # jointInfluences.usda: prim -> what the message must say
    "ErrorCases/MismatchedInterpolation": "interpolation 'constant' != jointWeights",
    "ErrorCases/InvalidInterpolation1": "interpolation 'uniform'",
    "ErrorCases/InvalidInterpolation2": "interpolation 'varying'",
    "ErrorCases/MismatchedElementSize": "elementSize 3 != jointWeights elementSize 4",
    "ErrorCases/InvalidElementSize": "elementSize -1",
    "ErrorCases/MismatchedArraySize": "3 jointIndices but 1 jointWeights",
    "ErrorCases/InvalidArraySize1": "not a multiple of elementSize 2",
    "ErrorCases/InvalidArraySize2": "4 constant joint influences for elementSize 2",
}


# -- UsdSkel oracles (row-vector Gf matrices; only UsdSkel computes here) -----------------------

def usdskel_cache(stage):
    cache = UsdSkel.Cache()
    for prim in stage.Traverse(Usd.TraverseInstanceProxies()):
        if prim.IsA(UsdSkel.Root):
            cache.Populate(UsdSkel.Root(prim), Usd.TraverseInstanceProxies())
    return cache


def usdskel_skin(stage, cache, path, t, method, normals=None, normal_vertex=None):
    """UsdSkel.SkinPoints (and SkinNormals) with UsdSkel's skinning transforms, in gprim space."""
    prim = stage.GetPrimAtPath(path)
    q = cache.GetSkinningQuery(prim)
    skel = UsdSkel.BindingAPI(prim).GetInheritedSkeleton()
    tc = Usd.TimeCode(float(t))
    xf = cache.GetSkelQuery(skel).ComputeSkinningTransforms(tc)
    if q.GetJointMapper():
        xf = q.GetJointMapper().Remap(xf)
    pts = Vt.Vec3fArray(UsdGeom.PointBased(prim).GetPointsAttr().Get(tc))
    idx, w = q.ComputeVaryingJointInfluences(len(pts), tc)
    K = q.GetNumInfluencesPerComponent()
    assert UsdSkel.SkinPoints(TOKENS[method], q.GetGeomBindTransform(tc), xf, idx, w, K, pts)
    skel_to_gprim = (UsdGeom.Imageable(skel.GetPrim()).ComputeLocalToWorldTransform(tc)
                     * UsdGeom.Imageable(prim).ComputeLocalToWorldTransform(tc).GetInverse())
    m = np.array(skel_to_gprim)
    p = np.asarray(pts, np.float64) @ m[:3, :3] + m[3, :3]
    if normals is None:
        return p, None
    if normal_vertex is not None:
        i = np.asarray(idx).reshape(-1, K)[normal_vertex]
        idx = Vt.IntArray.FromNumpy(np.ascontiguousarray(i.ravel(), dtype=np.int32))
        w = Vt.FloatArray.FromNumpy(np.ascontiguousarray(
            np.asarray(w).reshape(-1, K)[normal_vertex].ravel(), dtype=np.float32))
    n = Vt.Vec3fArray.FromNumpy(np.ascontiguousarray(normals, dtype=np.float32))
    inv_t = Vt.Matrix3dArray([x.GetInverse().GetTranspose().ExtractRotationMatrix() for x in xf])
    g = q.GetGeomBindTransform(tc).GetInverse().GetTranspose().ExtractRotationMatrix()
    assert UsdSkel.SkinNormals(TOKENS[method], g, inv_t, idx, w, K, n)
    nm = np.linalg.inv(m[:3, :3]).T
    n = np.asarray(n, np.float64) @ nm
    return p, n / np.linalg.norm(n, axis=1, keepdims=True)


def usd_rest_normals(stage, path):
    """Rest normals straight from the file, independent of our loader.

    Returns ``(normals, normal_vertex)`` with ``normal_vertex`` the face-vertex map for
    faceVarying (None for vertex), or (None, None)."""
    prim = stage.GetPrimAtPath(path)
    pv = UsdGeom.PrimvarsAPI(prim).GetPrimvar("normals")
    if pv and pv.HasAuthoredValue():
        values, interp = pv.ComputeFlattened(Usd.TimeCode.EarliestTime()), pv.GetInterpolation()
    else:
        attr = UsdGeom.PointBased(prim).GetNormalsAttr()
        if not attr.HasAuthoredValue():
            return None, None
        values, interp = attr.Get(Usd.TimeCode.EarliestTime()), \
            UsdGeom.PointBased(prim).GetNormalsInterpolation()
    normals = np.asarray(values, np.float64)
    if interp == UsdGeom.Tokens.faceVarying:
        return normals, np.asarray(UsdGeom.Mesh(prim).GetFaceVertexIndicesAttr().Get())
    return normals, None


def sample_times(scene, count=4):
    t = scene.times
    return np.unique(np.concatenate([t[:: max(1, len(t) // count)], t[-1:]]))


def assert_close(ours, ref, scale, what):
    err = np.abs(np.asarray(ours, np.float64) - ref).max() / scale
    assert err < 1e-5, f"{what}: relative error {err:.2e}"


# -- Pixar's baked baselines --------------------------------------------------------------------

@pytest.mark.parametrize("method", ["lbs", "dqs"])
def test_bake_matches_pixar_baseline(shared_assets, method, device):
    """Points and normals of every point-based prim, every frame, against ``*.baked.usda``."""
    scene = load_usd(shared_assets / BAKE / f"{method}.usda")
    assert {m.skinning_method for m in scene.meshes} == {method}
    assert np.array_equal(scene.times, np.arange(1.0, 31.0))
    base = Usd.Stage.Open(str(shared_assets / BAKE / "baseline" / f"{method}.baked.usda"))
    other = "dqs" if method == "lbs" else "lbs"
    skinned = scene.skin(device=device, normals=True)
    points, normals = skinned.points, skinned.normals
    wrong = scene.skin(method=other, device=device).points
    assert sorted(points) == ["/Root/Curves", "/Root/Mesh", "/Root/MeshWithFaceVaryingNormals",
                              "/Root/MeshWithNormals"]
    assert sorted(normals) == ["/Root/MeshWithFaceVaryingNormals", "/Root/MeshWithNormals"]
    worst_other = 0.0
    for name, p in points.items():
        prim = base.GetPrimAtPath(name)
        for i, t in enumerate(scene.times):
            ref = np.asarray(prim.GetAttribute("points").Get(t), np.float64)
            scale = np.abs(ref).max()
            assert_close(p[i], ref, scale, f"{name} points at {t}")
            worst_other = max(worst_other, np.abs(wrong[name][i] - ref).max() / scale)
            if name in normals:
                ref_n = np.asarray(prim.GetAttribute("normals").Get(t), np.float64)
                assert_close(normals[name][i], ref_n, 1.0, f"{name} normals at {t}")
    assert worst_other > 1e-3, "the baseline does not tell LBS from DQS"


@pytest.mark.parametrize("method", ["lbs", "dqs"])
def test_rigid_prims_match_pixar_baseline(shared_assets, method, device):
    """Sphere/Cube/Cylinder (constant influences, no points) are baked as xformOp:transform."""
    scene = load_usd(shared_assets / BAKE / f"{method}.usda")
    rigid = load_rigid_prims(scene)
    assert sorted(r.name for r in rigid) == ["/Root/Cube", "/Root/Cylinder", "/Root/Sphere"]
    base = Usd.Stage.Open(str(shared_assets / BAKE / "baseline" / f"{method}.baked.usda"))
    for r in rigid:
        ours = rigid_transforms(scene, r, scene.times, SkinOptions(device=device))
        attr = base.GetPrimAtPath(r.name).GetAttribute("xformOp:transform")
        ref = np.stack([np.array(attr.Get(t)).T for t in scene.times])
        assert_close(ours, ref, np.abs(ref).max(), r.name)


# -- every shared asset against UsdSkel ---------------------------------------------------------

def test_every_shared_usd_asset_is_covered(shared_assets):
    found = {str(p.relative_to(shared_assets)) for ext in ("usd", "usda", "usdc", "usdz")
             for p in shared_assets.rglob(f"*.{ext}")}
    found = {f for f in found if "/baseline/" not in f}
    assert found == set(ASSETS) | {JOINT_INFLUENCES, POPULATE}


@pytest.mark.parametrize("method", ["lbs", "dqs"])
@pytest.mark.parametrize("asset", ASSETS)
def test_asset_matches_usdskel(shared_assets, asset, method, device):
    path = shared_assets / asset
    scene = load_usd(path)
    stage = Usd.Stage.Open(str(path))
    cache = usdskel_cache(stage)
    times = sample_times(scene)
    skinned = scene.skin(times, method, device=device, normals=True)
    points, normals = skinned.points, skinned.normals
    for m in scene.meshes:
        rest_n, normal_vertex = usd_rest_normals(stage, m.name)
        assert (rest_n is None) == (m.normals is None), m.name
        for i, t in enumerate(times):
            ref, ref_n = usdskel_skin(stage, cache, m.name, t, method, rest_n, normal_vertex)
            assert_close(points[m.name][i], ref, np.abs(ref).max(), f"{m.name} at {t}")
            if rest_n is not None:
                assert_close(normals[m.name][i], ref_n, 1.0, f"{m.name} normals at {t}")


def test_loaded_rig_data(shared_assets):
    """Skeleton, influences (skel:joints remapped), bind data and metadata, from the file."""
    path = shared_assets / ASSETS[5]  # twoBends: per-mesh skel:joints subsets
    scene = load_usd(path)
    layer = Sdf.Layer.FindOrOpen(str(path))
    assert (scene.up_axis, scene.meters_per_unit) == (layer.pseudoRoot.GetInfo("upAxis"),
                                                      layer.pseudoRoot.GetInfo("metersPerUnit"))
    assert scene.time_codes_per_second == 24.0 and np.array_equal(scene.times, [0.0])
    stage = Usd.Stage.Open(str(path))
    skel_prim = UsdSkel.Skeleton(stage.GetPrimAtPath("/Root/joint1"))
    (skel,) = scene.skeletons
    names = [str(j) for j in skel_prim.GetJointsAttr().Get()]
    assert skel.joint_names == names and skel.name == "/Root/joint1"
    parents = [names.index(n.rsplit("/", 1)[0]) if "/" in n else -1 for n in names]
    assert skel.parents.tolist() == parents
    bind = np.array(skel_prim.GetBindTransformsAttr().Get()).transpose(0, 2, 1)
    np.testing.assert_array_equal(skel.bind_transforms, bind)
    rest = np.array(skel_prim.GetRestTransformsAttr().Get()).transpose(0, 2, 1)
    np.testing.assert_array_equal(skel.rest_transforms, rest)
    assert scene.animations[0] is not None and scene.animations[0].key_times.size == 0
    for m in scene.meshes:
        prim = UsdSkel.BindingAPI(stage.GetPrimAtPath(m.name))
        local = [str(j) for j in prim.GetJointsAttr().Get()]
        K = prim.GetJointIndicesPrimvar().GetElementSize()
        idx = np.array(prim.GetJointIndicesPrimvar().Get()).reshape(-1, K)
        w = np.array(prim.GetJointWeightsPrimvar().Get(), np.float32).reshape(-1, K)
        expect = np.array([[names.index(local[i]) for i in row] for row in idx])
        np.testing.assert_array_equal(m.joint_indices, expect)
        np.testing.assert_array_equal(m.joint_weights, w)
        mesh = UsdGeom.Mesh(prim.GetPrim())
        counts = np.array(mesh.GetFaceVertexCountsAttr().Get())
        np.testing.assert_array_equal(m.face_vertex_counts, counts)
        np.testing.assert_array_equal(m.face_vertex_indices, mesh.GetFaceVertexIndicesAttr().Get())
        assert m.faces.shape == ((counts - 2).sum(), 3)
        assert m.skinning_method == "lbs" and m.skeleton == 0
        np.testing.assert_array_equal(m.points, np.array(mesh.GetPointsAttr().Get(), np.float32))


def test_fan_triangulation_holes_and_winding(tmp_path):
    path = tmp_path / "fan.usda"
    build_rig(path)
    stage = Usd.Stage.Open(str(path))
    mesh = UsdGeom.Mesh(stage.GetPrimAtPath("/Root/Geo/Body"))
    mesh.GetFaceVertexCountsAttr().Set([3, 5, 4, 2])
    mesh.GetFaceVertexIndicesAttr().Set([0, 1, 6, 1, 2, 3, 8, 7, 3, 4, 9, 8, 4, 9])
    stage.GetRootLayer().Save()
    m = load_usd(path).meshes[0]
    assert m.faces.tolist() == [[0, 1, 6], [1, 2, 3], [1, 3, 8], [1, 8, 7], [3, 4, 9], [3, 9, 8]]
    mesh.CreateHoleIndicesAttr([1])
    mesh.CreateOrientationAttr(UsdGeom.Tokens.leftHanded)
    stage.GetRootLayer().Save()
    m = load_usd(path).meshes[0]
    assert m.faces.tolist() == [[6, 1, 0], [9, 4, 3], [8, 9, 3]]
    assert m.face_vertex_counts.tolist() == [3, 5, 4, 2]


# -- blend shapes, animated transforms, unanimated joints: UsdSkel.BakeSkinning ----------------

def _m(a):
    return Gf.Matrix4d(np.asarray(a, np.float64).T.tolist())


def build_rig(path, *, method="classicLinear", joints=("a", "a/b", "a/b/c"), joint_indices=None,
              joint_weights=None, mesh_joints=None, normal_offsets=False):
    """A 3-joint chain bending a 2×5 strip of quads, with blend shapes and animated parents.

    The animation drives two of the three joints (the third keeps its rest transform), with
    rotations, a non-uniform scale and blend-shape weights over time codes 0..4; the skeleton's
    and the mesh's parents are animated Xforms; one blend shape is sparse (pointIndices), the
    other has an inbetween, and weights go below 0 and above 1.
    """
    st = Usd.Stage.CreateNew(str(path))
    st.SetStartTimeCode(0)
    st.SetEndTimeCode(4)
    st.SetTimeCodesPerSecond(30)
    UsdGeom.SetStageUpAxis(st, "Z")
    UsdGeom.SetStageMetersPerUnit(st, 0.5)
    UsdSkel.Root.Define(st, "/Root")
    rig = UsdGeom.Xform.Define(st, "/Root/Rig")
    op = rig.AddTranslateOp()
    for t in range(5):
        op.Set(Gf.Vec3d(0.1 * t, 0.2, -0.3), t)
    rig.AddScaleOp().Set(Gf.Vec3f(1.5, 1.5, 1.5))
    geo = UsdGeom.Xform.Define(st, "/Root/Geo")
    op = geo.AddRotateZOp()
    for t in range(5):
        op.Set(10.0 * t, t)
    geo.AddTranslateOp().Set(Gf.Vec3d(0.5, -0.25, 0.0))
    skel = UsdSkel.Skeleton.Define(st, "/Root/Rig/Skel")
    J = len(joints)
    skel.CreateJointsAttr(list(joints))
    bind = np.tile(np.eye(4), (J, 1, 1))
    bind[:, 0, 3] = np.arange(J)
    skel.CreateBindTransformsAttr(Vt.Matrix4dArray([_m(b) for b in bind]))
    rest = np.tile(np.eye(4), (J, 1, 1))
    rest[1:, 0, 3] = 1.0
    skel.CreateRestTransformsAttr(Vt.Matrix4dArray([_m(r) for r in rest]))
    anim = UsdSkel.Animation.Define(st, "/Root/Rig/Skel/Anim")
    anim.CreateJointsAttr(list(joints)[:2])
    anim.CreateTranslationsAttr(Vt.Vec3fArray([Gf.Vec3f(0, 0, 0), Gf.Vec3f(1, 0, 0)]))
    anim.CreateScalesAttr(Vt.Vec3hArray([Gf.Vec3h(1, 1, 1), Gf.Vec3h(1, 1.2, 1)]))
    rot = anim.CreateRotationsAttr()
    for t in range(5):
        a = np.radians(20.0 * t)
        rot.Set(Vt.QuatfArray([Gf.Quatf(float(np.cos(a / 4)), 0, float(np.sin(a / 4)), 0),
                               Gf.Quatf(float(np.cos(a / 2)), 0, 0, float(np.sin(a / 2)))]), t)
    UsdSkel.BindingAPI.Apply(skel.GetPrim()).CreateAnimationSourceRel().SetTargets(
        [anim.GetPath()])
    mesh = UsdGeom.Mesh.Define(st, "/Root/Geo/Body")
    x = np.linspace(0, 2, 5)
    pts = np.array([(xi, y, 0.0) for y in (-0.5, 0.5) for xi in x], np.float32)
    mesh.CreatePointsAttr(Vt.Vec3fArray.FromNumpy(pts))
    mesh.CreateFaceVertexCountsAttr([4] * 4)
    mesh.CreateFaceVertexIndicesAttr([i for q in range(4) for i in (q, q + 1, q + 6, q + 5)])
    mesh.CreateNormalsAttr(Vt.Vec3fArray.FromNumpy(np.tile(np.float32([0, 0, 1]), (10, 1))))
    mesh.SetNormalsInterpolation("vertex")
    binding = UsdSkel.BindingAPI.Apply(mesh.GetPrim())
    binding.CreateSkeletonRel().SetTargets([skel.GetPath()])
    if joint_indices is None:
        xr = np.tile(x, 2)
        lo = np.minimum(xr.astype(int), J - 2)
        joint_indices = np.stack([lo, lo + 1], 1)
        f = np.clip(xr - lo, 0, 1)
        joint_weights = np.stack([1 - f, f], 1)
    ji = np.asarray(joint_indices, np.int32)
    binding.CreateJointIndicesPrimvar(False, ji.shape[1]).Set(Vt.IntArray.FromNumpy(ji.ravel()))
    binding.CreateJointWeightsPrimvar(False, ji.shape[1]).Set(
        Vt.FloatArray.FromNumpy(np.asarray(joint_weights, np.float32).ravel()))
    g = np.eye(4)
    g[:3, 3] = (0.0, 0.1, 0.0)
    binding.CreateGeomBindTransformAttr(_m(g))
    binding.CreateSkinningMethodAttr(method)
    if mesh_joints is not None:
        binding.CreateJointsAttr(list(mesh_joints))
    smile = UsdSkel.BlendShape.Define(st, "/Root/Geo/Body/smile")
    smile.CreateOffsetsAttr(Vt.Vec3fArray([Gf.Vec3f(0, 0, 0.3), Gf.Vec3f(0, 0.1, 0.2)]))
    smile.CreatePointIndicesAttr(Vt.IntArray([2, 7]))
    if normal_offsets:
        smile.CreateNormalOffsetsAttr(Vt.Vec3fArray([Gf.Vec3f(0.2, 0, 0), Gf.Vec3f(0, -0.3, 0)]))
    puff = UsdSkel.BlendShape.Define(st, "/Root/Geo/Body/puff")
    off = np.zeros((10, 3), np.float32)
    off[:, 2] = np.linspace(0.0, 0.4, 10)
    puff.CreateOffsetsAttr(Vt.Vec3fArray.FromNumpy(off))
    half = puff.CreateInbetween("half")
    half.SetWeight(0.5)
    half.SetOffsets(Vt.Vec3fArray.FromNumpy(np.ascontiguousarray(off[:, [1, 2, 0]] * 0.7)))
    binding.CreateBlendShapesAttr(["smile", "puff"])
    binding.CreateBlendShapeTargetsRel().SetTargets([smile.GetPath(), puff.GetPath()])
    anim.CreateBlendShapesAttr(["puff", "smile", "unused"])
    weights = anim.CreateBlendShapeWeightsAttr()
    for t, w in enumerate([(0, 0, 1), (0.25, 1, 0), (0.5, 0.5, 0), (0.8, -0.5, 0), (1.4, 1.5, 0)]):
        weights.Set(Vt.FloatArray(w), t)
    st.GetRootLayer().Save()
    return path


@pytest.mark.parametrize("method", ["lbs", "dqs"])
def test_blend_shapes_and_animated_parents_match_bake(tmp_path, method, device):
    """UsdSkel.BakeSkinning on an in-memory copy is the oracle (blend shapes before skinning,
    inbetweens, normal offsets, undriven joints at rest, time-varying skel/gprim transforms)."""
    path = build_rig(tmp_path / "rig.usda", method=TOKENS[method], normal_offsets=True)
    scene = load_usd(path)
    (m,) = scene.meshes
    assert m.deformer is not None and m.output_transforms is not None
    assert np.array_equal(scene.times, np.arange(5.0))
    baked = Usd.Stage.Open(Sdf.Layer.OpenAsAnonymous(str(path)))
    assert UsdSkel.BakeSkinning(baked.Traverse())
    prim = baked.GetPrimAtPath(m.name)
    times = np.array(prim.GetAttribute("points").GetTimeSamples())
    assert len(times) >= 5 and np.any(times % 1)  # fractional times: interpolated animation
    skinned = scene.skin(times, device=device, normals=True)
    points, normals = skinned.points, skinned.normals
    moved = 0.0
    for i, t in enumerate(times):
        ref = np.asarray(prim.GetAttribute("points").Get(t), np.float64)
        assert_close(points[m.name][i], ref, np.abs(ref).max(), f"points at {t}")
        ref_n = np.asarray(prim.GetAttribute("normals").Get(t), np.float64)
        ref_n /= np.linalg.norm(ref_n, axis=1, keepdims=True)
        assert_close(normals[m.name][i], ref_n, 1.0, f"normals at {t}")
        moved = max(moved, np.abs(m.deformer.points_at([t])[0] - m.points).max())
    assert moved > 0.1, "blend shapes had no effect"


@pytest.mark.parametrize("method", ["lbs", "dqs"])
def test_velocities_through_blend_shapes_and_animated_parents(tmp_path, method, device):
    """Velocities are the analytic derivative of what is skinned: blend-shape weights, inbetweens,
    a translating skeleton parent and a rotating gprim parent, chained with the joints. Oracle: a
    central difference of skinned points inside each interval (away from the kinks at keys)."""
    path = build_rig(tmp_path / "rig.usda", method=TOKENS[method], normal_offsets=True)
    scene = load_usd(path)
    (m,) = scene.meshes
    t = np.array([0.3, 1.6, 2.45, 3.7])
    vel = scene.skin(t, device=device, velocities=True).velocities[m.name]
    h = 1e-3
    plus = scene.skin(t + h, device=device).points[m.name].astype(np.float64)
    minus = scene.skin(t - h, device=device).points[m.name].astype(np.float64)
    fd = (plus - minus) / (2 * h) * scene.time_codes_per_second
    speed = np.linalg.norm(fd, axis=-1).max()
    assert speed > 0.1
    assert np.abs(vel - fd).max() <= 2e-3 * speed, np.abs(vel - fd).max() / speed


@pytest.mark.parametrize("method", ["lbs", "dqs"])
def test_batched_velocities_equal_the_per_mesh_ones(tmp_path, method, device):
    """Two meshes skin in one batched launch (:mod:`dqskin.pipeline`): their velocities
    through blend shapes, a moving skeleton parent and a rotating gprim parent (output transforms)
    equal the per-mesh loop's, which the central-difference test above checks."""
    import dataclasses
    path = build_rig(tmp_path / "rig.usda", method=TOKENS[method], normal_offsets=True)
    scene = load_usd(path)
    (m,) = scene.meshes
    twin = dataclasses.replace(m, name=m.name + "_twin", output_transforms=None)
    pair = dataclasses.replace(scene, meshes=[m, twin])
    pair._skinners = {}
    t = np.array([0.3, 1.6, 2.45, 3.7])
    one = scene.skin(t, device=device, velocities=True).velocities[m.name]
    both = pair.skin(t, device=device, velocities=True).velocities
    skeleton_space = scene.skin(t, device=device, velocities=True, space="skeleton")
    assert m.output_transforms is not None and np.abs(one).max() > 0.1
    np.testing.assert_allclose(both[m.name], one, atol=2e-5 * np.abs(one).max())
    np.testing.assert_allclose(both[twin.name], skeleton_space.velocities[m.name],
                               atol=2e-5 * np.abs(one).max())


def test_velocities_sample_the_animation_once(tmp_path):
    """Scene.skin with velocities samples each skeleton's animation once per call (the joint
    derivatives take the transforms already sampled), one mesh or two, with the same result."""
    import dataclasses
    path = build_rig(tmp_path / "rig.usda", normal_offsets=True)
    scene = load_usd(path)
    (m,) = scene.meshes
    pair = dataclasses.replace(scene, meshes=[m, dataclasses.replace(m, name=m.name + "_2")])
    pair._skinners = {}
    t = np.array([0.3, 1.0, 2.45])
    want = scene.skin(t, velocities=True).velocities[m.name]  # (the keys decomposed once)
    for sc in (scene, pair):
        anim = sc.skeletons[0].animation
        calls = []
        real = anim.local_transforms
        anim.local_transforms = lambda times: calls.append(len(times)) or real(times)
        try:
            vel = sc.skin(t, velocities=True).velocities[m.name]
        finally:
            del anim.local_transforms
        assert calls == [3]
        np.testing.assert_allclose(vel, want, rtol=1e-6, atol=1e-6)


def test_blend_shape_rest_points_follow_the_definition(tmp_path):
    """Sub-shape weights as the UsdSkel docs define them, summed with NumPy.

    ``smile`` (no inbetween, sparse): weight w adds w·offsets at pointIndices, negative w too.
    ``puff`` (inbetween at 0.5): weights interpolate linearly between rest (0), the inbetween
    (0.5) and the primary shape (1).
    """
    path = build_rig(tmp_path / "rig.usda", normal_offsets=True)
    m = load_usd(path).meshes[0]
    smile, smile_n = np.zeros((10, 3)), np.zeros((10, 3))
    smile[[2, 7]] = [[0, 0, 0.3], [0, 0.1, 0.2]]
    smile_n[[2, 7]] = [[0.2, 0, 0], [0, -0.3, 0]]
    puff = np.zeros((10, 3))
    puff[:, 2] = np.linspace(0.0, 0.4, 10)
    half = puff[:, [1, 2, 0]] * 0.7
    expect = {1.0: m.points + 1.0 * smile + 0.5 * half,  # smile 1, puff 0.25
              3.0: m.points - 0.5 * smile + 0.4 * half + 0.6 * puff}  # smile -0.5, puff 0.8
    got = m.deformer.points_at(list(expect))
    for f, want in enumerate(expect.values()):
        np.testing.assert_allclose(got[f], want, atol=1e-6)
    normals = m.deformer.normals_at([1.0, 3.0])
    np.testing.assert_allclose(normals[0], m.normals + smile_n, atol=1e-6)
    np.testing.assert_allclose(normals[1], m.normals - 0.5 * smile_n, atol=1e-6)


# -- errors -------------------------------------------------------------------------------------

def _only(tmp_path, asset, keep, prims):
    """A layer over ``asset`` deactivating every prim of ``prims`` but ``keep``."""
    layer = Sdf.Layer.CreateNew(str(tmp_path / f"{keep.name}.usda"))
    layer.subLayerPaths.append(str(asset))
    for p in prims:
        if p != keep:
            Sdf.CreatePrimInLayer(layer, p).active = False
    layer.Save()
    return layer


def _meshes(asset):
    stage = Usd.Stage.Open(str(asset))
    return [p.GetPath() for p in stage.Traverse() if p.IsA(UsdGeom.Mesh)]


@pytest.mark.parametrize("prim", sorted(ERROR_PRIMS))
def test_joint_influence_error_cases(shared_assets, tmp_path, prim):
    """UsdSkel refuses these influences; so do we, naming the file, the prim and the fault."""
    asset = shared_assets / JOINT_INFLUENCES
    path = Sdf.Path("/JointInfluences/" + prim)
    layer = _only(tmp_path, asset, path, _meshes(asset))
    stage = Usd.Stage.Open(layer)
    q = usdskel_cache(stage).GetSkinningQuery(stage.GetPrimAtPath(path))
    assert q.ComputeJointInfluences() is None
    with pytest.raises(ValueError) as err:
        load_usd(layer.realPath)
    msg = str(err.value)
    assert layer.realPath in msg and str(path) in msg and ERROR_PRIMS[prim] in msg, msg


@pytest.mark.parametrize("method", ["lbs", "dqs"])
@pytest.mark.parametrize("prim", ["RigidWeights", "NonRigidWeights", "NonRigidWeightsDQ"])
def test_unnormalized_weights_match_usdskel(shared_assets, tmp_path, prim, method, device):
    """jointInfluences.usda's valid prims (weights 5..8, never renormalized), given points and a
    5-joint skeleton by an over layer, skin as UsdSkel skins them."""
    asset = shared_assets / JOINT_INFLUENCES
    path = Sdf.Path("/JointInfluences/" + prim)
    layer = _only(tmp_path, asset, path, _meshes(asset))
    stage = Usd.Stage.Open(layer)
    skel = UsdSkel.Skeleton(stage.OverridePrim("/Skel1"))
    names = ["r", "r/a", "r/a/b", "r/a/b/c", "r/a/b/c/d"]
    skel.CreateJointsAttr(names)
    rng = np.random.default_rng(7)
    bind, rest = np.tile(np.eye(4), (5, 1, 1)), np.tile(np.eye(4), (5, 1, 1))
    bind[:, :3, 3] = np.cumsum(rng.normal(size=(5, 3)), axis=0)
    rest[:, :3, 3] = rng.normal(size=(5, 3))
    c, s = np.cos(0.4), np.sin(0.4)
    rest[:, :2, :2] = [[c, -s], [s, c]]
    skel.CreateBindTransformsAttr(Vt.Matrix4dArray([_m(b) for b in bind]))
    skel.CreateRestTransformsAttr(Vt.Matrix4dArray([_m(r) for r in rest]))
    UsdGeom.Mesh(stage.GetPrimAtPath(path)).CreatePointsAttr(
        Vt.Vec3fArray.FromNumpy(rng.normal(size=(2, 3)).astype(np.float32)))
    layer.Save()
    scene = load_usd(layer.realPath)
    (m,) = scene.meshes
    q = usdskel_cache(stage).GetSkinningQuery(stage.GetPrimAtPath(path))
    idx, w = q.ComputeVaryingJointInfluences(2)
    np.testing.assert_array_equal(m.joint_weights.ravel(), np.asarray(w))
    np.testing.assert_array_equal(m.joint_indices.ravel(), np.asarray(idx))
    ours = scene.skin([0.0], method, device=device).points[m.name][0]
    ref, _ = usdskel_skin(stage, usdskel_cache(stage), str(path), 0.0, method)
    assert_close(ours, ref, np.abs(ref).max(), prim)


def test_populate_asset_has_no_skinnable_prim(shared_assets):
    path = shared_assets / POPULATE
    with pytest.raises(ValueError, match="populate.usda: /SkelBinding/Scope/Inherit: 0 constant"):
        load_usd(path)


def test_unreadable_files(tmp_path):
    with pytest.raises(ValueError, match="nope.usda: no such file"):
        load_usd(tmp_path / "nope.usda")
    (tmp_path / "a.obj").write_text("v 0 0 0\n")
    with pytest.raises(ValueError, match="not a USD file"):
        load_usd(tmp_path / "a.obj")
    (tmp_path / "bad.usda").write_text('#usda 1.0\ndef Mesh "A" { points = [ }\n')
    with pytest.raises(ValueError, match="bad.usda: cannot open as USD: .*Expected"):
        load_usd(tmp_path / "bad.usda")
    (tmp_path / "bad.usdc").write_bytes(b"PXR-USDC garbage")
    with pytest.raises(ValueError, match="bad.usdc: cannot open as USD"):
        load_usd(tmp_path / "bad.usdc")
    (tmp_path / "plain.usda").write_text(
        '#usda 1.0\ndef Mesh "A"\n{\n    point3f[] points = [(0, 0, 0)]\n}\n')
    with pytest.raises(ValueError, match="plain.usda: no SkelRoot prim"):
        load_usd(tmp_path / "plain.usda")


BAD_RIGS = {
    "index out of range": (dict(joint_indices=np.full((10, 1), 3), joint_weights=np.ones((10, 1))),
                           "/Root/Geo/Body: joint index 3 out of range for the 3 joints"),
    "negative index": (dict(joint_indices=np.full((10, 1), -1), joint_weights=np.ones((10, 1))),
                       "/Root/Geo/Body: joint index -1 out of range"),
    "NaN weight": (dict(joint_indices=np.zeros((10, 1)), joint_weights=np.full((10, 1), np.nan)),
                   "/Root/Geo/Body: jointWeights has NaN"),
    "negative weight": (dict(joint_indices=np.zeros((10, 1)), joint_weights=-np.ones((10, 1))),
                        "/Root/Geo/Body: jointWeights has a negative weight"),
    "joints out of order": (dict(joints=("a/b", "a", "a/b/c")),
                            "/Root/Rig/Skel: invalid joint topology: .*mis-ordered"),
    "unknown skel:joints": (dict(mesh_joints=("a", "a/x", "a/b/c")),
                            "/Root/Geo/Body: skel:joints names 'a/x', not a joint"),
    "mapped index out of range": (dict(mesh_joints=("a/b",)),
                                  "/Root/Geo/Body: joint index 2 out of range for the 1 joints "
                                  "of skel:joints"),
}


@pytest.mark.parametrize("case", sorted(BAD_RIGS))
def test_invalid_rigs(tmp_path, case):
    kwargs, message = BAD_RIGS[case]
    path = build_rig(tmp_path / "bad.usda", **kwargs)
    with pytest.raises(ValueError, match=f"bad.usda: {message}"):
        load_usd(path)


def test_invalid_face_topology(tmp_path):
    path = build_rig(tmp_path / "faces.usda")
    stage = Usd.Stage.Open(str(path))
    mesh = UsdGeom.Mesh(stage.GetPrimAtPath("/Root/Geo/Body"))
    mesh.GetFaceVertexIndicesAttr().Set([0, 1, 6, 99])
    mesh.GetFaceVertexCountsAttr().Set([4])
    stage.GetRootLayer().Save()
    with pytest.raises(ValueError, match="Body: faceVertexIndices has index 99 out of range"):
        load_usd(path)
    mesh.GetFaceVertexCountsAttr().Set([3])
    stage.GetRootLayer().Save()
    with pytest.raises(ValueError, match="Body: faceVertexCounts sum to 3 but there are 4"):
        load_usd(path)
