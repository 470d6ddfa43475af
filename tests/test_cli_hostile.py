"""The CLI against hostile input and hostile conditions, as a process: validation in every output
format, SIGINT/SIGTERM mid-write, concurrent writers, per-frame file rules, messages and noise.

Exit status 0 done, 2 bad input or refused, 130 SIGINT, 143 SIGTERM; one line on stderr.
"""

import contextlib
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from test_cli import assert_clean_error, run, usda

ASSETS = Path(__file__).resolve().parents[1] / "assets"
HUMANOID = ASSETS / "humanoid.usda"
TWIST = ASSETS / "twist_cylinder.usda"


def start(*args):
    return subprocess.Popen([sys.executable, "-m", "dqskin.cli", *map(str, args)],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


def temp_files(folder):
    return sorted(p.name for p in Path(folder).iterdir() if p.name.startswith("."))


def temp_bytes(folder):
    """Bytes written so far into the temporary outputs beside the targets in ``folder`` (each a
    private folder named ``.*``, :class:`dqskin.files.atomic.atomic_path`), None before any."""
    temps = [p for p in Path(folder).iterdir() if p.name.startswith(".")]
    if not temps:
        return None
    total = 0
    for temp in temps:
        for f in (temp.rglob("*") if temp.is_dir() else [temp]):
            with contextlib.suppress(OSError):  # (renamed or removed meanwhile)
                total += f.stat().st_size if f.is_file() else 0
    return total


def wait_until(proc, what, ready, timeout=180.0):
    """Poll until ``ready()``; fail if the run ends first (it never reached ``what``)."""
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        if ready():
            return
        if proc.poll() is not None:
            out, err = proc.communicate()
            pytest.fail(f"finished (rc {proc.returncode}) before {what}: {err}")
        time.sleep(0.002)
    proc.kill()
    pytest.fail(f"timed out waiting for {what}")


# -- 1. validation: every output format refuses what the USD cache refuses --

def overflow_rig(tmp_path):
    """Every input within float32 range, but a point at y = 1e38 moved by 3e38: skinned points
    overflow to infinity."""
    path = usda(tmp_path)
    text = path.read_text()
    for old, new in (("(1,2,0), (0,2,0)]", "(1,2,0), (0,1e38,0)]"),
                     ("float3[] translations = [(0,0,0), (0,1,0)]",
                      "float3[] translations = [(0,0,0), (0,3e38,0)]")):
        assert old in text
        text = text.replace(old, new)
    path.write_text(text)
    return path


def test_non_finite_results_refused_in_every_format(tmp_path):
    src = overflow_rig(tmp_path)
    lines = []
    for out in ("o.usda", "o.npz", "f_{:03d}.obj", "f_{:03d}.ply"):
        # (USD velocities would stop at their own check of the key poses first)
        rc, _, err = run("skin", src, "--out", tmp_path / out, "--no-velocities")
        assert_clean_error(rc, err, "rig.usda")
        lines.append(err.strip().splitlines()[-1])
    assert len(set(lines)) == 1, lines  # one validation, one message
    assert "nan or infinite" in lines[0].lower() or "float32" in lines[0], lines[0]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["rig.usda"]  # nothing written
    rc, out, err = run("info", src)
    assert rc == 0, err
    assert "problems: none" not in out
    assert lines[0].split("error: ", 1)[1] in out


def test_info_reports_no_problem_for_a_good_rig(tmp_path):
    rc, out, err = run("info", usda(tmp_path))
    assert rc == 0, err
    assert "problems: none" in out


# -- 2. interrupts --

@pytest.mark.parametrize("sig,code", [(signal.SIGINT, 130), (signal.SIGTERM, 143)])
@pytest.mark.parametrize("out,asset,extra", [
    ("x.usdc", HUMANOID, ["--no-velocities", "--chunk", "64"]),
    ("x.npz", HUMANOID, ["--chunk", "64"]),
    ("f_{:05d}.obj", TWIST, ["--chunk", "16"]),
])
def test_signal_mid_write_leaves_nothing(tmp_path, sig, code, out, asset, extra):
    """A signal once the output is claimed (its temporary file beside it) leaves nothing behind:
    no output, no temporary file, no partial set of frames. Streamed outputs (a USD cache,
    per-frame files) get it once bytes are in their temporary files; an ``.npz``, written only
    when every frame is skinned, gets it while its frames are skinned (the whole run takes
    ~0.3 s from there on a quiet machine: the signal is sent within milliseconds)."""
    folder = tmp_path / "out"
    folder.mkdir()
    proc = start("skin", asset, "--out", folder / out, "--frames", "0:4000", "--hold", *extra)
    if out.endswith(".npz"):
        wait_until(proc, "skinning into a claimed .npz", lambda: temp_bytes(folder) == 0)
    else:
        wait_until(proc, "writing", lambda: (temp_bytes(folder) or 0) > 0)
    proc.send_signal(sig)
    stdout, stderr = proc.communicate(timeout=120)
    assert proc.returncode == code, stderr
    assert stderr.strip().splitlines() == ["dqskin: interrupted"], stderr
    assert list(folder.iterdir()) == []  # no temporary file, no output, no partial set


def handlers_installed(pid):
    """Whether the process catches SIGTERM (only dqskin.cli.main's handler does)."""
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("SigCgt:"):
            return bool(int(line.split()[1], 16) >> (signal.SIGTERM - 1) & 1)
    return False


@pytest.mark.skipif(not Path("/proc/self/status").is_file(), reason="needs Linux /proc")
@pytest.mark.parametrize("delay", [0.0, 0.05, 0.2, 0.5, 1.0])
def test_ctrl_c_during_start_up(tmp_path, delay):
    """Ctrl-C at any moment once dqskin.cli.main runs (its imports, Warp's init, loading the
    asset, checking it): 130, one line, nothing written."""
    # 19,201 distinct poses (samples past the animation's end cost little to write): two to
    # three seconds of work on a quiet machine, so that the longest delay still lands before the end
    proc = start("skin", HUMANOID, "--out", tmp_path / "x.usdc", "--frames", "0:48:0.0025",
                 "--no-velocities", "--no-clips")
    end = time.monotonic() + 120
    while not handlers_installed(proc.pid):
        assert proc.poll() is None and time.monotonic() < end, proc.communicate()
        time.sleep(0.002)
    time.sleep(delay)
    proc.send_signal(signal.SIGINT)
    stdout, stderr = proc.communicate(timeout=120)
    assert proc.returncode == 130, stderr
    assert stderr.strip().splitlines() == ["dqskin: interrupted"], stderr
    assert list(tmp_path.iterdir()) == []


def test_ctrl_c_while_the_package_imports(tmp_path):
    """dqskin/__init__.py imports lazily, so the handlers are installed before Warp and USD load
    (they take ~2 s): a Ctrl-C then is a clean 130, not a traceback or a run that goes on."""
    proc = start("skin", HUMANOID, "--out", tmp_path / "x.usdc", "--frames", "0:4000",
                 "--hold", "--no-velocities")
    time.sleep(0.3)
    proc.send_signal(signal.SIGINT)
    stdout, stderr = proc.communicate(timeout=120)
    assert proc.returncode == 130, stderr
    assert stderr.strip().splitlines() == ["dqskin: interrupted"], stderr


def test_entry_point_ends_the_process_after_exit_handlers_and_flushed_output(tmp_path):
    """The console script's ``main()`` ends the process itself (skipping the interpreter's
    finalization): it does not return, exit handlers still run after everything the command
    printed (stdout block-buffered: a file or pipe, no ``PYTHONUNBUFFERED``), the command's exit
    status is the process's, and output that cannot be written makes a success exit 120 with a
    message, as Python's own exit does."""
    script = ("import atexit, sys\n"
              "atexit.register(lambda: print('handler ran'))\n"
              "from dqskin.cli import main\n"
              "main()\n"
              "print('main returned')\n")
    env = {k: v for k, v in os.environ.items() if k != "PYTHONUNBUFFERED"}
    out = tmp_path / "x.npz"
    for args, code in (([HUMANOID, "--out", out, "--frames", "0:3"], 0),
                       ([tmp_path / "missing.usda", "--out", out], 2)):
        proc = subprocess.run([sys.executable, "-c", script, "skin", *map(str, args)],
                              capture_output=True, text=True, timeout=300, env=env)
        assert proc.returncode == code, proc.stderr
        lines = proc.stdout.splitlines()
        assert lines[-1] == "handler ran" and "main returned" not in lines, proc.stdout
        assert (lines[0].startswith(f"wrote {out}") if code == 0 else len(lines) == 1)
    assert out.is_file()
    if os.path.exists("/dev/full"):  # Linux: every write fails with ENOSPC
        with open("/dev/full", "w") as full:
            proc = subprocess.run([sys.executable, "-c", script, "skin", str(HUMANOID), "--out",
                                   str(tmp_path / "y.npz"), "--frames", "0:3"],
                                  stdout=full, stderr=subprocess.PIPE, text=True, timeout=300,
                                  env=env)
        assert proc.returncode == 120, proc.stderr
        assert "dqskin: error: writing" in proc.stderr and "Traceback" not in proc.stderr


def test_a_reader_that_goes_away_ends_the_command_silently(tmp_path):
    """``dqskin info X | head``: when the reader of stdout has gone, the command ends as a tool
    ended by SIGPIPE (status 141) without a message or traceback, whether the pipe breaks while
    it prints (output beyond the stream's buffer) or at its final flush."""
    big = tmp_path / "many.usda"  # an info of more than the 8 KiB a pipe's stream buffers
    big.write_text("#usda 1.0\n" + "".join(
        f'def "C{i:03d}" (references = @{HUMANOID}@) {{}}\n' for i in range(60)))
    for src in (big, HUMANOID):
        proc = subprocess.Popen([sys.executable, "-m", "dqskin.cli", "info", str(src)],
                                stdout=subprocess.PIPE, stderr=subprocess.PIPE)
        proc.stdout.close()  # the reader goes away before anything is written
        stderr = proc.stderr.read().decode()
        assert proc.wait(timeout=300) == 128 + signal.SIGPIPE, stderr
        assert stderr == "", stderr


def test_system_errors_name_their_file_in_one_line(monkeypatch, capsys):
    """An OSError from the system reads "FILE: reason" (not Python's "[Errno 13] reason:
    'FILE'"); a rename names both files; dqskin's own refusal names the flag."""
    from dqskin import cli
    from dqskin.errors import output_exists
    for exc, said in ((PermissionError(13, "Permission denied", "/x/shot.clips"),
                       "/x/shot.clips: Permission denied"),
                      (OSError(18, "Invalid cross-device link", "/a/t", None, "/b/t"),
                       "/a/t -> /b/t: Invalid cross-device link"),
                      (output_exists("/x/shot.usd"),
                       "/x/shot.usd: exists (use --force to overwrite)")):
        def fail(args, exc=exc):
            raise exc
        monkeypatch.setattr(cli, "cmd_info", fail)
        assert cli.main(["info", str(HUMANOID)]) == 2
        assert capsys.readouterr().err.strip() == f"dqskin: error: {said}"


def test_a_broken_pipe_elsewhere_is_an_error_and_python_callers_keep_their_stdout(
        tmp_path, monkeypatch, capsys):
    """A broken pipe that is not stdout's (a socket, a child process), stdout being a pipe with
    a reader or not, is an error like any other (one line, status 2); called from Python with a
    closed stdout, ``main`` returns 141 and leaves the caller's file descriptors alone."""
    from dqskin import cli

    def broken(args):
        raise BrokenPipeError(32, "Broken pipe")
    monkeypatch.setattr(cli, "cmd_info", broken)
    assert cli.main(["info", str(HUMANOID)]) == 2  # stdout: pytest's capture (not a pipe)
    assert capsys.readouterr().err.strip() == "dqskin: error: Broken pipe"
    read, write = os.pipe()  # a pipe with its reader
    with open(write, "w") as pipe, open(read):
        monkeypatch.setattr(sys, "stdout", pipe)
        assert cli.main(["info", str(HUMANOID)]) == 2
    monkeypatch.undo()
    assert capsys.readouterr().err.strip() == "dqskin: error: Broken pipe"
    read, write = os.pipe()
    os.close(read)  # a pipe without one: the reader went away
    pipe = open(write, "w", buffering=1)
    try:
        before = os.fstat(pipe.fileno())
        monkeypatch.setattr(sys, "stdout", pipe)
        assert cli.main(["info", str(HUMANOID)]) == 128 + signal.SIGPIPE
        after = os.fstat(pipe.fileno())
        monkeypatch.undo()
    finally:
        with contextlib.suppress(BrokenPipeError):
            pipe.close()
    assert (after.st_ino, after.st_dev) == (before.st_ino, before.st_dev)


# -- 3. concurrent writers --

@pytest.mark.parametrize("out,last", [("same.npz", 1500), ("same.usdc", 300),
                                      ("f_{:04d}.ply", 300)])
def test_concurrent_runs_to_one_output(tmp_path, out, last):
    """Without --force exactly one of two simultaneous runs wins, whichever finishes first; the
    other fails with one line and its temporary files are gone. (Long enough clips that the two
    runs overlap.)"""
    args = ["skin", HUMANOID, "--out", tmp_path / out, "--frames", f"0:{last}", "--hold",
            "--no-velocities"]
    procs = [start(*args) for _ in range(2)]
    results = [(p.wait(timeout=300), *p.communicate()) for p in procs]
    codes = sorted(r[0] for r in results)
    assert codes == [0, 2], results
    loser = next(r for r in results if r[0] == 2)
    assert_clean_error(loser[0], loser[2], "exists")
    assert temp_files(tmp_path) == []
    if out.endswith(".npz"):
        assert np.load(tmp_path / out)["points_0"].shape[0] == last + 1
    elif out.endswith(".ply"):
        assert len(list(tmp_path.glob("f_*.ply"))) == last + 1


def test_concurrent_runs_with_force_last_writer_wins(tmp_path):
    out = tmp_path / "same.usdc"
    args = ["skin", HUMANOID, "--out", out, "--frames", "0:60", "--hold", "--no-velocities",
            "--force"]
    procs = [start(*args) for _ in range(2)]
    for p in procs:
        assert p.wait(timeout=300) == 0, p.communicate()[1]
    from pxr import Usd
    stage = Usd.Stage.Open(str(out))
    assert stage.GetStartTimeCode() == 0 and stage.GetEndTimeCode() == 60
    assert temp_files(tmp_path) == []


# -- 4. a per-frame name without {} -------------------------------------------------------------

def test_name_without_field_needs_one_frame(tmp_path):
    src = usda(tmp_path)
    rc, _, err = run("skin", src, "--out", tmp_path / "x.obj")
    assert_clean_error(rc, err, "{}", "3 frames")
    assert not (tmp_path / "x.obj").exists()
    (tmp_path / "x.obj").write_text("precious")
    rc, _, err = run("skin", src, "--out", tmp_path / "x.obj", "--force")
    assert_clean_error(rc, err, "{}")
    assert (tmp_path / "x.obj").read_text() == "precious"
    rc, out, err = run("skin", src, "--out", tmp_path / "y.obj", "--frames", "2")
    assert rc == 0, err
    assert "wrote 1 file" in out
    assert [p.name for p in sorted(tmp_path.glob("*.obj"))] == ["x.obj", "y.obj"]


# -- 5. per-frame files: faces, normals, UVs ----------------------------------------------------

POINTS_RIG = dict(WEIGHTS="[1, 0, 0.5, 0.5, 1, 0, 1, 0]")


def points_rig(tmp_path):
    """The test rig with its mesh as a UsdGeom.Points prim (no faces)."""
    path = usda(tmp_path, "points.usda", **POINTS_RIG)
    text = path.read_text().replace('def Mesh "Mesh"', 'def Points "Mesh"')
    text = text.replace("int[] faceVertexCounts = [3, 3]\n", "")
    text = text.replace("int[] faceVertexIndices = [0, 1, 2, 0, 2, 3]\n", "")
    path.write_text(text)
    return path


@pytest.mark.parametrize("suffix", [".obj", ".stl", ".off", ".glb"])
def test_only_meshes_without_faces_is_an_error_where_faces_are_needed(tmp_path, suffix):
    rc, _, err = run("skin", points_rig(tmp_path), "--out", tmp_path / f"f_{{:03d}}{suffix}")
    assert_clean_error(rc, err, "/Root/Mesh", "no faces")
    assert not list(tmp_path.glob("f_*"))


def test_mesh_without_faces_kept_as_points_in_ply(tmp_path):
    import trimesh
    rc, _, err = run("skin", points_rig(tmp_path), "--out", tmp_path / "f_{:03d}.ply")
    assert rc == 0, err
    m = trimesh.load(tmp_path / "f_002.ply", process=False)
    assert len(m.vertices) == 4


def _humanoid_reference(frame):
    """Per triangle corner of the humanoid (meshes in order): skinned position, unit skinned
    normal and authored UV (faceVarying ``st``, fan-triangulated here independently)."""
    from pxr import Usd, UsdGeom

    import dqskin
    scene = dqskin.load(HUMANOID)
    res = scene.skin([float(frame)], normals=True)
    stage = Usd.Stage.Open(str(HUMANOID))
    pos, nrm, uv = [], [], []
    for m in scene.meshes:
        mesh = UsdGeom.Mesh(stage.GetPrimAtPath(m.name))
        counts = np.asarray(mesh.GetFaceVertexCountsAttr().Get())
        fvi = np.asarray(mesh.GetFaceVertexIndicesAttr().Get())
        st = UsdGeom.PrimvarsAPI(mesh).GetPrimvar("st")
        assert st.GetInterpolation() == "faceVarying"
        st = np.asarray(st.ComputeFlattened(), np.float64)
        corners, start = [], 0
        for c in counts:
            corners += [(start, start + k, start + k + 1) for k in range(1, c - 1)]
            start += c
        corners = np.asarray(corners)
        p = res.points[m.name][0]
        n = res.normals[m.name][0]
        n = n / np.linalg.norm(n, axis=1, keepdims=True)
        assert m.normal_vertex is None  # vertex-interpolated normals
        pos.append(p[fvi[corners]])
        nrm.append(n[fvi[corners]])
        uv.append(st[corners])
    return np.concatenate(pos), np.concatenate(nrm), np.concatenate(uv)


def test_ply_and_glb_frames_keep_normals_and_face_varying_uvs(tmp_path):
    import trimesh
    rc, out, err = run("skin", HUMANOID, "--out", tmp_path / "f_{:02d}.ply", "--frames", "5")
    assert rc == 0, err
    assert "normals, UVs" in out
    rc, _, err = run("skin", HUMANOID, "--out", tmp_path / "f_{:02d}.glb", "--frames", "5")
    assert rc == 0, err
    pos, nrm, uv = _humanoid_reference(5)
    ply = trimesh.load(tmp_path / "f_05.ply", process=False)
    # a .glb frame holds one glTF mesh per source mesh, named after it, on a node taking it to
    # glTF's metres (the humanoid: 0.01 m per unit)
    frame = trimesh.load(tmp_path / "f_05.glb", process=False)
    import dqskin
    glb = trimesh.util.concatenate([frame.geometry[m.name].copy().apply_transform(
        frame.graph[m.name][0]) for m in dqskin.load(HUMANOID).meshes])
    for m, scale in ((ply, 1.0), (glb, 0.01)):
        f = np.asarray(m.faces)
        assert f.shape[0] == pos.shape[0]
        np.testing.assert_allclose(np.asarray(m.vertices)[f], scale * pos, atol=1e-5 * scale)
        np.testing.assert_allclose(np.asarray(m.visual.uv)[f], uv, atol=1e-6)
    np.testing.assert_allclose(np.asarray(ply.vertex_normals)[np.asarray(ply.faces)], nrm,
                               atol=1e-5)
    # the UV seam splits vertices: more file vertices than points, far fewer than corners
    points = sum(len(m.points) for m in dqskin.load(HUMANOID).meshes)
    assert points < len(ply.vertices) < 3 * pos.shape[0] // 2


FACE_VARYING = """\
        normal3f[] normals = [(0,0,2), (0,0,1), (0,1,1), (0,0,1), (1,0,1), (0,0,3)] (
            interpolation = "faceVarying"
        )
        texCoord2f[] primvars:st = [(0,0), (1,0), (1,1), (0.5,0), (1,1), (0,1)] (
            interpolation = "faceVarying"
        )
        rel skel:skeleton = </Root/Skel>
"""


def test_face_varying_normals_and_uvs_split_vertices(tmp_path):
    """Corners of one point with different normals or UVs become separate file vertices; each
    corner keeps its own (normalized) normal and UV."""
    import trimesh
    src = usda(tmp_path)
    text = src.read_text()
    old = "        rel skel:skeleton = </Root/Skel>\n    }\n}"
    assert old in text
    src.write_text(text.replace(old, FACE_VARYING + "    }\n}"))
    rc, _, err = run("skin", src, "--out", tmp_path / "f_{}.ply", "--frames", "0")
    assert rc == 0, err
    m = trimesh.load(tmp_path / "f_0.ply", process=False)
    fvi = np.array([0, 1, 2, 0, 2, 3])
    rest = np.array([(0, 0, 0), (1, 0, 0), (1, 2, 0), (0, 2, 0)], float)
    normals = np.array([(0, 0, 2), (0, 0, 1), (0, 1, 1), (0, 0, 1), (1, 0, 1), (0, 0, 3)], float)
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    st = np.array([(0, 0), (1, 0), (1, 1), (0.5, 0), (1, 1), (0, 1)], float)
    corners = np.asarray(m.faces).ravel()
    assert len(m.vertices) == 6  # points 0 and 2 split (their corners differ), 1 and 3 not
    np.testing.assert_allclose(np.asarray(m.vertices)[corners], rest[fvi], atol=1e-6)
    np.testing.assert_allclose(np.asarray(m.vertex_normals)[corners], normals, atol=1e-6)
    np.testing.assert_allclose(np.asarray(m.visual.uv)[corners], st, atol=1e-6)


def test_obj_frames_have_normals_and_uvs_and_no_material_file(tmp_path):
    rc, _, err = run("skin", HUMANOID, "--out", tmp_path / "f_{:02d}.obj", "--frames", "0:2")
    assert rc == 0, err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["f_00.obj", "f_01.obj", "f_02.obj"]
    text = (tmp_path / "f_01.obj").read_text()
    assert "\nvn " in text and "\nvt " in text and "mtllib" not in text
    rc, _, err = run("skin", HUMANOID, "--out", tmp_path / "n_{:02d}.obj", "--frames", "0",
                     "--no-normals")
    assert rc == 0, err
    text = (tmp_path / "n_00.obj").read_text()
    assert "\nvn " not in text and "\nvt " in text


def test_gltf_uvs_keep_their_origin(shared_assets, tmp_path):
    """glTF stores UVs top-left; a .glb frame written from it holds the same TEXCOORD_0."""
    import pygltflib

    import dqskin
    src = shared_assets / "khronos-gltf" / "CesiumMan" / "CesiumMan.glb"
    rc, _, err = run("skin", src, "--out", tmp_path / "f_{:03d}.glb", "--frames", "1")
    assert rc == 0, err
    g = pygltflib.GLTF2().load(str(tmp_path / "f_001.glb"))
    prim = g.meshes[0].primitives[0]
    acc = g.accessors[prim.attributes.TEXCOORD_0]
    view = g.bufferViews[acc.bufferView]
    blob = g.binary_blob()
    raw = np.frombuffer(blob, np.float32, acc.count * 2,
                        (view.byteOffset or 0) + (acc.byteOffset or 0)).reshape(-1, 2)
    want = np.concatenate([m.uvs for m in dqskin.load(src).meshes])
    np.testing.assert_allclose(raw, want, atol=1e-6)


# -- 6. messages --

def test_input_that_is_not_a_regular_file(tmp_path):
    fifo = tmp_path / "pipe.usda"
    os.mkfifo(fifo)
    folder = tmp_path / "folder.usda"
    folder.mkdir()
    for src in (folder, fifo, "/dev/null"):
        for cmd in (["skin", src, "--out", tmp_path / "o.npz"], ["info", src]):
            rc, _, err = run(*cmd)
            assert_clean_error(rc, err, "not a regular file")
    rc, _, err = run("skin", tmp_path / "nope.usda", "--out", tmp_path / "o.npz")
    assert_clean_error(rc, err, "no such file")


def test_out_under_a_file(tmp_path):
    src = usda(tmp_path)
    for out in ("o.usdc", "o.npz", "f_{:02d}.obj"):
        rc, _, err = run("skin", src, "--out", src / out)
        assert_clean_error(rc, err, "not a directory", str(src))
        assert "Errno" not in err


def test_write_error_names_the_output_not_the_temporary_file(tmp_path):
    """A name of 254 characters is legal, its temporary folder (``.STEM.XXXXXXXX``) is not."""
    src = usda(tmp_path)
    for suffix in (".npz", ".usda"):
        out = tmp_path / ("n" * (254 - len(suffix)) + suffix)
        rc, _, err = run("skin", src, "--out", out)
        assert_clean_error(rc, err, out.name)
        line = err.strip().splitlines()[-1]
        assert f"/.{out.stem}." not in line, line
        assert sorted(p.name for p in tmp_path.iterdir()) == ["rig.usda"]


def test_counts_in_the_summary(tmp_path):
    rc, out, err = run("skin", usda(tmp_path), "--out", tmp_path / "o.npz")
    assert rc == 0, err
    assert "1 mesh × 3 frames" in out and "meshs" not in out


# -- 7. noise --

def test_successful_run_prints_only_its_own_line(tmp_path):
    rc, out, err = run("skin", TWIST, "--out", tmp_path / "t.usdc", "--frames", "0:24")
    assert rc == 0, err
    assert err == "", err
    assert out.count("\n") == 1 and out.startswith("wrote "), out
    assert "Warp" not in out + err and "Warning" not in out + err


@pytest.mark.parametrize("where", ["before", "after"])
def test_verbose_shows_library_messages(tmp_path, where):
    args = ["skin", TWIST, "--out", tmp_path / "t.npz", "--frames", "0:2"]
    args = ["--verbose", *args] if where == "before" else [*args, "--verbose"]
    rc, out, err = run(*args)
    assert rc == 0, err
    assert "Warp" in out + err  # Warp's banner (and, without CUDA, its driver notice)
