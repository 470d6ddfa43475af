"""dqskin.files.crate: crate files written without Sdf, read back by usd-core (the oracle):
the same layer built with Sdf and exported must read identically, as text and value by value."""

import numpy as np
import pytest
from pxr import Gf, Sdf, Usd, UsdGeom, Vt

from dqskin.files.crate import VALUE_TYPES, CrateSamples
from dqskin.files.direct import nbytes

RNG = np.random.default_rng(7)


def _sdf_layer(tcps, start, end, attrs):
    """The same samples written through Sdf (what the writer replaces)."""
    layer = Sdf.Layer.CreateAnonymous(".usdc")
    layer.timeCodesPerSecond = layer.framesPerSecond = tcps
    layer.startTimeCode, layer.endTimeCode = start, end
    for path, type_name, times, values, info in attrs:
        p = Sdf.Path(path)
        prim = (layer.GetPrimAtPath(p.GetPrimPath())
                or Sdf.CreatePrimInLayer(layer, p.GetPrimPath()))
        spec = (layer.GetAttributeAtPath(p)
                or Sdf.AttributeSpec(prim, p.name, Sdf.ValueTypeNames.Find(type_name)))
        for key, value in info:
            spec.SetInfo(key, value)
        for t, v in zip(times, values):
            if type_name == "matrix4d":
                v = Gf.Matrix4d(v.T.tolist())
            else:
                v = Vt.Vec3fArray.FromNumpy(v)
            layer.SetTimeSample(p, float(t), v)
    return layer


def _samples(n_frames, n_points):
    return RNG.normal(size=(n_frames, n_points, 3)).astype(np.float32) * 10


# Prims with children and properties, siblings at several depths, namespaced and odd-sized
# (padded) arrays, empty arrays, 2-element extents, matrices, an attribute added in blocks.
ATTRS = [
    ("/Root/Body/Mesh.points", "point3f[]", np.arange(1.0, 8.0), _samples(7, 5), ()),
    ("/Root/Body/Mesh.extent", "float3[]", np.arange(1.0, 8.0), _samples(7, 2), ()),
    ("/Root/Body/Mesh.primvars:normals", "normal3f[]", np.arange(1.0, 8.0), _samples(7, 5),
     (("interpolation", "faceVarying"),)),
    ("/Root/Body/Mesh.velocities", "vector3f[]", np.arange(1.0, 8.0), _samples(7, 700), ()),
    ("/Root/Body.xformOp:transform", "matrix4d", np.arange(1.0, 8.0),
     RNG.normal(size=(7, 4, 4)), ()),
    ("/Root/Body/Other.points", "point3f[]", np.array([1.0, 2.5, 4.0]), _samples(3, 0), ()),
    ("/Second.points", "point3f[]", np.array([-2.0, 0.0]), _samples(2, 4), ()),
]


@pytest.fixture(params=["add", "add_many"])
def written(tmp_path, request):
    """The layer of ATTRS, each attribute added alone, or (``add_many``) chunk by chunk: every
    attribute's frames of a chunk in one call, as a bake adds them."""
    path = tmp_path / "samples.usdc"
    crate = CrateSamples(path, 30.0)
    if request.param == "add_many":
        for a, b in ((0, 3), (3, 4), (4, 7)):
            crate.add_many([(attr, type_name, times[a:b], values[a:b], info)
                            for attr, type_name, times, values, info in ATTRS])
        assert crate.close(-2.0, 7.0) == path
        return path
    for attr, type_name, times, values, info in ATTRS:
        if attr.endswith(".velocities"):  # in blocks, the way a bake adds them
            for a, b in ((0, 3), (3, 4), (4, 7)):
                crate.add(attr, type_name, times[a:b], values[a:b], info)
        else:
            crate.add(attr, type_name, times, values, info)
    assert crate.close(-2.0, 7.0) == path
    return path


def test_reads_as_the_same_layer_written_by_sdf(written):
    ours = Sdf.Layer.FindOrOpen(str(written))
    ref = _sdf_layer(30.0, -2.0, 7.0, ATTRS)
    assert ours.ExportToString() == ref.ExportToString()
    for attr, type_name, times, values, _ in ATTRS:
        assert ours.ListTimeSamplesForPath(attr) == list(times)
        for t, v in zip(times, values):
            got = ours.QueryTimeSample(attr, float(t))
            if type_name == "matrix4d":
                np.testing.assert_array_equal(np.array(got), v.T)
            else:
                assert isinstance(got, Vt.Vec3fArray)
                np.testing.assert_array_equal(np.asarray(got).reshape(-1, 3), v)


def test_a_stage_reads_it_and_interpolates_between_samples(written):
    stage = Usd.Stage.Open(str(written))
    assert stage.GetTimeCodesPerSecond() == 30.0
    assert (stage.GetStartTimeCode(), stage.GetEndTimeCode()) == (-2.0, 7.0)
    mesh = stage.GetPrimAtPath("/Root/Body/Mesh")
    assert mesh.GetSpecifier() == Sdf.SpecifierOver
    _, _, times, values, _ = ATTRS[0]
    got = np.asarray(UsdGeom.Mesh(mesh).GetPointsAttr().Get(2.25))
    np.testing.assert_allclose(got, 0.75 * values[1] + 0.25 * values[2], rtol=1e-6, atol=1e-6)
    normals = UsdGeom.PrimvarsAPI(mesh).GetPrimvar("normals")
    assert normals.GetInterpolation() == "faceVarying"


def test_large_arrays_exact(tmp_path):
    """Arrays large enough for the reader to map them in place (≥ 2 KiB), odd and even sizes."""
    path = tmp_path / "big.usdc"
    crate = CrateSamples(path, 24.0)
    data = {n: _samples(4, n) for n in (4097, 10000)}
    for n, v in data.items():
        crate.add(f"/M{n}.points", "point3f[]", np.arange(4.0), v)
    crate.close(0, 3)
    layer = Sdf.Layer.FindOrOpen(str(path))
    for n, v in data.items():
        for f in range(4):
            np.testing.assert_array_equal(
                np.asarray(layer.QueryTimeSample(f"/M{n}.points", float(f))), v[f])


@pytest.mark.parametrize("direct", ["1", "0"])
def test_columns_of_a_larger_array_written_in_place(tmp_path, monkeypatch, direct):
    """A mesh's columns of a batch's frames (each frame's values contiguous, the frames apart),
    a reversed view and a transposed one (neither contiguous within a frame) read back as the
    values given, through the page cache and past it."""
    monkeypatch.setenv("DQSKIN_DIRECT_IO", direct)
    batch = _samples(5, 9000)  # (5, 9000, 3)
    views = {"/Cols.points": batch[:, 1000:6001], "/Rev.points": batch[:, ::-1][:, :700],
             "/T.points": np.ascontiguousarray(batch[:, :300].transpose(0, 2, 1)).transpose(
                 0, 2, 1)}
    path = tmp_path / "views.usdc"
    crate = CrateSamples(path, 24.0)
    for attr, v in views.items():
        crate.add(attr, "point3f[]", np.arange(5.0), v)
    crate.close(0, 4)
    layer = Sdf.Layer.FindOrOpen(str(path))
    for attr, v in views.items():
        for f in range(5):
            np.testing.assert_array_equal(np.asarray(layer.QueryTimeSample(attr, float(f))),
                                          v[f])


@pytest.mark.parametrize("args, match", [
    (("/A.points", "int[]", [0.0], np.zeros((1, 2, 3))), "cannot write type"),
    (("/A", "point3f[]", [0.0], np.zeros((1, 2, 3))), "not an attribute path"),
    (("/A.points", "point3f[]", [0.0, 1.0], np.zeros((1, 2, 3))), "expected 2 frames"),
    (("/A.points", "point3f[]", [0.0], np.zeros((1, 2, 4))), "expected 1 frames"),
    (("/A.points", "point3f[]", [np.nan], np.zeros((1, 2, 3))), "finite"),
    (("/A.xformOp:transform", "matrix4d", [0.0], np.zeros((1, 3, 3))), r"\(4, 4\)"),
    (("/A.xformOp:transform", "matrix4d", [0.0], np.zeros(16)), r"\(4, 4\)"),
    (("A.points", "point3f[]", [0.0], np.zeros((1, 2, 3))), "not an attribute path"),
    (("/A{v=x}B.points", "point3f[]", [0.0], np.zeros((1, 2, 3))), "variant"),
])
def test_bad_samples_are_refused(tmp_path, args, match):
    crate = CrateSamples(tmp_path / "bad.usdc", 24.0)
    with pytest.raises(ValueError, match=match):
        crate.add(*args)
    crate.abort()


def test_samples_in_any_order_and_a_time_added_again_replaces_the_earlier(tmp_path):
    """As ``Sdf.Layer.SetTimeSample``: any order; a later sample at a time replaces it."""
    a, b = _samples(3, 2), _samples(2, 2)
    crate = CrateSamples(tmp_path / "order.usdc", 24.0)
    crate.add("/A.points", "point3f[]", [5.0, 1.0, 3.0], a)
    crate.add("/A.points", "point3f[]", [3.0, 2.0], b)
    with pytest.raises(ValueError, match="added as point3f"):
        crate.add("/A.points", "normal3f[]", [2.0], np.zeros((1, 2, 3)))
    crate.close(1, 5)
    with pytest.raises(ValueError, match="closed"):
        crate.add("/A.points", "point3f[]", [2.0], np.zeros((1, 2, 3)))
    ref = _sdf_layer(24.0, 1.0, 5.0, [("/A.points", "point3f[]", [5.0, 1.0, 3.0], a, ()),
                                      ("/A.points", "point3f[]", [3.0, 2.0], b, ())])
    ours = Sdf.Layer.FindOrOpen(str(tmp_path / "order.usdc"))
    assert ours.ListTimeSamplesForPath("/A.points") == [1.0, 2.0, 3.0, 5.0]
    assert ours.ExportToString() == ref.ExportToString()
    np.testing.assert_array_equal(np.asarray(ours.QueryTimeSample("/A.points", 3.0)), b[0])


def test_every_value_type_is_one_sdf_knows():
    for name in VALUE_TYPES:
        assert Sdf.ValueTypeNames.Find(name), name


@pytest.mark.parametrize("writev", ["short", "missing"])
def test_short_writes_and_no_writev_give_the_same_file(tmp_path, monkeypatch, writev):
    """``os.writev`` may write less than asked (and is absent on some systems): the rest is
    written buffer by buffer, the file byte for byte the same (buffered writes: direct I/O
    off)."""
    import os
    monkeypatch.setenv("DQSKIN_DIRECT_IO", "0")

    def build(path):
        crate = CrateSamples(path, 24.0)
        crate.add("/A/B.points", "point3f[]", np.arange(5.0), _samples(5, 3))
        crate.add("/A.xformOp:transform", "matrix4d", np.arange(5.0), RNG.normal(size=(5, 4, 4)))
        crate.close(0, 4)
        return path.read_bytes()

    state = RNG.bit_generator.state
    expected = build(tmp_path / "plain.usdc")
    RNG.bit_generator.state = state
    if writev == "short":
        monkeypatch.setattr(os, "writev", lambda fd, bufs: os.write(
            fd, memoryview(bufs[0]).cast("B")[:max(1, nbytes(bufs[0]) // 2)]))
    else:
        monkeypatch.delattr(os, "writev")
    assert build(tmp_path / "other.usdc") == expected


def _base_layer():
    """A layer as the single-layer cache's static part: defined prims with types, attributes
    with defaults and metadata, strings, a relationship, a dictionary, an asset path, a
    time-sampled transform of its own, and the baked attributes' specs without samples."""
    layer = Sdf.Layer.CreateAnonymous(".usdc")
    layer.timeCodesPerSecond = layer.framesPerSecond = 30.0
    layer.startTimeCode, layer.endTimeCode = 0.0, 1.0
    layer.documentation = "a base"
    layer.pseudoRoot.SetInfo("upAxis", "Z")
    root = Sdf.PrimSpec(layer, "Root", Sdf.SpecifierDef, "Xform")
    root.customData = {"note": "kept", "n": 3, "nested": {"x": Gf.Vec3d(1, 2, 3)}}
    xf = Sdf.AttributeSpec(root, "xformOp:translate", Sdf.ValueTypeNames.Double3)
    for t in (0.0, 10.0):
        layer.SetTimeSample(xf.path, t, Gf.Vec3d(t, 0, 0))
    order = Sdf.AttributeSpec(root, "xformOpOrder", Sdf.ValueTypeNames.TokenArray,
                              Sdf.VariabilityUniform)
    order.default = Vt.TokenArray(["xformOp:translate"])
    mesh = Sdf.PrimSpec(root, "Mesh", Sdf.SpecifierDef, "Mesh")
    pts = Sdf.AttributeSpec(mesh, "points", Sdf.ValueTypeNames.Point3fArray)
    pts.default = Vt.Vec3fArray.FromNumpy(np.arange(15, dtype=np.float32).reshape(5, 3))
    Sdf.AttributeSpec(mesh, "extent", Sdf.ValueTypeNames.Float3Array)
    acc = Sdf.AttributeSpec(mesh, "accelerations", Sdf.ValueTypeNames.Vector3fArray)
    layer.SetTimeSample(acc.path, 0.0, Vt.Vec3fArray(5))
    nrm = Sdf.AttributeSpec(mesh, "primvars:normals", Sdf.ValueTypeNames.Normal3fArray)
    nrm.SetInfo("interpolation", "vertex")
    Sdf.AttributeSpec(mesh, "faceVertexCounts", Sdf.ValueTypeNames.IntArray).default = \
        Vt.IntArray([3, 3])
    tex = Sdf.AttributeSpec(mesh, "texture", Sdf.ValueTypeNames.Asset)
    tex.default = Sdf.AssetPath("textures/skin.png")
    Sdf.RelationshipSpec(mesh, "material:binding").targetPathList.explicitItems = ["/Root/Mat"]
    Sdf.PrimSpec(root, "Mat", Sdf.SpecifierDef, "Material")
    rigid = Sdf.PrimSpec(root, "Rigid", Sdf.SpecifierDef, "Cube")
    Sdf.AttributeSpec(rigid, "xformOp:transform", Sdf.ValueTypeNames.Matrix4d)
    return layer


BASE_ATTRS = [
    ("/Root/Mesh.points", "point3f[]", np.arange(1.0, 5.0), _samples(4, 5), ()),
    ("/Root/Mesh.extent", "float3[]", np.arange(1.0, 5.0), _samples(4, 2), ()),
    ("/Root/Mesh.primvars:normals", "normal3f[]", np.arange(1.0, 5.0), _samples(4, 5), ()),
    ("/Root/Rigid.xformOp:transform", "matrix4d", np.arange(1.0, 5.0),
     RNG.normal(size=(4, 4, 4)), ()),
]


def test_samples_added_to_a_base_layer_usd_wrote(tmp_path):
    """The base's specs and values are kept (its own time samples, dictionaries, relationships,
    asset paths, defaults), each baked attribute gets its samples and the time range is
    replaced: the file reads exactly as the base layer with the samples set through Sdf."""
    base = tmp_path / "base.usdc"
    assert _base_layer().Export(str(base))
    crate = CrateSamples(tmp_path / "out.usdc", 30.0, base=base)
    for attr, type_name, times, values, info in BASE_ATTRS:
        crate.add(attr, type_name, times[:2], values[:2], info)
    for attr, type_name, times, values, info in BASE_ATTRS:
        crate.add(attr, type_name, times[2:], values[2:], info)
    crate.close(1.0, 4.0)
    ref = _base_layer()
    ref.startTimeCode, ref.endTimeCode = 1.0, 4.0
    for attr, type_name, times, values, _ in BASE_ATTRS:
        for t, v in zip(times, values):
            ref.SetTimeSample(attr, float(t), Gf.Matrix4d(v.T.tolist()) if type_name ==
                              "matrix4d" else Vt.Vec3fArray.FromNumpy(v))
    ours = Sdf.Layer.FindOrOpen(str(tmp_path / "out.usdc"))
    assert ours.ExportToString() == ref.ExportToString()
    stage = Usd.Stage.Open(ours)
    mesh = UsdGeom.Mesh(stage.GetPrimAtPath("/Root/Mesh"))
    np.testing.assert_array_equal(np.asarray(mesh.GetPointsAttr().Get(3.0)), BASE_ATTRS[0][3][2])
    assert stage.GetPrimAtPath("/Root").GetCustomDataByKey("nested:x") == Gf.Vec3d(1, 2, 3)


def test_a_base_needs_the_spec_and_its_type(tmp_path):
    base = tmp_path / "base.usdc"
    _base_layer().Export(str(base))
    crate = CrateSamples(tmp_path / "out.usdc", 30.0, base=base)
    with pytest.raises(ValueError, match="the base layer has no attribute spec"):
        crate.add("/Root/Mesh.velocities", "vector3f[]", [1.0], np.zeros((1, 5, 3)))
    with pytest.raises(ValueError, match="declared matrix4d in the base layer, which "
                                         "normal3f"):
        crate.add("/Root/Rigid.xformOp:transform", "normal3f[]", [1.0], np.zeros((1, 5, 3)))
    with pytest.raises(ValueError, match="has time samples in the base layer already"):
        crate.add("/Root/Mesh.accelerations", "vector3f[]", [1.0], np.zeros((1, 5, 3)))
    crate.abort()
    with pytest.raises(ValueError, match="not a USD crate file"):
        CrateSamples(tmp_path / "x.usdc", 30.0, base=tmp_path / "out.usdc")


def test_lz4_blocks_with_overlapping_matches_and_long_lengths_decode():
    """The LZ4 decoder (for the structural sections usd-core compressed) against hand-made
    blocks: a back-reference longer than its offset repeats the bytes; lengths of 15 and more
    take extension bytes (255 = another byte follows)."""
    from dqskin.files.crate import _lz4_decode, _lz4_literals

    block = bytes([0x00, 0x38]) + b"abc" + bytes([3, 0, 0x50]) + b"defgh"
    assert _lz4_decode(block) == b"abc" + b"abc" * 4 + b"defgh"
    run = bytes([0x00, 0x1F, ord("z"), 1, 0, 255, 2, 0x50]) + b"12345"
    assert _lz4_decode(run) == b"z" * (1 + 15 + 255 + 2 + 4) + b"12345"
    for n in (0, 14, 15, 269, 270, 271, 1000):
        data = bytes(range(256)) * (n // 256 + 1)
        assert _lz4_decode(_lz4_literals(data[:n])) == data[:n]


@pytest.mark.parametrize("direct", ["1", "0"])
def test_a_failed_write_on_the_writer_thread_is_raised_here(tmp_path, monkeypatch, direct):
    """Samples are written on a writer thread: its error (a full disk) comes back from a later
    ``add`` or from ``close``, and ``abort`` still closes the file (direct I/O or not)."""
    import errno
    import os

    def full(*args):
        raise OSError(errno.ENOSPC, "No space left on device")

    from dqskin.files import direct as direct_io
    monkeypatch.setenv("DQSKIN_DIRECT_IO", direct)
    monkeypatch.setattr(direct_io, "STAGE", direct_io.BLOCK)  # direct: each add writes
    crate = CrateSamples(tmp_path / "full.usdc", 24.0)
    monkeypatch.setattr(os, "writev", full)
    monkeypatch.setattr(os, "pwrite", full)
    with pytest.raises(OSError, match="No space left"):
        for k in range(10):
            crate.add("/A.points", "point3f[]", [float(k)], np.zeros((1, 400, 3), np.float32))
        crate.close(0, 9)
    crate.abort()
    assert crate._file is None


def test_a_base_type_stored_as_the_samples_takes_them(tmp_path):
    """A primvar declared ``float3[]`` (or ``vector3f[]``) takes ``normal3f[]`` samples, as
    Sdf's SetTimeSample does: the declared type is kept."""
    layer = Sdf.Layer.CreateAnonymous(".usdc")
    mesh = Sdf.PrimSpec(layer, "Mesh", Sdf.SpecifierDef, "Mesh")
    for name, type_name in (("primvars:normals", Sdf.ValueTypeNames.Float3Array),
                            ("velocities", Sdf.ValueTypeNames.Vector3fArray)):
        Sdf.AttributeSpec(mesh, name, type_name)
    layer.Export(str(tmp_path / "base.usdc"))
    values = _samples(2, 3)
    crate = CrateSamples(tmp_path / "out.usdc", 24.0, base=tmp_path / "base.usdc")
    crate.add("/Mesh.primvars:normals", "normal3f[]", [0.0, 1.0], values)
    crate.add("/Mesh.velocities", "normal3f[]", [0.0, 1.0], values)
    crate.close(0, 1)
    for name, type_name in (("/Mesh.primvars:normals", "float3[]"),
                            ("/Mesh.velocities", "vector3f[]")):
        layer.SetTimeSample(name, 0.0, Vt.Vec3fArray.FromNumpy(values[0]))
        layer.SetTimeSample(name, 1.0, Vt.Vec3fArray.FromNumpy(values[1]))
    layer.startTimeCode, layer.endTimeCode = 0, 1
    ours = Sdf.Layer.FindOrOpen(str(tmp_path / "out.usdc"))
    assert ours.ExportToString() == layer.ExportToString()
    assert ours.GetAttributeAtPath("/Mesh.primvars:normals").typeName == "float3[]"


def test_refused_and_empty_adds_leave_a_valid_layer(tmp_path):
    """An add refused (non-finite times) or of no frames records nothing: close still writes a
    layer with the other attributes."""
    crate = CrateSamples(tmp_path / "x.usdc", 24.0)
    with pytest.raises(ValueError, match="finite"):
        crate.add("/A.points", "point3f[]", [np.inf], np.zeros((1, 2, 3)))
    crate.add("/B.points", "point3f[]", [], np.zeros((0, 2, 3)))
    crate.add("/C.points", "point3f[]", [1.0], np.ones((1, 2, 3)))
    crate.close(1, 1)
    layer = Sdf.Layer.FindOrOpen(str(tmp_path / "x.usdc"))
    assert [p.path for p in layer.rootPrims] == [Sdf.Path("/C")]


def test_deep_hierarchies_need_no_recursion(tmp_path):
    """Prims 1,500 levels deep (past Python's recursion limit), with siblings at every level."""
    deep = "".join(f"/P{k}" for k in range(1500))
    attrs = [(deep + ".points", "point3f[]", [0.0], _samples(1, 2), ()),
             ("/P0/Q.points", "point3f[]", [0.0], _samples(1, 2), ()),
             ("/P0/P1/R.points", "point3f[]", [0.0], _samples(1, 2), ()),
             ("/P0/P1.extent", "float3[]", [0.0], _samples(1, 2), ())]
    crate = CrateSamples(tmp_path / "deep.usdc", 24.0)
    for attr in attrs:
        crate.add(*attr)
    crate.close(0, 0)
    ours = Sdf.Layer.FindOrOpen(str(tmp_path / "deep.usdc"))
    for attr, _, _, values, _ in attrs:
        np.testing.assert_array_equal(np.asarray(ours.QueryTimeSample(attr, 0.0)), values[0])
    assert ours.GetPrimAtPath(deep).specifier == Sdf.SpecifierOver


def test_an_unclosed_writer_closes_its_file_when_dropped(tmp_path):
    import gc
    import os
    crate = CrateSamples(tmp_path / "dropped.usdc", 24.0)
    fds = [crate._file._fd]
    for fd in fds:
        assert os.readlink(f"/proc/self/fd/{fd}") == str(tmp_path / "dropped.usdc")
    del crate
    gc.collect()
    for fd in fds:
        assert not os.path.exists(f"/proc/self/fd/{fd}") or \
            os.readlink(f"/proc/self/fd/{fd}") != str(tmp_path / "dropped.usdc")


def test_integer_codes_of_every_width_decode():
    """Sdf_IntegerCompression's four codes (the common delta, 8, 16 and 32 bits), by hand:
    deltas from the previous value, wrapping at 32 bits."""
    import struct

    from dqskin.files.crate import _compressed_ints, _decode_ints, _lz4_literals

    deltas = [7, -3, 300, -70000, 7, 2**31 - 1, 5]  # common 7; 8, 16, 32, common, 32, 8 bits
    codes = [0, 1, 2, 3, 0, 3, 1]
    packed = bytes([codes[0] | codes[1] << 2 | codes[2] << 4 | codes[3] << 6,
                    codes[4] | codes[5] << 2 | codes[6] << 4])
    body = (struct.pack("<i", 7) + packed + struct.pack("<b", -3) + struct.pack("<h", 300)
            + struct.pack("<i", -70000) + struct.pack("<i", 2**31 - 1) + struct.pack("<b", 5))
    blob = _lz4_literals(body)
    values, end = _decode_ints(struct.pack("<Q", len(blob)) + blob, 0, len(deltas))
    expected = (np.cumsum(deltas) + 2**31) % 2**32 - 2**31
    np.testing.assert_array_equal(values, expected)
    assert end == 8 + len(blob)
    ours = np.array([0, 5, -1, 2**31 - 1, -2**31, 12], np.int64)
    np.testing.assert_array_equal(_decode_ints(_compressed_ints(ours), 0, len(ours))[0], ours)


def test_a_large_base_usd_compressed(tmp_path):
    """A base of 2,000 prims: usd-core's sections use LZ4 back-references and short integer
    codes; the merged file reads as Sdf's."""
    layer = Sdf.Layer.CreateAnonymous(".usdc")
    root = Sdf.PrimSpec(layer, "World", Sdf.SpecifierDef, "Xform")
    attrs = []
    for k in range(2000):
        prim = Sdf.PrimSpec(root, f"Mesh_{k}", Sdf.SpecifierDef, "Mesh")
        Sdf.AttributeSpec(prim, "points", Sdf.ValueTypeNames.Point3fArray)
        Sdf.AttributeSpec(prim, "doubleSided", Sdf.ValueTypeNames.Bool).default = k % 2 == 0
        if k % 97 == 0:
            attrs.append((f"/World/Mesh_{k}.points", _samples(2, 3)))
    layer.Export(str(tmp_path / "base.usdc"))
    crate = CrateSamples(tmp_path / "out.usdc", 24.0, base=tmp_path / "base.usdc")
    for attr, values in attrs:
        crate.add(attr, "point3f[]", [0.0, 1.0], values)
    crate.close(0, 1)
    for attr, values in attrs:
        for t, v in enumerate(values):
            layer.SetTimeSample(attr, float(t), Vt.Vec3fArray.FromNumpy(v))
    layer.startTimeCode, layer.endTimeCode = 0, 1
    assert Sdf.Layer.FindOrOpen(str(tmp_path / "out.usdc")).ExportToString() == \
        layer.ExportToString()


def test_held_frames_are_stored_once(tmp_path):
    """A frame equal to the one added before it (a held pose, a static mesh or transform) is
    stored once and shared, as usd-core's crate writer shares equal arrays: every time still
    reads its values, and the file holds each distinct frame once."""
    a, b = _samples(2, 1000)
    d = a.copy()
    d[0, 1] += 1.0  # equal to ``a`` at every probed element (a sample of 16), not at one other
    frames = np.stack([a, a, d, b, b, b])
    m = RNG.normal(size=(2, 4, 4))
    mats = np.stack([m[0], m[0], m[0], m[1], m[1], m[1]])

    def write(path, hold):
        crate = CrateSamples(path, 24.0)
        for lo, hi in ((0, 3), (3, 4), (4, 6)):  # holds across blocks too
            crate.add("/A.points", "point3f[]", np.arange(lo, hi, dtype=float),
                      frames[lo:hi] if hold else frames[lo:hi] + np.arange(lo, hi)[:, None, None])
            crate.add("/B.xformOp:transform", "matrix4d", np.arange(lo, hi, dtype=float),
                      mats[lo:hi])
        crate.close(0, 5)
        return path.stat().st_size

    held, moving = write(tmp_path / "held.usdc", True), write(tmp_path / "moving.usdc", False)
    assert moving - held == 3 * (8 + 12_000)  # a held once, b twice; d (one float off) written
    layer = Sdf.Layer.FindOrOpen(str(tmp_path / "held.usdc"))
    for f in range(6):
        np.testing.assert_array_equal(np.asarray(layer.QueryTimeSample("/A.points", f)),
                                      frames[f])
        np.testing.assert_array_equal(np.array(layer.QueryTimeSample("/B.xformOp:transform", f)),
                                      mats[f].T)


def test_one_attribute_however_its_path_is_spelled(tmp_path):
    """A variant selection written with spaces is the same attribute (its samples kept)."""
    layer = Sdf.Layer.CreateAnonymous(".usdc")
    prim = Sdf.PrimSpec(layer, "A", Sdf.SpecifierDef)
    variant = Sdf.VariantSpec(Sdf.VariantSetSpec(prim, "v"), "x")
    mesh = Sdf.PrimSpec(variant.primSpec, "B", Sdf.SpecifierDef, "Mesh")
    Sdf.AttributeSpec(mesh, "points", Sdf.ValueTypeNames.Point3fArray)
    layer.Export(str(tmp_path / "base.usdc"))
    crate = CrateSamples(tmp_path / "out.usdc", 24.0, base=tmp_path / "base.usdc")
    crate.add("/A{ v = x }B.points", "point3f[]", [0.0], np.ones((1, 2, 3)))
    crate.add("/A{v=x}B.points", "point3f[]", [1.0], np.zeros((1, 2, 3)))
    crate.close(0, 1)
    ours = Sdf.Layer.FindOrOpen(str(tmp_path / "out.usdc"))
    assert ours.ListTimeSamplesForPath("/A{v=x}B.points") == [0.0, 1.0]


@pytest.mark.parametrize("direct", ["1", "0"])
def test_a_dropped_writer_closes_only_after_its_queued_writes(tmp_path, monkeypatch, direct):
    """The writer thread may still hold an unclosed writer's writes when it is dropped: its
    descriptor closes after them (closed earlier, the number could be reused by another file,
    which the late writes would then fill), direct I/O or not."""
    import gc
    import os
    import threading

    import dqskin.files.crate as crate_mod
    from dqskin.files.direct import AppendFile

    monkeypatch.setenv("DQSKIN_DIRECT_IO", direct)
    gate, real = threading.Event(), AppendFile.append_records
    crate = CrateSamples(tmp_path / "dropped.usdc", 24.0)
    monkeypatch.setattr(AppendFile, "append_records",
                        lambda self, *args: (gate.wait(5), real(self, *args))[1])
    crate.add("/A.points", "point3f[]", [0.0], np.ones((1, 1000, 3), np.float32))
    fds = [crate._file._fd]
    del crate
    gc.collect()
    for fd in fds:
        assert os.readlink(f"/proc/self/fd/{fd}") == str(tmp_path / "dropped.usdc")  # not yet
    gate.set()
    crate_mod._writer().submit(lambda: None).result()  # the writer thread's queue ran
    for fd in fds:
        assert not os.path.exists(f"/proc/self/fd/{fd}") or \
            os.readlink(f"/proc/self/fd/{fd}") != str(tmp_path / "dropped.usdc")
    if direct == "0":
        assert (tmp_path / "dropped.usdc").stat().st_size == 88 + 8 + 12_000  # its write, done


@pytest.mark.parametrize("version", [(0, 6, 0), (1, 0, 0)])
def test_a_base_of_another_crate_version_is_refused_as_unsupported(tmp_path, version):
    """A base whose crate version this writer cannot extend raises ``UnsupportedCrate`` (which
    a caller can write another way), leaving no output; a file that is not a crate raises a
    plain ValueError."""
    from dqskin.files.crate import UnsupportedCrate
    base = tmp_path / "base.usdc"
    assert _base_layer().Export(str(base))
    data = bytearray(base.read_bytes())
    data[8:11] = bytes(version)
    base.write_bytes(bytes(data))
    with pytest.raises(UnsupportedCrate, match="crate version"):
        CrateSamples(tmp_path / "out.usdc", 30.0, base=base)
    assert not (tmp_path / "out.usdc").exists()
    (tmp_path / "text.usdc").write_text("#usda 1.0\n")
    with pytest.raises(ValueError, match="not a USD crate file") as err:
        CrateSamples(tmp_path / "out2.usdc", 30.0, base=tmp_path / "text.usdc")
    assert not isinstance(err.value, UnsupportedCrate)


def test_add_many_takes_an_attribute_twice_and_refuses_before_writing_any(tmp_path):
    """One ``add_many`` holding two blocks of one attribute (the second's first frame a hold of
    the first's last) reads as Sdf's layer of them; a call with a block it refuses (another
    type for an attribute added in the same call) adds none of its blocks."""
    path = tmp_path / "many.usdc"
    crate = CrateSamples(path, 24.0)
    a, b = _samples(3, 5), _samples(2, 5)
    b[0] = a[-1]
    crate.add_many([("/M.points", "point3f[]", [1.0, 2.0, 3.0], a, ()),
                    ("/M.points", "point3f[]", [4.0, 5.0], b, ())])
    with pytest.raises(ValueError, match="added as point3f"):
        crate.add_many([("/N.points", "point3f[]", [1.0], a[:1], ()),
                        ("/N.points", "normal3f[]", [2.0], a[1:2], ())])
    crate.close(1.0, 5.0)
    ref = _sdf_layer(24.0, 1.0, 5.0, [("/M.points", "point3f[]", [1.0, 2.0, 3.0, 4.0, 5.0],
                                       np.concatenate([a, b]), ())])
    assert Sdf.Layer.FindOrOpen(str(path)).ExportToString() == ref.ExportToString()


def test_chunks_of_many_attributes_store_each_held_frame_once(tmp_path):
    """``add_many`` of many attributes at once, as a bake adds a chunk (point counts 0, 1, odd
    and even: padded records; matrices; 2 frames of most attributes and 1 of others in one
    call; an attribute twice in one call): each frame equal to its attribute's frame before it
    (within a block, across blocks, across calls, after the same attribute's block in the same
    call) is stored once, a frame off at one element the probe skips is stored, and every time
    reads its own values (Sdf's layer of the same samples, as text)."""
    counts = [0, 1, 3, 16, 17, 1000]
    pattern = [0, 0, 1, 1, 2, 2, 2, 3]  # distinct frame of each of the 8 times
    attrs = []  # (path, type name, (8, ...) values)
    for k, n in enumerate(counts):
        distinct = _samples(4, n)
        if n == 1000:
            distinct[3] = distinct[2]
            distinct[3, 0, 1] += 1.0  # element 1 of 3000: not among the 16 probed
        attrs.append((f"/M{k}.points", "point3f[]", distinct[np.roll(pattern, k)]))
    m = RNG.normal(size=(4, 4, 4))
    attrs.append(("/X.xformOp:transform", "matrix4d", m[pattern]))
    # the calls: times 0-1 of all; 2-3 (/M2 as two blocks, /M4 only at 2); 4-6 (/M4 at 3-6); 7
    calls = [[(a, [0, 1]) for a in range(len(attrs))],
             [(a, [2, 3]) for a in range(len(attrs)) if a not in (2, 4)]
             + [(2, [2]), (4, [2]), (2, [3])],
             [(a, [4, 5, 6]) for a in range(len(attrs)) if a != 4] + [(4, [3, 4, 5, 6])],
             [(a, [7]) for a in range(len(attrs))]]

    def write(path, moving):
        crate = CrateSamples(path, 24.0)
        for call in calls:
            crate.add_many([(attrs[a][0], attrs[a][1], np.array(ts, float),
                             attrs[a][2][ts] + (np.array(ts)[:, None, None] if moving else 0),
                             ()) for a, ts in call])
        crate.close(0, 7)
        return path.stat().st_size

    held = write(tmp_path / "held.usdc", False)
    moving = write(tmp_path / "moving.usdc", True)
    record = [8 + 12 * n + (-12 * n) % 8 if n else 0 for n in counts] + [128]
    again = [sum(np.array_equal(v[f], v[f - 1]) for f in range(1, 8)) for _, _, v in attrs]
    assert list(np.roll(pattern, 5)[3:5]) == [2, 3] and again[-2] == 3  # 3 after 2: stored
    assert moving - held == sum(r * h for r, h in zip(record, again))
    ref = _sdf_layer(24.0, 0.0, 7.0, [(p, t, np.arange(8.0), v, ()) for p, t, v in attrs])
    assert Sdf.Layer.FindOrOpen(str(tmp_path / "held.usdc")).ExportToString() == \
        ref.ExportToString()
