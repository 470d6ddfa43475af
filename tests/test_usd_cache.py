"""dqskin.usd_cache: point caches against Pixar's baked baselines, exact round trips, safety."""

import hashlib
import os
from pathlib import Path

import numpy as np
import pytest
from pxr import Sdf, Usd, UsdGeom, UsdShade, UsdSkel, Vt

from dqskin.options import SkinOptions
from dqskin.readers.usd import load_usd
from dqskin.writers.usd_cache import UsdCacheWriter, write_usd_cache

BAKE = "openusd/pxr/usd/usdSkel/testenv/testUsdSkelBakeSkinning"
RIGID = ["/Root/Cube", "/Root/Cylinder", "/Root/Sphere"]


def digest(path):
    return hashlib.sha256(open(path, "rb").read()).hexdigest()


def assert_unskinned(stage):
    """No SkelRoot, no SkelBindingAPI and no skel property: UsdSkel skins nothing."""
    for prim in stage.Traverse(Usd.TraverseInstanceProxies()):
        assert not prim.IsA(UsdSkel.Root), prim.GetPath()
        assert not prim.HasAPI(UsdSkel.BindingAPI), prim.GetPath()
        skel_props = [p.GetName() for p in prim.GetAuthoredProperties()
                      if p.GetName().startswith(("skel:", "primvars:skel:"))]
        assert not skel_props, (prim.GetPath(), skel_props)


def random_frames(scene, times, seed=0):
    rng = np.random.default_rng(seed)
    F = len(times)
    points = {m.name: rng.normal(size=(F,) + m.points.shape).astype(np.float32)
              for m in scene.meshes}
    normals = {m.name: rng.normal(size=(F,) + m.normals.shape).astype(np.float32)
               for m in scene.meshes if m.normals is not None}
    velocities = {m.name: rng.normal(size=(F,) + m.points.shape).astype(np.float32)
                  for m in scene.meshes}
    return points, normals, velocities


@pytest.mark.parametrize("method", ["lbs", "dqs"])
def test_cache_matches_pixar_baseline(shared_assets, tmp_path, method, device):
    """Points, normals, extent and rigid xformOp:transform of every frame vs ``*.baked.usda``."""
    src = shared_assets / BAKE / f"{method}.usda"
    before = digest(src)
    scene = load_usd(src)
    skinned = scene.skin(device=device, normals=True)
    points, normals = skinned.points, skinned.normals
    out = write_usd_cache(scene, tmp_path / "cache.usdc", scene.times, points, normals,
                          options=SkinOptions(device=device))
    assert digest(src) == before
    stage = Usd.Stage.Open(out)
    base = Usd.Stage.Open(str(shared_assets / BAKE / "baseline" / f"{method}.baked.usda"))
    assert_unskinned(stage)
    for name in list(points) + RIGID:
        prim, ref_prim = stage.GetPrimAtPath(name), base.GetPrimAtPath(name)
        attrs = (["xformOp:transform"] if name in RIGID else
                 ["points", "extent"] + (["normals"] if name in normals else []))
        for attr in attrs:
            for t in scene.times:
                ours = np.array(prim.GetAttribute(attr).Get(t), np.float64)
                ref = np.array(ref_prim.GetAttribute(attr).Get(t), np.float64)
                err = np.abs(ours - ref).max() / max(np.abs(ref).max(), 1.0)
                assert err < 1e-5, f"{name}.{attr} at {t}: {err:.2e}"
        if name in RIGID:
            assert list(UsdGeom.Xformable(prim).GetXformOpOrderAttr().Get()) == [
                "xformOp:transform"]
    # the whole stage still composes what the baseline shows: same world-space bounds
    bbox = UsdGeom.BBoxCache(Usd.TimeCode(20), ["default", "render"])
    ref_box = UsdGeom.BBoxCache(Usd.TimeCode(20), ["default", "render"])
    ours = bbox.ComputeWorldBound(stage.GetPrimAtPath("/Root")).ComputeAlignedRange()
    ref = ref_box.ComputeWorldBound(base.GetPrimAtPath("/Root")).ComputeAlignedRange()
    np.testing.assert_allclose([ours.GetMin(), ours.GetMax()], [ref.GetMin(), ref.GetMax()],
                               atol=1e-5)


@pytest.mark.parametrize("ext", [".usda", ".usdc", ".usd"])
def test_round_trip_is_exact(shared_assets, tmp_path, ext, device):
    src = shared_assets / BAKE / "lbs.usda"
    before = digest(src)
    scene = load_usd(src)
    times = np.array([2.0, 3.5, 7.0])
    points, normals, velocities = random_frames(scene, times)
    out = write_usd_cache(scene, tmp_path / f"cache{ext}", times, points, normals,
                          velocities=velocities, options=SkinOptions(device=device))
    assert digest(src) == before
    assert os.listdir(tmp_path) == [f"cache{ext}"]  # no temporary file left behind
    magic = open(out, "rb").read(8)
    assert magic == (b"#usda 1." if ext == ".usda" else b"PXR-USDC")
    layer = Sdf.Layer.FindOrOpen(out)
    assert (layer.timeCodesPerSecond, layer.startTimeCode, layer.endTimeCode) == (24, 2, 7)
    assert layer.pseudoRoot.GetInfo("upAxis") == "Y"
    stage, source = Usd.Stage.Open(out), Usd.Stage.Open(str(src))
    assert UsdGeom.GetStageMetersPerUnit(stage) == scene.meters_per_unit
    assert_unskinned(stage)
    for name, p in points.items():
        prim = UsdGeom.PointBased(stage.GetPrimAtPath(name))
        assert prim.GetPointsAttr().GetTimeSamples() == times.tolist()
        for f, t in enumerate(times):
            np.testing.assert_array_equal(prim.GetPointsAttr().Get(t), p[f])
            np.testing.assert_array_equal(prim.GetVelocitiesAttr().Get(t), velocities[name][f])
            np.testing.assert_array_equal(prim.GetExtentAttr().Get(t),
                                          [p[f].min(axis=0), p[f].max(axis=0)])
            if name in normals:
                np.testing.assert_array_equal(prim.GetNormalsAttr().Get(t), normals[name][f])
        if name in normals:
            assert prim.GetNormalsInterpolation() == UsdGeom.PointBased(
                source.GetPrimAtPath(name)).GetNormalsInterpolation()
    mesh = UsdGeom.Mesh(stage.GetPrimAtPath("/Root/MeshWithNormals"))
    original = UsdGeom.Mesh(source.GetPrimAtPath("/Root/MeshWithNormals"))
    assert mesh.GetFaceVertexIndicesAttr().Get() == original.GetFaceVertexIndicesAttr().Get()


def test_instanced_characters_are_de_instanced(shared_assets, tmp_path, device):
    """Two instances of the baked asset: each instance's prims get their own samples."""
    world = tmp_path / "world.usda"
    asset = (shared_assets / BAKE / "dqs.usda").as_posix()
    world.write_text(f"""#usda 1.0
(
    startTimeCode = 1
    endTimeCode = 30
    timeCodesPerSecond = 24
)
def Xform "World"
{{
    def "A" (instanceable = true
             references = @{asset}@</Root>) {{
        double3 xformOp:translate = (3, 0, 0)
        uniform token[] xformOpOrder = ["xformOp:translate"]
    }}
    def "B" (instanceable = true
             references = @{asset}@</Root>) {{
        double3 xformOp:translate = (-3, 0, 0)
        uniform token[] xformOpOrder = ["xformOp:translate"]
    }}
}}
""")
    scene = load_usd(world)
    assert len(scene.meshes) == 8 and len(scene.skeletons) == 2
    skinned = scene.skin([1.0, 15.0], device=device, normals=True)
    points, normals = skinned.points, skinned.normals
    out = write_usd_cache(scene, tmp_path / "cache.usda", [1.0, 15.0], points, normals,
                          options=SkinOptions(device=device))
    stage = Usd.Stage.Open(out)
    base = Usd.Stage.Open(str(shared_assets / BAKE / "baseline" / "dqs.baked.usda"))
    assert_unskinned(stage)
    for inst in ("A", "B"):
        assert not stage.GetPrimAtPath(f"/World/{inst}").IsInstance()
        for name, attr in (("Mesh", "points"), ("MeshWithNormals", "normals"),
                           ("Cube", "xformOp:transform")):
            ours = stage.GetPrimAtPath(f"/World/{inst}/{name}").GetAttribute(attr).Get(15.0)
            ref = base.GetPrimAtPath(f"/Root/{name}").GetAttribute(attr).Get(15.0)
            np.testing.assert_allclose(np.array(ours), np.array(ref), atol=1e-5)


def test_refusals(shared_assets, tmp_path):
    src = shared_assets / BAKE / "lbs.usda"
    copy = tmp_path / "rig.usda"
    copy.write_bytes(src.read_bytes())
    top = tmp_path / "top.usda"
    top.write_text('#usda 1.0\n(\n    subLayers = [@./rig.usda@]\n)\n')
    scene = load_usd(top)
    points, _, _ = random_frames(scene, [1.0])
    before = {p: digest(p) for p in (copy, top)}
    for target in (top, copy):
        with pytest.raises(ValueError, match="refusing to overwrite an input"):
            write_usd_cache(scene, target, [1.0], points)
    assert {p: digest(p) for p in (copy, top)} == before
    with pytest.raises(ValueError, match="cannot write extension '.usdz'"):
        write_usd_cache(scene, tmp_path / "out.usdz", [1.0], points)
    with pytest.raises(ValueError, match=r"points\['/Root/Mesh'\]: expected shape \(2, 40, 3\)"):
        write_usd_cache(scene, tmp_path / "out.usda", [1.0, 2.0], points)
    with pytest.raises(ValueError, match="points: no mesh '/Root/Nope'"):
        write_usd_cache(scene, tmp_path / "out.usda", [1.0], {"/Root/Nope": points["/Root/Mesh"]})
    bad = dict(points)
    bad["/Root/Mesh"] = np.full_like(points["/Root/Mesh"], np.nan)
    with pytest.raises(ValueError, match="NaN"):
        write_usd_cache(scene, tmp_path / "out.usda", [1.0], bad)
    with pytest.raises(ValueError, match=r"normals\['/Root/Mesh'\]: the mesh has no rest normals"):
        write_usd_cache(scene, tmp_path / "out.usda", [1.0], points,
                        {"/Root/Mesh": points["/Root/Mesh"]})
    assert sorted(os.listdir(tmp_path)) == ["rig.usda", "top.usda"]
    nested = tmp_path / "new" / "folder" / "out.usda"  # made, as for every other output
    write_usd_cache(scene, nested, [1.0], points)
    assert nested.is_file()


def test_overwrites_previous_output_atomically(shared_assets, tmp_path, device):
    scene = load_usd(shared_assets / BAKE / "lbs.usda")
    out = tmp_path / "cache.usdc"
    for seed in (1, 2):
        points, _, _ = random_frames(scene, [4.0], seed)
        write_usd_cache(scene, out, [4.0], points, options=SkinOptions(device=device))
        fresh = Usd.Stage.Open(Sdf.Layer.OpenAsAnonymous(str(out)))  # read from disk
        got = fresh.GetPrimAtPath("/Root/Mesh").GetAttribute("points").Get(4)
        np.testing.assert_array_equal(got, points["/Root/Mesh"][0])
    assert os.listdir(tmp_path) == ["cache.usdc"]


def test_indexed_primvar_normals_are_flattened(shared_assets, tmp_path, device):
    """``primvars:normals`` (indexed) beats ``normals``; the cache writes flat values there."""
    top = Sdf.Layer.CreateNew(str(tmp_path / "top.usda"))
    top.subLayerPaths.append(str(shared_assets / BAKE / "lbs.usda"))
    stage = Usd.Stage.Open(top)
    prim = stage.GetPrimAtPath("/Root/MeshWithNormals")
    pv = UsdGeom.PrimvarsAPI(prim).CreatePrimvar(
        "normals", Sdf.ValueTypeNames.Normal3fArray, UsdGeom.Tokens.vertex)
    unique = np.float32([[1, 0, 0], [0, 1, 0], [0, 0, 1]])
    pv.Set(Vt.Vec3fArray.FromNumpy(unique))
    pv.SetIndices(Vt.IntArray.FromNumpy((np.arange(12) % 3).astype(np.int32)))
    top.Save()
    scene = load_usd(top.realPath)
    mesh = scene.mesh("/Root/MeshWithNormals")
    np.testing.assert_array_equal(mesh.normals, unique[np.arange(12) % 3])
    skinned = scene.skin([5.0], device=device, normals=True)
    points, normals = skinned.points, skinned.normals
    out = write_usd_cache(scene, tmp_path / "cache.usda", [5.0], points, normals,
                          options=SkinOptions(device=device))
    cache = Usd.Stage.Open(out)
    written = UsdGeom.PrimvarsAPI(cache.GetPrimAtPath(mesh.name)).GetPrimvar("normals")
    assert not written.IsIndexed()
    assert written.GetInterpolation() == UsdGeom.Tokens.vertex
    np.testing.assert_array_equal(written.Get(5.0), normals[mesh.name][0])
    assert np.abs(normals[mesh.name][0] - mesh.normals).max() > 0.1  # really skinned


def test_usdz_source_keeps_uvs_materials_and_topology(shared_assets, tmp_path, device):
    src = shared_assets / "usd-wg/CesiumMan/CesiumMan.usdz"
    scene = load_usd(src)
    points = scene.skin([1.0, 24.0], device=device).points
    out = write_usd_cache(scene, tmp_path / "cesium.usdc", [1.0, 24.0], points,
                          options=SkinOptions(device=device))
    source, cache = Usd.Stage.Open(str(src)), Usd.Stage.Open(out)
    assert_unskinned(cache)
    (name,) = points
    a, b = source.GetPrimAtPath(name), cache.GetPrimAtPath(name)
    for attr in ("faceVertexCounts", "faceVertexIndices", "primvars:st"):
        np.testing.assert_array_equal(b.GetAttribute(attr).Get(), a.GetAttribute(attr).Get())
    material = UsdShade.MaterialBindingAPI(b).ComputeBoundMaterial()[0]
    assert material and material.GetPath() == UsdShade.MaterialBindingAPI(
        a).ComputeBoundMaterial()[0].GetPath()
    np.testing.assert_array_equal(b.GetAttribute("points").Get(24.0), points[name][1])


def test_exclusive_writer_and_temporary_file(shared_assets, tmp_path):
    """overwrite=False: a cache finished by someone else meanwhile is kept, ours dropped; the
    writer's temporary file exists while it writes and never after."""
    scene = load_usd(shared_assets / BAKE / "lbs.usda")
    out = tmp_path / "cache.usdc"
    points, _, _ = random_frames(scene, [4.0])
    with pytest.raises(FileExistsError, match="cache.usdc: exists"):
        with UsdCacheWriter(scene, out, overwrite=False) as writer:
            assert [p.name.startswith(".cache.") for p in tmp_path.iterdir()] == [True]
            writer.write([4.0], points)
            out.write_bytes(b"finished by another run")
    assert os.listdir(tmp_path) == ["cache.usdc"] and out.read_bytes().startswith(b"finished")
    with pytest.raises(ValueError, match="NaN"):
        with UsdCacheWriter(scene, tmp_path / "other.usdc") as writer:
            writer.write([4.0], {k: np.full_like(v, np.nan) for k, v in points.items()})
    assert os.listdir(tmp_path) == ["cache.usdc"]
    with pytest.raises(NotADirectoryError, match="is not a directory"):
        write_usd_cache(scene, out / "x.usdc", [4.0], points)


@pytest.mark.filterwarnings("ignore:overflow encountered in cast:RuntimeWarning")  # 1e39 → inf
def test_pipelined_chunks_are_checked_once_by_the_check(shared_assets, tmp_path):
    """write_chunks with a check that finds non-finite values (``checked``): an infinite value of
    a later chunk is refused by that check (its message names the time), which the values then
    rely on; without a check, or with one that checks nothing, the values are checked all the
    same, and float64 values beyond float32 too; nothing is written in any case."""
    from dqskin.scene import SkinnedFrames
    from dqskin.validation import check_skinned

    scene = load_usd(shared_assets / BAKE / "lbs.usda")
    chunks = []
    for k, t in enumerate((1.0, 2.0, 3.0)):
        p, n, v = random_frames(scene, [t], seed=k)
        chunks.append(SkinnedFrames(np.array([t]), p, n, v))
    name = scene.meshes[0].name
    chunks[2].velocities[name][0, 5, 1] = np.inf
    late = r"velocities\[.*NaN or infinite"
    for check, checked, want in (
            (lambda r: check_skinned("SRC", r), True,
             "SRC: .*skinned velocities are NaN or infinite at time 3"),
            (None, True, late), (lambda r: None, False, late)):
        with pytest.raises(ValueError, match=want):
            with UsdCacheWriter(scene, tmp_path / "cache.usdc") as writer:
                writer.write_chunks(iter(chunks), check, checked)
        assert os.listdir(tmp_path) == []
    chunks[2].velocities[name] = chunks[2].velocities[name].astype(np.float64)
    chunks[2].velocities[name][0, 5, 1] = 1e39  # finite, but not as float32
    with pytest.raises(ValueError, match=late):
        with UsdCacheWriter(scene, tmp_path / "cache.usdc") as writer:
            writer.write_chunks(iter(chunks), lambda r: check_skinned("SRC", r), True)
    assert os.listdir(tmp_path) == []


def test_check_skinned_through_a_shared_array():
    """check_skinned on meshes that are column views of one (F, V, 3) array (a batch's result,
    checked through it): a NaN or an infinity is named by its mesh and time wherever it is;
    one in columns no mesh holds (padding) is not the meshes' and passes; so do arrays of
    their own and a view of a small part of a large array."""
    from dqskin.scene import SkinnedFrames
    from dqskin.validation import check_skinned

    times = np.array([1.0, 2.0, 3.0])
    for bad, where, want in (((1, 7, 2), np.nan, "b.*points.*time 2"),
                             ((2, 0, 0), -np.inf, "a.*points.*time 3"),
                             ((0, 9, 1), np.inf, "b.*points.*time 1"),
                             ((1, 12, 0), np.nan, None)):  # column 12: no mesh's
        base = np.ones((3, 13, 3), np.float32)
        base[bad] = where
        result = SkinnedFrames(times, {"a": base[:, :4], "b": base[:, 4:12]})
        if want is None:
            check_skinned("SRC", result)
        else:
            with pytest.raises(ValueError, match=f"SRC: {want}"):
                check_skinned("SRC", result)
    big = np.ones((3, 100, 3), np.float32)
    big[0, 50, 0] = np.nan  # outside the one view: not its value
    check_skinned("SRC", SkinnedFrames(times, {"a": big[:, :10]}, {"a": np.ones((3, 4, 3))}))
    own = np.ones((3, 4, 3), np.float32)
    own[2, 1, 1] = np.nan
    with pytest.raises(ValueError, match="SRC: a: skinned normals .* time 3"):
        check_skinned("SRC", SkinnedFrames(times, {"a": big[:, :10]}, {"a": own}))


def test_vt_arrays_hold_each_frame_exactly(monkeypatch):
    """vec3f_arrays (copies into Vt's own storage through the buffer protocol; FromNumpy for
    small arrays): each array equals its frame, for small and large, strided and float64 input,
    and the arrays are independent of the input and of each other; another module typing
    ctypes.pythonapi's buffer functions its own way changes nothing."""
    import ctypes

    from dqskin.writers.usd_cache import SMALL_ARRAY, vec3f_arrays
    shared = ctypes.pythonapi.PyObject_GetBuffer
    monkeypatch.setattr(shared, "argtypes", [ctypes.py_object, ctypes.POINTER(ctypes.c_char),
                                             ctypes.c_int])
    rng = np.random.default_rng(4)
    for n in (0, 1, SMALL_ARRAY, SMALL_ARRAY + 1, 580):
        frames = rng.normal(size=(5, n, 3))
        for given in (frames.astype(np.float32), frames, frames.astype(np.float32)[::2]):
            arrays = vec3f_arrays(given)
            want = np.asarray(given, np.float32).copy()
            given[...] = 7  # the arrays are copies
            assert len(arrays) == len(want)
            for a, w in zip(arrays, want):
                assert isinstance(a, Vt.Vec3fArray) and len(a) == n
                np.testing.assert_array_equal(np.asarray(a).reshape(n, 3), w)


def test_vt_arrays_from_several_threads_at_once():
    """vec3f_arrays on four threads at once (a bake's values thread beside other writers): each
    call's arrays hold exactly its own frames."""
    from concurrent.futures import ThreadPoolExecutor

    from dqskin.writers.usd_cache import vec3f_arrays
    rng = np.random.default_rng(9)
    inputs = [rng.normal(size=(200, 700, 3)).astype(np.float32) for _ in range(8)]
    with ThreadPoolExecutor(4) as pool:
        results = list(pool.map(vec3f_arrays, inputs))
    for frames, arrays in zip(inputs, results):
        got = np.stack([np.asarray(a).reshape(700, 3) for a in arrays])
        np.testing.assert_array_equal(got, frames)


def test_crate_cache_streams_what_the_sdf_layer_holds(shared_assets, tmp_path):
    """A .usdc cache (the source's copy exported once, the samples streamed after it) reads as
    the .usda cache written through Sdf: every spec and value, the time range included, with
    chunks written out of order and a time written twice (the later wins in both); a value the
    first chunk did not hold is refused for .usdc only (its spec is in the exported copy)."""
    scene = load_usd(shared_assets / BAKE / "lbs.usda")
    writes = []
    for k, t in enumerate(([3.0, 4.0], [1.0, 2.0], [4.0])):
        writes.append((t,) + random_frames(scene, t, seed=k))
    layers = {}
    for ext in (".usda", ".usdc", ".usd"):
        with UsdCacheWriter(scene, tmp_path / f"cache{ext}") as writer:
            for t, p, n, v in writes:
                writer.write(t, p, n, v)
        layers[ext] = Sdf.Layer.FindOrOpen(str(tmp_path / f"cache{ext}"))
    assert open(tmp_path / "cache.usdc", "rb").read(8) == b"PXR-USDC"
    assert open(tmp_path / "cache.usd", "rb").read(8) == b"PXR-USDC"
    text = layers[".usda"].ExportToString()
    assert "4: [" in text and layers[".usda"].endTimeCode == 4.0
    assert layers[".usdc"].ExportToString() == text
    assert layers[".usd"].ExportToString() == text
    t, p, n, v = writes[0]
    with pytest.raises(ValueError, match="late.usdc: .*: normals was not in the first chunk"):
        with UsdCacheWriter(scene, tmp_path / "late.usdc") as writer:
            writer.write(t, p)
            writer.write([5.0], *random_frames(scene, [5.0])[:2])
    assert not (tmp_path / "late.usdc").exists()
    assert sorted(os.listdir(tmp_path)) == ["cache.usd", "cache.usda", "cache.usdc"]
    odd = tmp_path / "odd" / ".base.usdc"  # the name of nothing the writer uses itself
    write_usd_cache(scene, odd, t, p, n, velocities=v)
    assert sorted(os.listdir(odd.parent)) == [".base.usdc"]
    assert Sdf.Layer.FindOrOpen(str(odd)).ListTimeSamplesForPath(
        f"{scene.meshes[0].name}.points") == t


def test_a_single_layer_bake_skins_chunks_of_bounded_bytes(tmp_path, monkeypatch):
    """A single-layer USD bake streams its chunks to the file, so the chunk is what it holds:
    256 frames, or fewer when they would exceed ``usd_cache.CHUNK_BYTES`` of samples (at least
    ``CHUNK_MIN_FRAMES``); a given ``chunk`` is used as given."""
    from dqskin import bake
    from dqskin.scene import Scene
    from dqskin.writers import usd_cache

    sizes = []
    real = Scene.skin_chunks

    def spy(self, times, chunk, **kw):
        sizes.append(chunk)
        return real(self, times, chunk, **kw)

    monkeypatch.setattr(Scene, "skin_chunks", spy)
    src = Path(__file__).resolve().parents[1] / "assets" / "humanoid.usda"
    bake(src, tmp_path / "a.usdc", clips=False)
    monkeypatch.setattr(usd_cache, "CHUNK_BYTES", 1)
    bake(src, tmp_path / "b.usdc", clips=False)
    bake(src, tmp_path / "c.usdc", clips=False, chunk=5)
    assert sizes == [256, usd_cache.CHUNK_MIN_FRAMES, 5]


def test_a_usd_bake_imports_only_what_it_uses(tmp_path):
    """Loading a USD character and baking a points-only single-layer cache without a progress bar
    imports no glTF reader, progress bar, Dask module or ``numpy.ma`` (each import is milliseconds
    of every bake's start: 40 ms together)."""
    import subprocess
    import sys

    src = Path(__file__).resolve().parents[1] / "assets" / "humanoid.usda"
    code = (
        "import sys\n"
        "from dqskin import bake, load\n"
        f"bake(load({str(src)!r}), {str(tmp_path / 'a.usdc')!r}, clips=False, method='lbs',\n"
        "     normals=False, velocities=False)\n"
        "print('imported:', *sorted(m for m in sys.modules if m.split('.')[0] in "
        "('pygltflib', 'tqdm', 'dask', 'distributed') or m in ('numpy.ma', 'dqskin.distributed')))"
        "\n")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.splitlines()[-1] == "imported:", out.stdout


def test_a_base_usd_core_writes_in_another_crate_version_falls_back_to_sdf(tmp_path, monkeypatch):
    """When usd-core's copy of the source is a crate version the writer cannot extend, the cache
    is written through Sdf and reads the same; any other error of the writer is raised."""
    from dqskin import bake
    from dqskin.files import crate

    src = Path(__file__).resolve().parents[1] / "assets" / "humanoid.usda"
    bake(src, tmp_path / "crate.usdc", clips=False)

    def unsupported(*args, **kwargs):
        raise crate.UnsupportedCrate("crate version (0, 6, 0)")
    monkeypatch.setattr(crate.CrateSamples, "__init__", unsupported)
    bake(src, tmp_path / "sdf.usdc", clips=False)
    a, b = (Sdf.Layer.FindOrOpen(str(tmp_path / n)) for n in ("crate.usdc", "sdf.usdc"))
    assert a.ExportToString() == b.ExportToString()

    def broken(*args, **kwargs):
        raise ValueError("tokens do not decode")
    monkeypatch.setattr(crate.CrateSamples, "__init__", broken)
    with pytest.raises(ValueError, match="tokens do not decode"):
        bake(src, tmp_path / "broken.usdc", clips=False)
    assert not (tmp_path / "broken.usdc").exists()
