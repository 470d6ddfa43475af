"""UsdSkel's joint-transform sampling done in NumPy (dqskin.readers.usd_anim) against usd-core:
USD's own interpolation of float3[], half3[] and quatf[] attributes, UsdSkel's
``ComputeJointLocalTransforms`` on every animation of the shared assets and on sparse rigs,
and the loader's fallback to UsdSkel where the samples could resolve otherwise."""

import numpy as np
import pytest
from pxr import Gf, Sdf, Usd, Vt
from test_usd import build_rig

from dqskin.readers import load
from dqskin.readers.usd import load_usd
from dqskin.readers.usd_anim import _lerp, _slerp

rng = np.random.default_rng(7)


def _interpolated(type_name, lower, upper, alphas):
    """What USD resolves for an attribute of ``type_name`` sampled ``lower`` at 0 and
    ``upper`` at 1, at each of ``alphas``: (len(alphas), N, C) in the type's precision."""
    stage = Usd.Stage.CreateInMemory()
    attr = stage.DefinePrim("/P").CreateAttribute("a", Sdf.ValueTypeNames.Find(type_name))
    vt = {"float3[]": Vt.Vec3fArray, "half3[]": Vt.Vec3hArray, "quatf[]": Vt.QuatfArray}[type_name]
    for t, v in ((0.0, lower), (1.0, upper)):
        if type_name == "quatf[]":
            attr.Set(vt([Gf.Quatf(float(q[3]), *map(float, q[:3])) for q in v]), t)
        else:
            attr.Set(vt.FromNumpy(np.asarray(v, np.float64)), t)
    out = []
    for a in alphas:
        value = attr.Get(float(a))
        m = memoryview(value)
        out.append(np.frombuffer(bytes(m), m.format).reshape(m.shape))
    return np.stack(out)


def test_lerp_is_usds_interpolation_of_float3_and_half3_bit_for_bit():
    alphas = np.concatenate([rng.random(200), [1e-9, 0.5, 1 - 1e-9]])
    for type_name, dtype, scale in (("float3[]", np.float32, 100.0), ("half3[]", np.float16, 2.0)):
        lower = (rng.standard_normal((64, 3)) * scale).astype(dtype)
        upper = (rng.standard_normal((64, 3)) * scale).astype(dtype)
        want = _interpolated(type_name, lower, upper, alphas)
        got = _lerp(alphas[:, None, None], lower[None], upper[None])
        assert got.dtype == dtype
        np.testing.assert_array_equal(got, want.astype(dtype), err_msg=type_name)


def test_slerp_is_usds_interpolation_of_quatf():
    """Bit for bit but for NumPy's float32 sine, correctly rounded where glibc's ``sinf`` is
    not always: components of these unit quaternions at most 2.5e-7 apart (2 float32 ulps of
    1), in well under 1% of them. Covers both signs of the dot product and nearly equal
    rotations (USD's linear branch, bit for bit)."""
    q0 = rng.standard_normal((400, 4))
    q1 = rng.standard_normal((400, 4))
    q1[:50] = q0[:50] + rng.standard_normal((50, 4)) * 1e-4  # nearly equal: linear weights
    q0 = (q0 / np.linalg.norm(q0, axis=1, keepdims=True)).astype(np.float32)
    q1 = (q1 / np.linalg.norm(q1, axis=1, keepdims=True)).astype(np.float32)
    dots = (q0.astype(np.float64) * q1).sum(axis=1)
    assert (dots < 0).sum() > 100 and (dots > 0).sum() > 100
    alphas = np.concatenate([rng.random(12), [0.5]])
    want = _interpolated("quatf[]", q0, q1, alphas)
    got = _slerp(alphas[:, None, None], q0[None], q1[None])
    assert np.abs(got - want).max() <= 2.5e-7
    assert (got != want).mean() < 0.01
    np.testing.assert_array_equal(got[:, :50], want[:, :50])  # the linear branch


def _probes(keys):
    k = np.asarray(keys, np.float64)
    inner = k[:-1, None] + np.diff(k)[:, None] * np.array([0.013, 0.37, 0.5, 0.999])
    return np.concatenate([k, inner.ravel(), [k[0] - 1.5, k[-1] + 2.0]])


def _check_animation(anim, probes=None, keys=None):
    """The loader's sampler against UsdSkel frame by frame: equal at every sample and outside
    the samples; between them, where a slerped rotation may be 2 float32 ulps off, each matrix
    entry within 2·10⁻⁶ of its joint's largest rotation-scale entry (or of 1)."""
    assert anim._tracks is not None, anim.name  # sampled here, not by UsdSkel per frame
    if keys is None:  # (key_times has the blend-shape weights' samples too)
        keys = anim.key_times if anim.key_times.size else np.zeros(1)
    if probes is None:
        probes = _probes(keys) if len(keys) > 1 else np.array([keys[0], keys[0] + 0.5])
    got = anim.local_transforms(probes)
    want = anim._usdskel_local_transforms(probes)
    assert got.shape == want.shape and got.dtype == np.float64
    exact = np.isin(probes, keys) | (probes < keys[0]) | (probes > keys[-1])
    np.testing.assert_array_equal(got[exact], want[exact], err_msg=anim.name)
    scale = np.maximum(np.abs(want[..., :3, :3]).max(axis=(-1, -2)), 1.0)[..., None, None]
    assert (np.abs(got - want) <= 2e-6 * scale).all(), anim.name
    return len(probes)


SHARED_USD = ["usd-wg/CesiumMan/CesiumMan.usdz", "usd-wg/RiggedFigure/RiggedFigure.usdz",
              "usd-wg/RiggedSimple/RiggedSimple.usdz",
              "openusd/pxr/usd/usdSkel/testenv/testUsdSkelBakeSkinning/lbs.usda",
              "openusd/pxr/usd/usdSkel/testenv/testUsdSkelBakeSkinning/dqs.usda",
              "openusd/pxr/usdImaging/usdImagingGL/testenv/testUsdImagingGLSkelSkinning/"
              "test_lbs.usda",
              "openusd/pxr/usdImaging/usdImagingGL/testenv/testUsdImagingGLUsdSkel/twoBends.usda"]


@pytest.mark.parametrize("name", SHARED_USD)
def test_shared_animations_sample_as_usdskel(shared_assets, name):
    scene = load(shared_assets / name)
    anims = [s.animation for s in scene.skeletons if s.animation is not None]
    assert anims
    assert sum(_check_animation(a) for a in anims) >= 2


def test_sparse_animation_of_defaults_and_samples(tmp_path):
    """build_rig's animation drives two of three joints (the third keeps its rest transform),
    its translations and scales are default values, its rotations time samples; with its
    joints listed in another order than the skeleton's too."""
    anim = load_usd(build_rig(tmp_path / "rig.usda")).skeletons[0].animation
    _check_animation(anim)
    path = build_rig(tmp_path / "swapped.usda")
    stage = Usd.Stage.Open(str(path))
    prim = stage.GetPrimAtPath("/Root/Rig/Skel/Anim")
    prim.GetAttribute("joints").Set(["a/b", "a"])
    stage.Save()
    _check_animation(load_usd(path).skeletons[0].animation)


def test_random_animation_with_unnormalized_rotations_and_negative_scales(tmp_path):
    """Seven keys at uneven, fractional times; quaternions of lengths 0.1 to 3; scales from
    -1.5 to 1.5; translations of tens of units; probed densely, before and after the keys."""
    path = build_rig(tmp_path / "random.usda")
    stage = Usd.Stage.Open(str(path))
    prim = stage.GetPrimAtPath("/Root/Rig/Skel/Anim")
    attrs = {a: prim.GetAttribute(a) for a in ("translations", "rotations", "scales")}
    for attr in attrs.values():
        attr.Clear()
    keys = np.sort(rng.choice(np.arange(-20, 60) * 0.37, 7, replace=False))
    for k in keys.tolist():
        attrs["translations"].Set(Vt.Vec3fArray.FromNumpy(rng.standard_normal((2, 3)) * 50), k)
        q = rng.standard_normal((2, 4)) * (rng.random((2, 1)) * 3 + 0.1)
        attrs["rotations"].Set(Vt.QuatfArray([Gf.Quatf(*map(float, (x[3], *x[:3]))) for x in q]),
                               k)
        attrs["scales"].Set(Vt.Vec3hArray.FromNumpy(rng.random((2, 3)) * 3 - 1.5), k)
    stage.Save()
    anim = load_usd(path).skeletons[0].animation
    assert set(keys.tolist()) <= set(anim.key_times.tolist())
    _check_animation(anim, np.concatenate([keys, np.linspace(keys[0] - 3, keys[-1] + 3, 1500)]),
                     keys)


def test_nan_times_are_left_to_usdskel(tmp_path):
    """USD reads a NaN time code as the default time: so does the loader's animation."""
    anim = load_usd(build_rig(tmp_path / "rig.usda")).skeletons[0].animation
    t = np.array([1.0, np.nan, 3.5])
    np.testing.assert_array_equal(anim.local_transforms(t), anim._usdskel_local_transforms(t))


def test_samples_usd_would_resolve_otherwise_are_left_to_usdskel(tmp_path):
    """A blocked rotation sample (UsdSkel composes identity rotations from it on, where the
    samples before it would be held) and rotations from a value clip: the loader leaves both
    to UsdSkel, frame by frame."""
    path = build_rig(tmp_path / "blocked.usda")
    stage = Usd.Stage.Open(str(path))
    rot = stage.GetPrimAtPath("/Root/Rig/Skel/Anim").GetAttribute("rotations")
    rot.Set(Sdf.ValueBlock(), 6.0)
    stage.Save()
    anim = load_usd(path).skeletons[0].animation
    assert anim._tracks is None
    t = np.array([1.5, 4.0, 5.0, 6.0, 7.0])
    got = anim.local_transforms(t)
    np.testing.assert_array_equal(got, anim._usdskel_local_transforms(t))
    assert not np.allclose(got[3], got[1])  # not held from time 4

    # rotations as quath[] (not the schema's quatf[]): UsdSkel gives the rest pose throughout
    path = build_rig(tmp_path / "quath.usda")
    layer = Sdf.Layer.FindOrOpen(str(path))
    spec = layer.GetPrimAtPath("/Root/Rig/Skel/Anim")
    attr = spec.attributes["rotations"]
    samples = {t: layer.QueryTimeSample(attr.path, t) for t in layer.ListTimeSamplesForPath(
        attr.path)}
    spec.RemoveProperty(attr)
    attr = Sdf.AttributeSpec(spec, "rotations", Sdf.ValueTypeNames.QuathArray)
    for t, v in samples.items():
        layer.SetTimeSample(attr.path, t, Vt.QuathArray([Gf.Quath(q) for q in v]))
    # unit scales: the first key is then the rest pose, which the loader's check at the first
    # key cannot tell from UsdSkel's answer
    spec.attributes["scales"].default = Vt.Vec3hArray([Gf.Vec3h(1, 1, 1)] * 2)
    layer.Save()
    anim = load_usd(path).skeletons[0].animation
    assert anim._tracks is None
    t = np.array([0.0, 2.0, 4.0])
    got = anim.local_transforms(t)
    np.testing.assert_array_equal(got, anim._usdskel_local_transforms(t))
    np.testing.assert_array_equal(got[0], got[2])

    path = build_rig(tmp_path / "clipped.usda")
    stage = Usd.Stage.Open(str(path))
    prim = stage.GetPrimAtPath("/Root/Rig/Skel/Anim")
    clip = Sdf.Layer.CreateNew(str(tmp_path / "rotations_clip.usda"))
    Sdf.CopySpec(stage.GetRootLayer(), prim.GetPath(), clip, Sdf.Path("/Anim"))
    clip.Save()
    prim.GetAttribute("rotations").Clear()
    clips = Usd.ClipsAPI(prim)
    clips.SetClipAssetPaths([Sdf.AssetPath("./rotations_clip.usda")])
    clips.SetClipPrimPath("/Anim")
    clips.SetClipActive([(0.0, 0.0)])
    clips.SetClipTimes([(0.0, 0.0), (4.0, 4.0)])
    stage.Save()
    anim = load_usd(path).skeletons[0].animation
    assert anim._tracks is None
    t = np.array([0.0, 1.5, 4.0])
    np.testing.assert_array_equal(anim.local_transforms(t), anim._usdskel_local_transforms(t))
    assert not np.allclose(anim.local_transforms([1.0]), anim.local_transforms([3.0]))
