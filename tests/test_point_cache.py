"""``dqskin info`` on point caches: dqskin's own (one layer, value clips) and UsdSkel's
``BakeSkinning`` output. Oracles: usd-core read directly (sample times, point counts, rates) and
``UsdGeom.BBoxCache`` world bounds from the extents each writer authored (BakeSkinning's are
UsdSkel's own; CesiumMan's only transform above the mesh is a quarter turn, so the aligned box of
the extent is the exact point bound).
"""

import re

import numpy as np
import pytest
from pxr import Gf, Sdf, Usd, UsdGeom, UsdSkel

from dqskin.cli import main

MESH = "/CesiumMan/Geom/Z_UP/Armature/Skeleton_torso_joint_1_3/Cesium_Man_2"


@pytest.fixture(scope="module")
def caches(shared_assets, tmp_path_factory):
    src = shared_assets / "usd-wg" / "CesiumMan" / "CesiumMan.usdz"
    tmp = tmp_path_factory.mktemp("caches")
    ours, clips = tmp / "cesium.usdc", tmp / "cesium_clips.usda"
    assert main(["skin", str(src), "--out", str(ours)]) == 0
    assert main(["skin", str(src), "--out", str(clips), "--clips", "--chunk", "16"]) == 0
    baked = tmp / "baked.usda"  # UsdSkel's bake, over a layer that sublayers the asset
    layer = Sdf.Layer.CreateNew(str(baked))
    layer.subLayerPaths.append(str(src))
    stage = Usd.Stage.Open(layer)
    stage.SetTimeCodesPerSecond(24)
    stage.SetFramesPerSecond(24)
    assert UsdSkel.BakeSkinning(stage.Traverse(), Gf.Interval(1, 48))
    layer.Save()
    return {"ours": ours, "clips": clips, "baked": baked}


def _info(path, capsys):
    assert main(["info", str(path)]) == 0
    return capsys.readouterr().out


def _bounds(path, start, end):
    """World bounds over the time codes start..end from the authored extents (BBoxCache)."""
    stage = Usd.Stage.Open(str(path))
    prim = stage.GetPrimAtPath(MESH)
    times = [t for t in UsdGeom.Mesh(prim).GetPointsAttr().GetTimeSamples() if start <= t <= end]
    lo, hi = np.full(3, np.inf), np.full(3, -np.inf)
    for t in times:
        box = UsdGeom.BBoxCache(t, [UsdGeom.Tokens.default_]).ComputeWorldBound(prim)
        r = box.ComputeAlignedRange()
        lo, hi = np.minimum(lo, r.GetMin()), np.maximum(hi, r.GetMax())
    return lo, hi


@pytest.mark.parametrize("kind", ["ours", "clips", "baked"])
def test_info_on_a_point_cache(caches, capsys, kind):
    path = caches[kind]
    out = _info(path, capsys)
    stage = Usd.Stage.Open(str(path))
    mesh = UsdGeom.Mesh(stage.GetPrimAtPath(MESH))
    samples = mesh.GetPointsAttr().GetTimeSamples()
    assert len(samples) == 48 and (samples[0], samples[-1]) == (1, 48)
    points = len(mesh.GetPointsAttr().Get(1))
    faces = len(mesh.GetFaceVertexCountsAttr().Get())
    assert "frames: 1 .. 48 (48 samples; time codes at 24/s: 0.0416667 .. 2 s; 24 fps)" in out
    assert f"mesh {MESH!r}: {points} points, {faces} faces; points animated: 48 samples " \
           "(1 .. 48)" in out
    normals = stage.GetPrimAtPath(MESH).GetAttribute("primvars:normals").GetNumTimeSamples()
    assert normals == (48 if kind != "baked" else 0)  # BakeSkinning leaves them as they were
    assert f"normals (primvars:normals, {f'{normals} samples' if normals else 'static'})" in out
    has_velocities = mesh.GetVelocitiesAttr().GetNumTimeSamples()
    assert has_velocities == (48 if kind != "baked" else 0)  # BakeSkinning writes none
    assert ("velocities (velocities, 48 samples)" in out) == bool(has_velocities)
    assert ("value clips: 3 clip layers" in out) == (kind == "clips")
    ranges = re.findall(r"frames (\S+) \.\. (\S+): min \((.*?)\), max \((.*?)\)", out)
    assert [(a, b) for a, b, *_ in ranges] == [("1", "12"), ("13", "24"), ("25", "36"),
                                               ("37", "48")]
    for a, b, lo, hi in ranges:
        want_lo, want_hi = _bounds(path, float(a), float(b))
        np.testing.assert_allclose([float(x) for x in lo.split(",")], want_lo, rtol=1e-3,
                                   atol=1e-4)
        np.testing.assert_allclose([float(x) for x in hi.split(",")], want_hi, rtol=1e-3,
                                   atol=1e-4)
    assert out.rstrip().endswith("problems: none")


def test_info_names_are_escaped(tmp_path, capsys):
    """A prim or file name cannot write control characters to the terminal."""
    path = tmp_path / "evil\x1b[2J.usda"
    stage = Usd.Stage.CreateNew(str(path))
    mesh = UsdGeom.Mesh.Define(stage, "/Root/M")
    mesh.GetPointsAttr().Set([(0, 0, 0), (1, 0, 0), (0, 1, 0)], 1.0)
    mesh.GetPointsAttr().Set([(0, 0, 0), (2, 0, 0), (0, 1, 0)], 2.0)
    mesh.GetFaceVertexCountsAttr().Set([3])
    mesh.GetFaceVertexIndicesAttr().Set([0, 1, 2])
    stage.GetRootLayer().Save()
    out = _info(path, capsys)
    assert "\x1b" not in out and "\\x1b[2J" in out
    assert "frames 1 .. 1: min (0, 0, 0), max (1, 1, 0)" in out
    assert "frames 2 .. 2: min (0, 0, 0), max (2, 1, 0)" in out
    assert "no normals, velocities or UVs" in out
