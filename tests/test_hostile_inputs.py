"""Hostile inputs to the readers, weights files, the weights cache and ``rig`` (issue 30, part B):
never a hang, never an allocation the data does not justify, never silently wrong, and every
error one line naming the file and field, printed safely.

Every hostile file is generated here, small; the sizes an input claims are checked against
``max_input_gib`` lowered to a few MiB, so no test allocates more than that even without the
checks. Reads that would block (FIFOs) run in a thread that the test unblocks itself if they do.
"""

import os
import re
import socket
import struct
import subprocess
import sys
import threading
import tracemalloc
import zipfile
from pathlib import Path

import numpy as np
import pytest
import trimesh

from dqskin import cache as weights_cache
from dqskin import readers
from dqskin.cli import main
from dqskin.errors import InputError, LimitError
from dqskin.files.inputs import open_input, read_npz, regular_file
from dqskin.readers import bvh
from dqskin.readers.mesh import load_mesh
from dqskin.rigging import read_weights, replace_weights, rig_mesh
from dqskin.terminal import printable
from dqskin.writers.usd_rig import write_rig

HUMANOID = Path(__file__).resolve().parents[1] / "assets" / "humanoid.usda"

LEG = """HIERARCHY
ROOT hips
{
OFFSET 0 0 0
CHANNELS 6 Xposition Yposition Zposition Zrotation Xrotation Yrotation
JOINT knee
{
OFFSET 0 -1 0
CHANNELS 3 Zrotation Xrotation Yrotation
End Site
{
OFFSET 0 -1 0
}
}
}
MOTION
Frames: 3
Frame Time: 0.04
0 0 0 0 0 0 0 0 0
0 0 0 0 0 0 30 0 0
0 0 0 0 0 0 60 0 0
"""


@pytest.fixture
def leg(tmp_path):
    """A two-joint BVH and a box around its bones, in its rest pose."""
    path = tmp_path / "leg.bvh"
    path.write_text(LEG)
    box = trimesh.creation.box(extents=(0.4, 2.0, 0.4))
    box.apply_translation((0, -1.0, 0))
    box = box.subdivide()
    mesh = tmp_path / "leg.obj"
    box.export(mesh)
    return path, mesh


def returns_soon(fn, unblock=None, timeout=20.0):
    """``fn()``'s result (or exception) if it returns within ``timeout`` seconds; otherwise
    ``unblock()`` is called (so the thread ends) and the test fails."""
    out = {}

    def run():
        try:
            out["value"] = fn()
        except BaseException as exc:  # noqa: BLE001 — handed to the test
            out["error"] = exc

    t = threading.Thread(target=run, daemon=True)
    t.start()
    t.join(timeout)
    if t.is_alive():
        if unblock is not None:
            unblock()
        t.join(5)
        pytest.fail(f"{fn} did not return within {timeout} s (blocked on its input)")
    if "error" in out:
        raise out["error"]
    return out.get("value")


def fifo(path):
    os.mkfifo(path)

    def unblock():  # a writer that opens and closes: a blocked reader sees the end of the file
        fd = os.open(path, os.O_WRONLY | os.O_NONBLOCK)
        os.close(fd)
    return path, unblock


# -- bounded reads: one check where an input is opened ------------------------------------------

def test_special_files_are_refused_by_name(tmp_path):
    """FIFOs, devices, sockets and folders are refused where any input is opened, in one line
    naming the file and what it is; nothing blocks on them."""
    pipe, unblock = fifo(tmp_path / "pipe.npz")
    sock_path = tmp_path / "s.bvh"
    sock = socket.socket(socket.AF_UNIX)
    sock.bind(str(sock_path))
    try:
        cases = [(pipe, "a FIFO"), (Path("/dev/null"), "a device"), (sock_path, "a socket"),
                 (tmp_path, "a folder")]
        for path, kind in cases:
            for fn in (regular_file, open_input):
                with pytest.raises(InputError, match=f"^{re.escape(str(path))}: {kind}, not a "
                                   "regular file$"):
                    returns_soon(lambda: fn(path), unblock)
        readers_ = [lambda: read_npz(pipe, ["a"]), lambda: read_weights(pipe, ["a"], 1),
                    lambda: bvh.read_bvh(pipe), lambda: load_mesh(pipe),
                    lambda: readers.load(pipe.rename(tmp_path / "pipe.glb") or
                                         tmp_path / "pipe.glb")]
        for read in readers_:
            with pytest.raises(InputError, match="a FIFO, not a regular file"):
                returns_soon(read, unblock)
    finally:
        sock.close()


def test_each_loader_refuses_a_fifo_itself(tmp_path):
    """Every format's own loader (and ``flatten``) makes the check, not only
    :func:`dqskin.readers.load` or the CLI: called directly, none hands a FIFO to its parser
    (ufbx would block on it) or calls it a missing file."""
    from dqskin.readers import fbx, gltf, usd
    for module, name in ((fbx, "pipe.fbx"), (gltf, "pipe.glb"), (usd, "pipe.usda"),
                         (bvh, "pipe.bvh")):
        pipe, unblock = fifo(tmp_path / name)
        with pytest.raises(InputError, match="a FIFO, not a regular file"):
            returns_soon(lambda: module.load(pipe), unblock)
    from dqskin.writers.usd_clips import flatten
    with pytest.raises(InputError, match="pipe.usda: a FIFO, not a regular file"):
        returns_soon(lambda: flatten(tmp_path / "pipe.usda", tmp_path / "flat.usda"), unblock)


def test_a_fifo_in_the_weights_cache_is_a_miss_and_rig_does_not_hang(leg, tmp_path, monkeypatch):
    """The cache entry of a rig replaced by a FIFO: the entry is a miss, computed again."""
    monkeypatch.setenv("DQSKIN_CACHE_DIR", str(tmp_path / "cache"))
    path, mesh = leg
    first = rig_mesh(mesh, path, as_is=True).meshes[0]
    (entry,) = (tmp_path / "cache" / "weights").glob("*.npz")
    entry.unlink()
    _, unblock = fifo(entry)
    assert returns_soon(lambda: weights_cache.load(entry, {"a": ((1,), np.int32)}), unblock) \
        is None
    again = returns_soon(lambda: rig_mesh(mesh, path, as_is=True).meshes[0], unblock)
    np.testing.assert_array_equal(again.joint_weights, first.joint_weights)


def test_flatten_refuses_a_fifo_in_place_of_a_clip_layer(tmp_path):
    from pxr import Sdf, Vt
    folder = tmp_path / "c"
    folder.mkdir()
    clip = Sdf.Layer.CreateNew(str(folder / "clip.0.usda"))
    prim = Sdf.CreatePrimInLayer(clip, "/A")
    attr = Sdf.AttributeSpec(prim, "x", Sdf.ValueTypeNames.Float)
    clip.SetTimeSample(attr.path, 0, 0.0)
    clip.Save()
    os.mkfifo(folder / "clip.1.usda")
    top = Sdf.Layer.CreateNew(str(tmp_path / "top.usda"))
    prim = Sdf.PrimSpec(top, "A", Sdf.SpecifierDef)
    Sdf.AttributeSpec(prim, "x", Sdf.ValueTypeNames.Float)
    prim.SetInfo("clips", {"default": {
        "assetPaths": Sdf.AssetPathArray(["./c/clip.0.usda", "./c/clip.1.usda"]),
        "primPath": "/A", "active": Vt.Vec2dArray([(0.0, 0.0), (1.0, 1.0)])}})
    top.Save()
    proc = subprocess.run([sys.executable, "-m", "dqskin.cli", "flatten",
                           str(tmp_path / "top.usda"), "--out", str(tmp_path / "flat.usda")],
                          capture_output=True, text=True, timeout=60)
    assert proc.returncode == 2, proc.stderr
    assert "c/clip.1.usda: layer named by " in proc.stderr, proc.stderr
    assert "top.usda: a FIFO, not a regular file" in proc.stderr, proc.stderr
    assert not (tmp_path / "flat.usda").exists()


def test_flatten_does_not_block_on_a_fifo_plan_or_record(tmp_path):
    """A clip bake whose plan.json, then a chunk's record, is a FIFO: flatten reads neither
    (a record that is not a file is no record: the layer is then checked as another tool's)."""
    from dqskin import bake
    from dqskin.writers.usd_clips import clips_folder, flatten
    out = tmp_path / "shot.usd"
    scene = readers.load(HUMANOID)
    bake(scene, out, scene.times[:24], chunk=8, clips=True, normals=False, velocities=False)
    folder = clips_folder(out)
    for n, name in enumerate(["plan.json", "chunk_00001.json"]):
        (folder / name).unlink()
        _, unblock = fifo(folder / name)
        returns_soon(lambda: flatten(out, tmp_path / f"flat{n}.usdc"), unblock)
        assert (tmp_path / f"flat{n}.usdc").is_file()


# -- sizes checked before allocating --------------------------------------------------------------

def _npy_header(shape, dtype="<f4"):
    header = repr({"descr": dtype, "fortran_order": False, "shape": shape}).encode()
    header += b" " * (63 - (len(header) + 10) % 64) + b"\n"
    return b"\x93NUMPY\x01\x00" + struct.pack("<H", len(header)) + header


def test_npz_headers_are_checked_before_the_array_is_allocated(tmp_path):
    """A header claiming 9.6 GB over 16 bytes of data is refused as damaged; an honest array
    (or a deflate bomb: a small archive of a large array) beyond the limit is a LimitError
    naming the file, the array and the parameter, before anything is decompressed."""
    liar = tmp_path / "liar.npz"
    with zipfile.ZipFile(liar, "w") as z:
        z.writestr("joint_weights.npy", _npy_header((1_200_000_000, 2)) + bytes(16))
    with pytest.raises(InputError, match=r"liar.npz: cannot read weights: joint_weights: the "
                       r"header asks for 9,600,000,000 bytes, the archive holds 16"):
        read_npz(liar, ["joint_weights"], what="weights")
    bomb = tmp_path / "bomb.npz"  # 8 MiB of zeros in a few kB
    with zipfile.ZipFile(bomb, "w", zipfile.ZIP_DEFLATED) as z:
        with z.open("joint_weights.npy", "w") as m:
            m.write(_npy_header((1 << 21,)))
            for _ in range(8):
                m.write(bytes(1 << 20))
    assert bomb.stat().st_size < 100_000
    tracemalloc.start()
    try:
        with pytest.raises(LimitError, match=r"bomb.npz: joint_weights: needs 0.00781 GiB, more "
                           r"than the limit of 0.001 GiB; raise max_input_gib"):
            read_npz(bomb, ["joint_weights"], max_input_gib=0.001)
        assert tracemalloc.get_traced_memory()[1] < 1 << 20
    finally:
        tracemalloc.stop()
    assert read_npz(bomb, ["joint_weights"])["joint_weights"].shape == (1 << 21,)


def test_a_weights_file_that_is_no_npz_is_one_line(leg, tmp_path, capsys):
    path, mesh = leg
    npy, text = tmp_path / "plain.npz", tmp_path / "text.npz"
    np.save(tmp_path / "plain.npy", np.zeros(3))
    (tmp_path / "plain.npy").rename(npy)
    text.write_text("joint_indices = 1\n")
    for f, what in ((npy, "a .npy array, not an .npz archive"), (text, "not an .npz archive")):
        with pytest.raises(InputError, match=f"^{re.escape(str(f))}: cannot read weights: "
                           f"{re.escape(what)}$"):
            read_weights(f, ["hips", "knee"], 10)
        assert main(["rig", str(mesh), "--skeleton", str(path), "--as-is", "--weights", str(f),
                     "--out", str(tmp_path / "r.usda")]) == 2
        err = capsys.readouterr().err
        assert err == f"dqskin: error: {f}: cannot read weights: {what}\n", err


def test_gltf_morph_targets_sharing_one_accessor_are_sized_first(tmp_path):
    """100 morph targets sharing one 3,000-vertex accessor without a bufferView (zeros): the
    (targets, V, 3) offsets are sized against the limit before they are allocated."""
    import json
    V, T = 3000, 100
    doc = {"asset": {"version": "2.0"},
           "accessors": [{"componentType": 5126, "count": V, "type": "VEC3",
                          "min": [0, 0, 0], "max": [0, 0, 0]},
                         {"componentType": 5126, "count": V, "type": "VEC3"}],
           "meshes": [{"primitives": [{"attributes": {"POSITION": 0},
                                       "targets": [{"POSITION": 1}] * T}]}],
           "nodes": [{"mesh": 0}], "scenes": [{"nodes": [0]}], "scene": 0}
    path = tmp_path / "shared.gltf"
    path.write_text(json.dumps(doc))
    with pytest.raises(LimitError, match=r"shared.gltf: meshes\[0\].primitives\[0\].targets: 100 "
                       r"POSITION targets × 3000 vertices: needs 0.00671 GiB, more than the limit "
                       r"of 0.001 GiB; raise max_input_gib"):
        readers.load(path, max_input_gib=0.001)
    assert len(readers.load(path).meshes) == 1
    assert main(["info", str(path), "--max-input-gib", "0.001"]) == 2


def test_bvh_frames_and_channels_are_sized_against_the_data(tmp_path):
    """A header asking for Frames × channels far beyond the characters that follow it is
    refused before the values are allocated (no allocation of that size is traced)."""
    J, F = 300, 2000  # 1,800 channels × 2,000 frames: 28.8 MB asked by a 40 kB file
    lines = ["HIERARCHY", "ROOT j0", "{", "OFFSET 0 0 0",
             "CHANNELS 6 Xposition Yposition Zposition Zrotation Xrotation Yrotation"]
    for j in range(1, J):
        lines += [f"JOINT j{j}", "{", "OFFSET 0 1 0", "CHANNELS 6 Xposition Yposition "
                  "Zposition Zrotation Xrotation Yrotation"]
    lines += ["}"] * J + ["MOTION", f"Frames: {F}", "Frame Time: 0.04"] + ["0"] * F
    path = tmp_path / "greedy.bvh"
    path.write_text("\n".join(lines) + "\n")
    tracemalloc.start()
    try:
        with pytest.raises(InputError, match=r"greedy.bvh: line \d+: frame 0 has 1 values, "
                           r"expected 1800"):
            bvh.read_bvh(path)
        assert tracemalloc.get_traced_memory()[1] < 20_000_000
    finally:
        tracemalloc.stop()
    short = tmp_path / "short.bvh"  # honest data, beyond a lowered limit
    short.write_text(LEG)
    with pytest.raises(LimitError, match=r"short.bvh: Frames × channels \(3 × 9\): needs "
                       "2.01e-07 GiB, more than the limit of 1e-07 GiB; raise max_input_gib"):
        bvh.read_bvh(short, max_input_gib=1e-7)


def test_automatic_weights_refuse_a_mesh_beyond_the_vertex_limit(leg, capsys, tmp_path):
    path, mesh = leg
    n = len(load_mesh(mesh)[0])
    with pytest.raises(LimitError, match=f"leg.obj: {n} vertices, more than the limit of 10 "
                       "for automatic weights; raise max_vertices"):
        rig_mesh(mesh, path, as_is=True, max_vertices=10)
    with pytest.raises(LimitError, match="humanoid.usda: .*: [0-9,]+ vertices, more than the "
                       "limit of 10"):
        replace_weights(readers.load(HUMANOID), max_vertices=10)
    assert main(["rig", str(mesh), "--skeleton", str(path), "--as-is", "--max-vertices", "10",
                 "--out", str(tmp_path / "r.usda")]) == 2
    assert "raise --max-vertices to allow more" in capsys.readouterr().err


# -- the weights cache is validated where it is read ----------------------------------------------

def test_a_cache_entry_with_negative_weights_is_never_used(leg, tmp_path, monkeypatch):
    monkeypatch.setenv("DQSKIN_CACHE_DIR", str(tmp_path / "cache"))
    path, mesh = leg
    first = rig_mesh(mesh, path, as_is=True).meshes[0]
    (entry,) = (tmp_path / "cache" / "weights").glob("*.npz")
    w = np.array(first.joint_weights)
    w[:, 0], w[:, 1] = -w[:, 0], w[:, 1] + 2 * w[:, 0]  # still summing to 1
    np.savez(entry, joint_indices=np.asarray(first.joint_indices, np.int32),
             joint_weights=w.astype(np.float32))
    again = rig_mesh(mesh, path, as_is=True).meshes[0]
    assert np.asarray(again.joint_weights).min() >= 0
    np.testing.assert_array_equal(again.joint_weights, first.joint_weights)
    write_rig(rig_mesh(mesh, path, as_is=True), tmp_path / "r.usda")
    from pxr import Usd, UsdSkel
    stage = Usd.Stage.Open(str(tmp_path / "r.usda"))
    (prim,) = [p for p in stage.Traverse() if p.GetTypeName() == "Mesh"]
    assert min(UsdSkel.BindingAPI(prim).GetJointWeightsPrimvar().Get()) >= 0


# -- BVH ------------------------------------------------------------------------------------------

def _chain(depth, end_sites=False):
    lines = ["HIERARCHY"]
    for j in range(depth):
        lines += [("ROOT" if j == 0 else "JOINT") + f" j{j}", "{", "OFFSET 0 0.01 0",
                  "CHANNELS 3 Zrotation Xrotation Yrotation"]
        if end_sites:
            lines += ["End Site", "{", "OFFSET 0 0.01 0", "}"]
    lines += ["}"] * depth + ["MOTION", "Frames: 1", "Frame Time: 0.04",
                              " ".join(["0"] * 3 * depth)]
    return "\n".join(lines) + "\n"


def test_a_bvh_ten_thousand_joints_deep_reads_and_info_is_fast(tmp_path, capsys):
    import time
    path = tmp_path / "deep.bvh"
    path.write_text(_chain(10_000, end_sites=True))
    motion = bvh.read_bvh(path)
    assert len(motion.joint_names) == 10_000 and motion.parents[-1] == 9_998
    assert len(motion.end_sites) == 10_000
    start = time.perf_counter()
    assert main(["info", str(path)]) == 0
    assert time.perf_counter() - start < 30  # (109 s when the rest pose was redone per End Site)
    out = capsys.readouterr().out
    assert "10000 End Sites" in out and "problems: none" in out


@pytest.mark.parametrize("header, field", [
    ("Frames: inf", "Frames: 'inf'"), ("Frames: nan", "Frames: 'nan'"),
    ("Frames: \u0661\u0662", "Frames: '\u0661\u0662'"), ("Frames: 1e3", "Frames: '1e3'")])
def test_bvh_frame_counts_must_be_ascii_whole_numbers(tmp_path, header, field):
    path = tmp_path / "bad.bvh"
    path.write_text(LEG.replace("Frames: 3", header), encoding="utf-8")
    with pytest.raises(InputError, match=f"^{re.escape(str(path))}: line 17: {re.escape(field)}: "
                       "expected a whole number from 1 to 10000000$"):
        bvh.read_bvh(path)


@pytest.mark.parametrize("value", ["5e-324", "1e-9", "0", "-0.04", "nan", "inf", "\u0660.04"])
def test_bvh_frame_time_must_be_a_usable_ascii_number(tmp_path, value):
    """A subnormal Frame Time would make time codes per second infinite."""
    path = tmp_path / "bad.bvh"
    path.write_text(LEG.replace("Frame Time: 0.04", f"Frame Time: {value}"), encoding="utf-8")
    with pytest.raises(InputError, match=f"^{re.escape(str(path))}: line 18: Frame Time: "
                       f"{re.escape(repr(value))}: expected seconds per frame, at least 1e-06$"):
        bvh.read_bvh(path)


def test_bvh_values_must_be_ascii_numbers_within_float32(tmp_path):
    for value, what in (("\u0663\u0660", "not a number: '\u0663\u0660'"),
                        ("1e39", "channel 6: 1e39 is not finite or beyond float32 range")):
        path = tmp_path / "bad.bvh"
        path.write_text(LEG.replace("0 0 0 0 0 0 60 0 0", f"0 0 0 0 0 0 {value} 0 0"),
                        encoding="utf-8")
        with pytest.raises(InputError, match=f"^{re.escape(str(path))}: line 21: frame 2: "
                           f"{re.escape(what)}$"):
            bvh.read_bvh(path)


def test_a_bvh_with_a_byte_order_mark_is_read(tmp_path):
    path = tmp_path / "bom.bvh"
    path.write_bytes(b"\xef\xbb\xbf" + LEG.encode())
    motion = bvh.read_bvh(path)
    assert motion.joint_names == ["hips", "knee"] and motion.frame_count == 3


def test_skin_errors_name_the_bvh_not_the_temporary_rig(leg, tmp_path, capsys):
    """A motion whose FK overflows float32 (each value within it), bound as it is: the USD
    cache's error names the BVH the user gave, not a temporary rig."""
    path, mesh = leg
    path.write_text(LEG.replace("0 0 0 0 0 0 30 0 0", "0 3e38 0 0 0 0 30 0 0")
                    .replace("0 0 0 0 0 0 60 0 0", "0 3e38 0 0 0 0 60 0 0"))
    assert main(["skin", str(mesh), "--skeleton", str(path), "--as-is", "--out",
                 str(tmp_path / "x.usda")]) == 2
    err = capsys.readouterr().err.splitlines()[-1]
    assert err.startswith(f"dqskin: error: {path}: "), err
    assert "dqskin-rig-" not in err


# -- meshes and morph weights ---------------------------------------------------------------------

@pytest.mark.parametrize("vertex, what", [
    ("v inf 0 0", r"vertices: NaN or infinite at vertex 0"),
    ("v nan 0 0", r"vertices: NaN or infinite at vertex 0"),
    ("v 1e39 0 0", r"vertices: beyond float32 range at vertex 0")])
def test_obj_vertices_must_be_finite(tmp_path, vertex, what):
    path = tmp_path / "bad.obj"
    path.write_text(f"{vertex}\nv 0 1 0\nv 0 0 1\nf 1 2 3\n")
    with pytest.raises(InputError, match=f"^{re.escape(str(path))}: {what}"):
        load_mesh(path)


def test_a_mesh_without_extent_is_refused(leg, tmp_path, capsys):
    path, _ = leg
    flat = tmp_path / "dot.obj"
    flat.write_text("v 0 -1 0\nv 0 -1 0\nv 0 -1 0\nf 1 2 3\n")
    with pytest.raises(InputError, match=r"dot.obj: vertices: all 3 are at one point"):
        load_mesh(flat)
    with pytest.raises(InputError, match=r"^mesh: vertices: NaN or infinite at vertex 1"):
        rig_mesh((np.array([[0, 0, 0], [np.nan, 0, 0], [0, 1, 0]]), [[0, 1, 2]]), path)
    assert main(["rig", str(flat), "--skeleton", str(path), "--out",
                 str(tmp_path / "r.usda")]) == 2
    assert "--scale" not in capsys.readouterr().err


def test_gltf_morph_weights_beyond_float32_name_the_file_and_field(tmp_path):
    import json

    from test_gltf_morph import build_morph
    path = tmp_path / "m.gltf"
    build_morph(path)
    doc = json.loads(path.read_text())
    doc["nodes"][2]["weights"] = [1e300, 0, 0]
    doc.pop("animations")
    bad = tmp_path / "big.gltf"
    bad.write_text(json.dumps(doc))
    with pytest.raises(InputError, match=r"^big.gltf: nodes\[2\].weights\[0\]: 1e\+300 is "
                       "beyond float32 range$"):
        readers.load(bad)
    # weights within float32 whose sum of offsets is not: the vertex coordinate where the
    # targets' offsets add up most (|Σ oᵢ| > 1), each weight 3e38 with its offset's sign
    offsets = readers.load(path).meshes[0].deformer.offsets["POSITION"]  # (T, V, 3)
    total = np.abs(offsets).sum(0)
    at = np.unravel_index(total.argmax(), total.shape)
    assert total[at] * 3e38 > 3.5e38
    doc["nodes"][2]["weights"] = [3e38 * float(np.sign(o)) for o in offsets[:, at[0], at[1]]]
    bad.write_text(json.dumps(doc))
    scene = readers.load(bad)
    with pytest.raises(InputError, match=r"^big.gltf: meshes\[0\].primitives\[0\]: POSITION "
                       r"morphed by weights \[.*\] at time 0 is beyond float32 range$"):
        scene.skin([0.0])


# -- data loss: rig over a layer of its input -----------------------------------------------------

def test_rig_refuses_to_replace_a_sublayer_of_its_input(tmp_path, capsys):
    anim = tmp_path / "anim.usda"
    anim.write_bytes(HUMANOID.read_bytes())
    root = tmp_path / "root.usda"
    root.write_text('#usda 1.0\n(\n    subLayers = [@./anim.usda@]\n)\n')
    before = anim.read_bytes()
    with pytest.raises(InputError, match="anim.usda: refusing to overwrite an input of"):
        write_rig(readers.load(root), anim, force=True)
    assert main(["rig", str(root), "--weights", "auto", "--out", str(anim), "--force"]) == 2
    assert "refusing to overwrite an input" in capsys.readouterr().err
    assert anim.read_bytes() == before


# -- output and terminal --------------------------------------------------------------------------

def test_unbuffered_output_to_a_full_disk_exits_120(tmp_path):
    if not os.path.exists("/dev/full"):
        pytest.fail("/dev/full is missing (a Linux machine runs this test)")
    env = dict(os.environ, PYTHONUNBUFFERED="1")
    with open("/dev/full", "w") as full:
        proc = subprocess.run([sys.executable, "-m", "dqskin.cli", "info", str(HUMANOID)],
                              stdout=full, stderr=subprocess.PIPE, text=True, timeout=300,
                              env=env)
    assert proc.returncode == 120, proc.stderr
    assert proc.stderr == ("dqskin: error: writing <stdout>: [Errno 28] No space left on "
                           "device\n")


def test_names_are_printed_safely(tmp_path, capsys):
    """A joint name with escape sequences (clear the screen, retitle the terminal) and a file
    name with a newline and a forged line: printed as escapes, one line each."""
    evil = "j\x1b[2J\x1b]0;pwned\x07\u202e"
    path = tmp_path / "evil.bvh"
    path.write_text(LEG.replace("JOINT knee", f"JOINT {evil}"))
    assert main(["info", str(path)]) == 0
    out = capsys.readouterr().out
    assert "\x1b" not in out and "\x07" not in out and "\u202e" not in out
    assert "j\\x1b[2J\\x1b]0;pwned\\x07\\u202e" in out
    forged = tmp_path / "x\n  problems: none\n.bvh"
    assert main(["info", str(forged)]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "x\\n  problems: none\\n.bvh: no such file" in err
    assert printable("plain näme") == "plain näme"
