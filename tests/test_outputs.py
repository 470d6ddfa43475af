"""Outputs in the right place and time (issue 29): one space rule, materials that travel, every
input to a USD cache, one time model, ``--prims``; and ``--frames`` that cannot crash (issue 30).

Oracles: USD's own ``ComputeLocalToWorldTransform`` and ``UsdSkel.BakeSkinning``, pygltflib and
trimesh reading the files back, the source files' own bytes (zipfile, pygltflib), closed forms.
"""

import io
import zipfile
from pathlib import Path

import numpy as np
import pygltflib
import pytest
import trimesh
from PIL import Image
from pxr import Gf, Usd, UsdGeom, UsdSkel

from dqskin.cli import main

ROOT = Path(__file__).resolve().parents[1]
SHARED = ROOT.parent / "shared" / "assets"
HUMANOID = ROOT / "assets" / "humanoid.usda"


def asset(*parts: str) -> Path:
    """A file of ../shared/assets: missing is a failure, not a skip."""
    path = SHARED.joinpath(*parts)
    assert path.is_file(), f"{path}: the shared assets are required"
    return path


def cesium_usdz() -> Path:
    return asset("usd-wg", "CesiumMan", "CesiumMan.usdz")


def cesium_glb() -> Path:
    return asset("khronos-gltf", "CesiumMan", "CesiumMan.glb")


def skin(capsys, *argv) -> str:
    code = main(["skin", *map(str, argv)])
    out, err = capsys.readouterr()
    assert code == 0, err
    return out


def refused(capsys, *argv) -> str:
    """The one error line of a refused ``dqskin`` command."""
    code = main(list(map(str, argv)))
    out, err = capsys.readouterr()
    assert code == 2, (out, err)
    lines = err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("dqskin: error: "), err
    assert "Traceback" not in err
    return lines[0]


def world_points(stage: Usd.Stage, path: str, code: float) -> np.ndarray:
    """USD's own world points of a mesh at a time code."""
    mesh = UsdGeom.Mesh(stage.GetPrimAtPath(path))
    pts = np.asarray(mesh.GetPointsAttr().Get(code), np.float64)
    m = np.asarray(mesh.ComputeLocalToWorldTransform(code), np.float64)  # row vectors
    return pts @ m[:3, :3] + m[3, :3]


def glb_positions(path: Path) -> tuple[np.ndarray, list]:
    """POSITION of every primitive (concatenated) and the node matrices, read by pygltflib."""
    g = pygltflib.GLTF2().load(str(path))
    blob = g.binary_blob()
    out = []
    for mesh in g.meshes:
        for prim in mesh.primitives:
            acc = g.accessors[prim.attributes.POSITION]
            view = g.bufferViews[acc.bufferView]
            out.append(np.frombuffer(blob, np.float32, acc.count * 3,
                                     (view.byteOffset or 0) + (acc.byteOffset or 0))
                       .reshape(-1, 3))
    return np.concatenate(out), [n.matrix for n in g.nodes]


def same_points(a: np.ndarray, b: np.ndarray, tol: float) -> None:
    """Every point of ``a`` is one of ``b`` and every one of ``b`` one of ``a``, within ``tol``
    (files split vertices where UV corners differ)."""
    from scipy.spatial import cKDTree
    assert cKDTree(b).query(a)[0].max() <= tol
    assert cKDTree(a).query(b)[0].max() <= tol


# -- 1. one space rule ----------------------------------------------------------------------------

def test_frames_and_npz_are_world_points_a_usd_cache_shows(tmp_path, capsys):
    """CesiumMan.usdz has a Y-up correction above its mesh: .npz, .glb and .obj frames hold the
    points of the USD cache of the same run through USD's local-to-world, and UsdSkel's own
    skinning (LBS) of the source, placed by USD, is the same motion."""
    src = cesium_usdz()
    for out in ("c.usdc", "c.npz", "g_{:02d}.glb", "o_{:02d}.obj"):
        skin(capsys, src, "--out", tmp_path / out, "--frames", "10:11", "--method", "lbs")
    cache = Usd.Stage.Open(str(tmp_path / "c.usdc"))
    ref = Usd.Stage.Open(str(src))
    ref.SetEditTarget(ref.GetSessionLayer())
    assert UsdSkel.BakeSkinning(ref.Traverse(), Gf.Interval(10, 11))
    with np.load(tmp_path / "c.npz") as z:
        (name,) = [str(n) for n in z["names"]]
        assert str(z["space"]) == "world" and str(z["up_axis"]) == "Y"
        assert float(z["meters_per_unit"]) == 1.0 and float(z["fps"]) == 24.0
        np.testing.assert_array_equal(z["frames"], [10.0, 11.0])
        for k, code in enumerate((10.0, 11.0)):
            want = world_points(cache, name, code)
            np.testing.assert_allclose(z["points_0"][k], want, atol=1e-5)
            usd = world_points(ref, name, code)
            np.testing.assert_allclose(z["points_0"][k], usd, atol=1e-4 * np.abs(usd).max())
            # height along +Y: the character stands up (lying on its back it would be ~0.4)
            assert np.ptp(z["points_0"][k][:, 1]) > 1.3
    pos, matrices = glb_positions(tmp_path / "g_10.glb")
    np.testing.assert_allclose(pos, world_points(cache, name, 10.0), atol=1e-5)
    assert all(m is None for m in matrices)  # Y-up metres: glTF's own space
    obj = trimesh.load(tmp_path / "o_11.obj", process=False, force="mesh")
    assert (tmp_path / "o_11.obj").read_text().startswith("# dqskin: world space, +Y up, 1 m")
    same_points(obj.vertices, world_points(cache, name, 11.0), 1e-5)


def test_glb_frames_are_in_gltf_space_and_local_is_asked_for(tmp_path, capsys):
    """The humanoid is in centimetres (metersPerUnit 0.01) under a placement: .glb frames hold
    its world points under a node scaling them to metres, which is what a glTF viewer (trimesh)
    shows; ``--space local`` writes the prims' own points."""
    src = tmp_path / "placed.usda"
    src.write_text(f'#usda 1.0\n(\n    metersPerUnit = 0.01\n    upAxis = "Z"\n)\n'
                   f'def "Placed" (prepend references = @{HUMANOID}@)\n{{\n'
                   '    double3 xformOp:translate = (100, 0, -5)\n'
                   '    uniform token[] xformOpOrder = ["xformOp:translate"]\n}\n')
    skin(capsys, src, "--out", tmp_path / "w_{:02d}.glb", "--frames", "3", "--no-normals")
    skin(capsys, src, "--out", tmp_path / "c.usda", "--frames", "3", "--no-normals",
         "--no-velocities")
    skin(capsys, src, "--out", tmp_path / "l.npz", "--frames", "3", "--space", "local")
    cache = Usd.Stage.Open(str(tmp_path / "c.usda"))
    names = [str(p.GetPath()) for p in cache.Traverse() if p.IsA(UsdGeom.Mesh)]
    world = np.concatenate([world_points(cache, n, 3.0) for n in names])
    pos, matrices = glb_positions(tmp_path / "w_03.glb")
    same_points(pos, world, 1e-4)  # (vertices split where UV corners differ)
    # metres and +Y up: (x, y, z) → 0.01 (x, z, -y), glTF's column-major matrix, on the node of
    # each mesh
    want = np.array([[1, 0, 0, 0], [0, 0, -1, 0], [0, 1, 0, 0], [0, 0, 0, 100]]) * 0.01
    assert len(matrices) == len(names)
    for matrix in matrices:
        np.testing.assert_allclose(np.reshape(matrix, (4, 4)), want, atol=1e-12)
    shown = trimesh.load(tmp_path / "w_03.glb", force="mesh", process=False).vertices
    same_points(shown, 0.01 * world[:, [0, 2, 1]] * [1, 1, -1], 1e-6)
    with np.load(tmp_path / "l.npz") as z:
        assert str(z["space"]) == "local"
        for k, n in enumerate(z["names"]):
            local = np.asarray(UsdGeom.Mesh(cache.GetPrimAtPath(str(n))).GetPointsAttr().Get(3))
            np.testing.assert_allclose(z[f"points_{k}"][0], local, atol=1e-4)


# -- 2. materials travel --------------------------------------------------------------------------

def _gltf_image(path: Path) -> bytes:
    """The base-colour image bytes of a glTF file, read by pygltflib."""
    g = pygltflib.GLTF2().load(str(path))
    tex = g.materials[0].pbrMetallicRoughness.baseColorTexture.index
    view = g.bufferViews[g.images[g.textures[tex].source].bufferView]
    start = view.byteOffset or 0
    return g.binary_blob()[start:start + view.byteLength]


@pytest.mark.parametrize("source", ["glb", "usdz"])
def test_materials_and_textures_travel(tmp_path, capsys, source):
    src = cesium_glb() if source == "glb" else cesium_usdz()
    if source == "glb":
        image = _gltf_image(src)
    else:
        with zipfile.ZipFile(src) as z:
            image = z.read("0/CesiumMan_img0.jpg")
    pixels = np.asarray(Image.open(io.BytesIO(image)).convert("RGB"), np.float64)
    said = skin(capsys, src, "--out", tmp_path / "f_{:02d}.obj", "--frames", "5:6")
    skin(capsys, src, "--out", tmp_path / "g_{:02d}.glb", "--frames", "5")
    assert "materials in" in said
    # .obj: an .mtl beside the frames, naming the source's texture, copied byte for byte
    mtl = (tmp_path / "f.mtl").read_text()
    texture = next(ln.split()[1] for ln in mtl.splitlines() if ln.startswith("map_Kd"))
    assert (tmp_path / texture).read_bytes() == image
    assert "mtllib f.mtl" in (tmp_path / "f_05.obj").read_text()
    mesh = trimesh.load(tmp_path / "f_06.obj", process=False, force="mesh")
    assert mesh.visual.uv is not None and len(mesh.visual.uv) == len(mesh.vertices)
    assert np.asarray(mesh.visual.material.image).shape[:2] == pixels.shape[:2]
    # .glb: the material and its image embedded
    g = pygltflib.GLTF2().load(str(tmp_path / "g_05.glb"))
    (material,) = g.materials
    assert material.pbrMetallicRoughness.baseColorTexture is not None
    (img,) = g.images
    assert img.mimeType == "image/jpeg"
    prim = g.meshes[0].primitives[0]
    assert prim.material == 0 and prim.attributes.TEXCOORD_0 is not None
    data = _gltf_image(tmp_path / "g_05.glb")
    got = np.asarray(Image.open(io.BytesIO(data)).convert("RGB"), np.float64)
    assert got.shape == pixels.shape and np.abs(got - pixels).mean() < 2.0  # (JPEG re-saved)


# -- 3. every input to a USD cache ----------------------------------------------------------------

def test_gltf_to_usd_cache_at_whole_frames(tmp_path, capsys):
    """A glTF input becomes a USD point cache with time codes 1 … 48 at exactly 24 fps; its
    points are UsdSkel's own skinning (LBS) of the rig ``dqskin rig`` writes, at those codes."""
    src = cesium_glb()
    said = skin(capsys, src, "--out", tmp_path / "c.usdc", "--method", "lbs")
    assert "1 mesh × 48 frames" in said
    assert main(["rig", str(src), "--out", str(tmp_path / "rig.usda")]) == 0
    capsys.readouterr()
    cache = Usd.Stage.Open(str(tmp_path / "c.usdc"))
    rig = Usd.Stage.Open(str(tmp_path / "rig.usda"))
    for stage in (cache, rig):
        assert stage.GetTimeCodesPerSecond() == 24.0 == stage.GetFramesPerSecond()
        assert (stage.GetStartTimeCode(), stage.GetEndTimeCode()) == (1.0, 48.0)
    (anim,) = [p for p in rig.Traverse() if p.IsA(UsdSkel.Animation)]
    assert anim.GetAttribute("rotations").GetTimeSamples() == [float(f) for f in range(1, 49)]
    (mesh,) = [p for p in cache.Traverse() if p.IsA(UsdGeom.Mesh)]
    assert not mesh.HasAPI(UsdSkel.BindingAPI)
    attr = UsdGeom.Mesh(mesh).GetPointsAttr()
    assert attr.GetTimeSamples() == [float(f) for f in range(1, 49)]
    assert UsdSkel.BakeSkinning(rig.Traverse(), Gf.Interval(1, 48))
    (ref,) = [p for p in rig.Traverse() if p.IsA(UsdGeom.Mesh)]
    for code in (1.0, 17.0, 48.0):
        want = world_points(rig, str(ref.GetPath()), code)
        got = world_points(cache, str(mesh.GetPath()), code)
        np.testing.assert_allclose(got, want, atol=1e-4 * np.abs(want).max())
    assert sorted(p.name for p in tmp_path.iterdir()) == ["c.usdc", "rig.usda"]


# -- 4. one time model ----------------------------------------------------------------------------

def test_gltf_frames_are_at_the_frame_rate(tmp_path, capsys):
    """RiggedFigure has two keys 1.25 s apart: every frame at 24 fps is baked (0 … 30), not two;
    CesiumMan's clip ends at frame 48 and a selection past it is refused naming the range."""
    fig = asset("khronos-gltf", "RiggedFigure", "RiggedFigure.glb")
    skin(capsys, fig, "--out", tmp_path / "f.npz")
    with np.load(tmp_path / "f.npz") as z:
        np.testing.assert_array_equal(z["frames"], np.arange(31.0))
        np.testing.assert_array_equal(z["times"], np.arange(31.0) / 24)
        assert len(np.unique(z["points_0"], axis=0)) == 31  # every frame a distinct pose
    skin(capsys, fig, "--out", tmp_path / "g.npz", "--fps", "10")
    with np.load(tmp_path / "g.npz") as z:
        np.testing.assert_array_equal(z["times"], np.arange(13.0) / 10)
    src = cesium_glb()
    line = refused(capsys, "skin", src, "--out", tmp_path / "c.npz", "--frames", "1:60")
    assert "--frames 1:60" in line and "frames 1 .. 48 at 24 fps (0.04167 .. 2 s)" in line
    assert "--hold" in line and not (tmp_path / "c.npz").exists()
    skin(capsys, src, "--out", tmp_path / "c.npz", "--frames", "1:60", "--hold")
    with np.load(tmp_path / "c.npz") as z:
        assert len(z["times"]) == 60
        np.testing.assert_array_equal(z["points_0"][47], z["points_0"][59])  # held
        assert not np.array_equal(z["points_0"][0], z["points_0"][47])
    line = refused(capsys, "skin", HUMANOID, "--out", tmp_path / "h.npz", "--frames", "1e9")
    assert "frames 0 .. 48 at 24 fps (0 .. 2 s)" in line
    assert main(["info", str(src)]) == 0
    assert "frames 1 .. 48 at 24 fps (0.04167 .. 2 s)" in capsys.readouterr().out


def test_frames_text_cannot_crash_or_exhaust(tmp_path, capsys):
    """Issue 30: huge exponents, a million digits and a raised --max-frames are one line naming
    the flag, before anything is allocated."""
    out = tmp_path / "x.npz"
    for text in ("0:1e9999999:1", "1e999999", "0:1:1e-999999999", "9" * 1_000_000,
                 "0:" + "9" * 5000):
        line = refused(capsys, "skin", HUMANOID, "--out", out, "--frames", text)
        assert line.startswith("dqskin: error: --frames ") and len(line) < 400, line[:400]
    line = refused(capsys, "skin", HUMANOID, "--out", out, "--frames", "0:1e11", "--hold",
                   "--max-frames", str(10 ** 12))
    assert "--max-frames" in line and "10,000,000" in line
    line = refused(capsys, "skin", HUMANOID, "--out", out, "--frames", "0:2e6", "--hold",
                   "--max-frames", "3000000")
    assert "--out" in line and "GiB in memory" in line  # 2M frames of the humanoid in one .npz
    assert not out.exists()


# -- 5. --prims --------------------------------------------------------------------------------

def test_prims_select_and_unholdable_prims_are_skipped(tmp_path, capsys):
    """OpenUSD's dqs.usda holds a BasisCurves prim: .obj frames skip it with one line; --prims
    chooses meshes; a USD cache deactivates the prims left out."""
    src = asset("openusd", "pxr", "usd", "usdSkel", "testenv", "testUsdSkelBakeSkinning",
                "dqs.usda")
    said = skin(capsys, src, "--out", tmp_path / "a_{}.obj", "--frames", "2")
    assert said.splitlines()[0] == "skipped /Root/Curves (no faces; .obj files hold triangle " \
                                   "meshes)"
    said = skin(capsys, src, "--out", tmp_path / "b_{}.obj", "--frames", "2",
                "--prims=!/Root/Curves,-/Root/MeshWithNormals")
    assert "skipped" not in said and "2 meshes × 1 frame" in said
    skin(capsys, src, "--out", tmp_path / "c.npz", "--frames", "2", "--prims", "/Root/Mesh*")
    with np.load(tmp_path / "c.npz") as z:
        assert sorted(map(str, z["names"])) == ["/Root/Mesh", "/Root/MeshWithFaceVaryingNormals",
                                                "/Root/MeshWithNormals"]
    line = refused(capsys, "skin", src, "--out", tmp_path / "d.npz", "--prims", "/Nope")
    assert "--prims /Nope" in line and "matches no mesh" in line
    skin(capsys, src, "--out", tmp_path / "all.usda", "--frames", "2:3")
    skin(capsys, src, "--out", tmp_path / "one.usda", "--frames", "2:3", "--prims", "/Root/Mesh")
    full, one = (Usd.Stage.Open(str(tmp_path / n)) for n in ("all.usda", "one.usda"))
    assert not one.GetPrimAtPath("/Root/MeshWithNormals").IsActive()
    assert one.GetPrimAtPath("/Root/Mesh").IsActive()
    for code in (2.0, 3.0):
        np.testing.assert_array_equal(world_points(one, "/Root/Mesh", code),
                                      world_points(full, "/Root/Mesh", code))


def test_compare_frames_are_frames_too(tmp_path, capsys):
    """``compare --frames`` counts frames at the asset's rate as ``skin`` does: frame 24 of a
    glTF clip is its time 1 s; past the clip is refused naming the range."""
    import json
    src = cesium_glb()
    args = ["compare", str(src), "--out", str(tmp_path / "r"), "--methods", "lbs,dqs",
            "--views", "front", "--width", "24", "--supersample", "1", "--viewer-frames", "0",
            "--no-sweeps", "--quiet"]
    assert main([*args, "--frames", "24"]) == 0, capsys.readouterr().err
    capsys.readouterr()
    assert json.loads((tmp_path / "r" / "metrics.json").read_text())["frames"] == [1.0]
    line = refused(capsys, *args, "--frames", "100", "--force")
    assert "frames 1 .. 48 at 24 fps" in line
