"""Hostile input on clip bakes, ``flatten`` and ``--resume`` (issue 30): every file they trust is
verified, ``--force`` replaces only what dqskin made, locks cover readers, names USD cannot
resolve are refused before the bake, and every refusal is one line naming the file.

The reference for every "same animation" check is a single-layer cache of the same frames, read
through USD; damaged or swapped files are made by hand.
"""

import os
import shutil
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest
from pxr import Usd

from dqskin import bake
from dqskin.baking import BakeSettings
from dqskin.errors import DqskinError, InputError, LimitError
from dqskin.readers import load
from dqskin.writers.clip_lock import LOCK_FILE, bake_lock, reading_lock
from dqskin.writers.usd_clips import clips_folder, flatten, read_json

sys.path.insert(0, str(Path(__file__).resolve().parent))
from test_clips import HUMANOID, assert_same_animation  # noqa: E402

ARGS = dict(chunk=4, clips=True, normals=False, velocities=False)


@pytest.fixture(scope="module")
def shot(tmp_path_factory):
    """A finished clip bake of the humanoid's first 12 frames (three clips) and a single-layer
    cache of the same frames; each test works on its own copy."""
    tmp = tmp_path_factory.mktemp("shot")
    scene = load(HUMANOID)
    out, single = tmp / "shot.usd", tmp / "single.usdc"
    bake(scene, out, scene.times[:12], **ARGS)
    bake(scene, single, scene.times[:12], clips=False, normals=False, velocities=False)
    return dict(out=out, single=single, times=scene.times[:12],
                names=[m.name for m in scene.meshes])


def copy_of(shot, tmp_path):
    shutil.copy2(shot["out"], tmp_path / "shot.usd")
    shutil.copytree(clips_folder(shot["out"]), clips_folder(tmp_path / "shot.usd"))
    return tmp_path / "shot.usd"


def same_as_single(shot, path):
    return assert_same_animation(Usd.Stage.Open(str(shot["single"])), Usd.Stage.Open(str(path)),
                                 shot["names"], shot["times"]) > 0


@pytest.mark.parametrize("damage", ["deleted", "emptied", "folder"])
def test_flatten_refuses_a_manifest_that_is_not_the_bakes(shot, tmp_path, damage):
    """A deleted, emptied (``#usda 1.0``) or folder ``manifest.usda``: USD reads no animation
    through it, and flatten wrote a cache without one (37,604 of 37,889 values differed)."""
    out = copy_of(shot, tmp_path)
    manifest = clips_folder(out) / "manifest.usda"
    manifest.unlink()
    if damage == "emptied":
        manifest.write_text("#usda 1.0\n")
    elif damage == "folder":
        manifest.mkdir()
    # (a folder is refused before USD opens anything: every layer must be a regular file)
    why = ("layer named by .*shot.usd: a folder, not a regular file" if damage == "folder" else
           "missing, damaged or not the manifest shot.usd was written with")
    with pytest.raises(InputError, match=r"shot.clips/manifest.usda: " + why):
        flatten(out, tmp_path / "flat.usdc")
    assert not (tmp_path / "flat.usdc").exists()


@pytest.mark.parametrize("damage", ["record deleted", "record truncated", "swapped",
                                    "swapped with records", "layer damaged, record deleted"])
def test_flatten_verifies_every_layer_against_the_top_levels_list(shot, tmp_path, damage):
    """The top level lists each clip layer's size and checksum: a record deleted or truncated
    changes nothing (the layers are still verified and the result is exact); a chunk swapped
    with its neighbour, with or without its record, or a damaged chunk without a record, is
    refused (flatten wrote wrong data)."""
    out = copy_of(shot, tmp_path)
    folder = clips_folder(out)
    a, b = folder / "chunk_00001.usdc", folder / "chunk_00002.usdc"
    if damage == "record deleted":
        a.with_suffix(".json").unlink()
    elif damage == "record truncated":
        a.with_suffix(".json").write_text(a.with_suffix(".json").read_text()[:20])
    elif damage.startswith("swapped"):
        pairs = [(a, b)] + ([(a.with_suffix(".json"), b.with_suffix(".json"))]
                            if "records" in damage else [])
        for x, y in pairs:
            x.rename(folder / "tmp")
            y.rename(x)
            (folder / "tmp").rename(y)
    else:
        data = bytearray(a.read_bytes())
        data[len(data) // 2] ^= 0xFF
        a.write_bytes(bytes(data))
        a.with_suffix(".json").unlink()
    flat = tmp_path / "flat.usdc"
    if damage.startswith("record"):
        assert same_as_single(shot, flatten(out, flat))
        return
    with pytest.raises(InputError, match=r"chunk_0000[12].usdc: missing, damaged or not the clip "
                                         "layer shot.usd was written with"):
        flatten(out, flat)
    assert not flat.exists()


def test_flatten_of_an_older_cache_needs_every_record_in_a_dqskin_folder(shot, tmp_path):
    """A top level without the list (written before it existed): in a folder of a dqskin plan,
    a clip without its record is refused (it was taken as another tool's clip, unchecked)."""
    from pxr import Sdf
    out = copy_of(shot, tmp_path)
    layer = Sdf.Layer.FindOrOpen(str(out))
    layer.customLayerData = {}
    layer.Save()
    (clips_folder(out) / "chunk_00001.json").unlink()
    with pytest.raises(InputError, match="chunk_00001.usdc: its dqskin record chunk_00001.json "
                                         "is missing"):
        flatten(out, tmp_path / "flat.usdc")


def test_flatten_and_a_bake_of_one_output_exclude_each_other(shot, tmp_path):
    """A bake holds its clip folder while it runs, and flatten holds it while it reads: a flatten
    during a (``--force``) bake is refused, and so is a bake during a flatten (flatten wrote
    2,496 of 4,701 frames while a --force bake replaced the clips). Several flattens may read
    at once; the lock file goes with the last."""
    out = copy_of(shot, tmp_path)
    folder = clips_folder(out)
    with bake_lock(out):
        with pytest.raises(FileExistsError, match=r"shot.usd: a dqskin bake \(pid \d+\) is "
                                                  "writing its clips"):
            flatten(out, tmp_path / "flat.usdc")
    assert not (tmp_path / "flat.usdc").exists()
    scene = load(HUMANOID)
    with reading_lock(folder, out), reading_lock(folder, out):
        with pytest.raises(FileExistsError, match=r"shot.usd: another dqskin run .*reading its "
                                                  "clips"):
            bake(scene, out, shot["times"], **ARGS, force=True)
        assert same_as_single(shot, flatten(out, tmp_path / "flat.usdc"))
    assert not (folder / LOCK_FILE).exists()
    bake(scene, out, shot["times"], **ARGS, force=True)
    assert not (folder / LOCK_FILE).exists()


@pytest.mark.parametrize("name", ["back\\slash.usda", "new\nline.usd", "tab\there.usdc"])
def test_clip_names_usd_cannot_resolve_are_refused_before_the_bake(tmp_path, name, capsys):
    """USD reads a backslash in a clip path as a folder separator (the cache pointed at nothing)
    and refuses control characters (a traceback after the whole bake): refused up front, one
    line, nothing written."""
    out = tmp_path / name
    with pytest.raises(InputError, match="USD cannot name value clips there") as err:
        bake(HUMANOID, out, **ARGS)
    assert "\n" not in str(err.value)
    from dqskin.cli import main
    assert main(["skin", str(HUMANOID), "--out", str(out), "--clips"]) == 2
    said = capsys.readouterr().err
    assert len(said.splitlines()) == 1 and "USD cannot name value clips there" in said, said
    assert sorted(os.listdir(tmp_path)) == []
    bake(HUMANOID, out, load(HUMANOID).times[:3], clips=False)  # one layer takes any name
    assert out.is_file()


@pytest.mark.parametrize("foreign", ["plan.json", "manifest.usda", "chunk_00001.usdc",
                                     "chunk_00001.json"])
def test_force_replaces_only_what_dqskin_made(tmp_path, foreign):
    """Another tool's file at a name a clip bake writes: ``--force`` refuses it, naming it, and
    leaves every file as it was (it deleted and overwrote them); without ``--force`` the refusal
    does not call them an unfinished clip bake."""
    out = tmp_path / "shot.usd"
    folder = clips_folder(out)
    folder.mkdir()
    theirs = {foreign: b'{"theirs": true}\n', "notes.txt": b"mine"}
    for name, data in theirs.items():
        (folder / name).write_bytes(data)
    scene = load(HUMANOID)
    for extra in ({"force": True}, {}, {"resume": True}):
        with pytest.raises((InputError, FileExistsError)) as err:
            bake(scene, out, scene.times[:12], **ARGS, **extra)
        assert f"{foreign}: not made by dqskin" in str(err.value), str(err.value)
        assert "unfinished" not in str(err.value)
        assert {p.name: p.read_bytes() for p in folder.iterdir()} == theirs
    assert not out.exists()


def test_force_over_a_dqskin_bake_keeps_other_files(shot, tmp_path):
    """Over dqskin's own bake ``--force`` replaces its files; a file of the user's at a name the
    new bake does not write stays."""
    out = copy_of(shot, tmp_path)
    folder = clips_folder(out)
    (folder / "chunk_00007.usdc").write_bytes(b"someone else's")
    scene = load(HUMANOID)
    bake(scene, out, shot["times"][:8], method="lbs", **ARGS, force=True)
    assert sorted(p.name for p in folder.glob("chunk_*")) == [
        "chunk_00000.json", "chunk_00000.usdc", "chunk_00001.json", "chunk_00001.usdc",
        "chunk_00007.usdc"]
    assert (folder / "chunk_00007.usdc").read_bytes() == b"someone else's"


def test_two_single_layer_bakes_leave_no_folder_and_name_the_file(tmp_path):
    """Two single-layer bakes to one ``same.usdc`` at once: one wins, the other's refusal names
    ``same.usdc`` (it named a ``same.clips`` lock folder), and no ``same.clips/`` is left."""
    scene = load(HUMANOID)
    out = tmp_path / "same.usdc"
    barrier, outcome = threading.Barrier(2), []

    def run():
        barrier.wait()
        try:
            bake(scene, out, scene.times[:6], clips=False)
            outcome.append("ok")
        except FileExistsError as exc:
            outcome.append(str(exc))
    threads = [threading.Thread(target=run) for _ in range(2)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert sorted(outcome)[-1] == "ok" and len(outcome) == 2, outcome
    assert all(r == "ok" or r.startswith(f"{out}: exists") for r in outcome), outcome
    assert sorted(os.listdir(tmp_path)) == ["same.usdc"]


def test_resume_after_a_sublayer_changed_is_refused(tmp_path):
    """The input's animation is in a sublayer of the file given: ``--resume`` after that layer
    changed is refused, naming it (it kept the old clips and baked the rest from the edited
    layer: one cache, two animations)."""
    anim = tmp_path / "anim.usda"
    shutil.copy(HUMANOID, anim)
    root = tmp_path / "root.usda"
    head = HUMANOID.read_text().split("\n)\n", 1)[0]  # the layer metadata (time codes, axes)
    root.write_text(head.replace("(\n", '(\n    subLayers = [@./anim.usda@]\n', 1) + "\n)\n")
    out = tmp_path / "shot.usd"
    scene = load(root)
    times = scene.times[:12]
    bake(scene, out, times, **ARGS)
    out.unlink()  # unfinished, as after an interrupt
    (clips_folder(out) / "chunk_00002.usdc").unlink()
    text = anim.read_text()
    anim.write_text(text.replace("endTimeCode = 48", "endTimeCode = 48 "))  # edited
    with pytest.raises(InputError, match=rf"an earlier bake of this input before {anim} changed"):
        bake(root, out, times, **ARGS, resume=True)
    assert not out.exists()


def test_a_worker_reloads_the_asset_when_a_sublayer_changed(tmp_path):
    """A long-lived worker process keeps its loaded asset between tasks; an edit to a layer the
    asset reads (not the file named) makes it load the asset again (it kept baking the old
    one)."""
    import dqskin.distributed as dist
    anim = tmp_path / "anim.usda"
    shutil.copy(HUMANOID, anim)
    root = tmp_path / "root.usda"
    head = HUMANOID.read_text().split("\n)\n", 1)[0]
    root.write_text(head.replace("(\n", '(\n    subLayers = [@./anim.usda@]\n', 1) + "\n)\n")
    first = dist._worker_scene(str(root))
    assert dist._worker_scene(str(root)) is first
    anim.write_text(anim.read_text().replace("endTimeCode = 48", "endTimeCode = 48 "))
    assert dist._worker_scene(str(root)) is not first
    dist._scenes.clear()


def test_nested_json_is_one_line_not_a_recursion_error(tmp_path):
    """A ``plan.json`` or clip record nested 100,000 deep: a one-line refusal naming the file
    (a RecursionError traceback)."""
    deep = tmp_path / "plan.json"
    deep.write_text("[" * 100_000 + "]" * 100_000)
    with pytest.raises(InputError, match=r"plan.json: JSON nested too deeply"):
        read_json(deep)
    out = tmp_path / "shot.usd"
    scene = load(HUMANOID)
    bake(scene, out, scene.times[:8], **ARGS)
    out.unlink()
    folder = clips_folder(out)
    (folder / "chunk_00001.json").write_text("{" * 0 + "[" * 100_000 + "]" * 100_000)
    shutil.copy(deep, folder / "plan.json")
    proc = subprocess.run([sys.executable, "-m", "dqskin.cli", "skin", str(HUMANOID), "--out",
                           str(out), "--frames", "0:7", "--clips", "--chunk", "4", "--resume",
                           "--no-normals", "--no-velocities"],
                          capture_output=True, text=True, timeout=300)
    assert proc.returncode == 2 and len(proc.stderr.strip().splitlines()) == 1, proc.stderr
    assert "plan.json: JSON nested too deeply" in proc.stderr, proc.stderr
    assert "Recursion" not in proc.stderr


def test_a_dangling_lock_link_says_how_to_go_on(tmp_path):
    out = tmp_path / "shot.usd"
    clips_folder(out).mkdir()
    (clips_folder(out) / LOCK_FILE).symlink_to(tmp_path / "nowhere")
    with pytest.raises(FileExistsError, match=r"\.lock: a symbolic link where dqskin keeps the "
                                              r"lock .*remove the link, then rerun \(resume=True"):
        bake(HUMANOID, out, **ARGS)
    (clips_folder(out) / LOCK_FILE).unlink()
    bake(HUMANOID, out, load(HUMANOID).times[:4], **ARGS)


def test_an_interrupt_once_the_output_is_in_place_is_a_success(shot, tmp_path, monkeypatch,
                                                                capsys):
    """SIGTERM while flatten's finished output is being renamed into place (the last ~0.35 s):
    the complete output stays and the run succeeds (it exited 143 "interrupted" with the output
    in place); an interrupt before the commit leaves nothing."""
    from dqskin import cli
    from dqskin.errors import Interrupted
    from dqskin.files import atomic
    link = atomic._link_exclusive

    def interrupted_link(tmp, path):
        atomic.interrupt(Interrupted(15))  # as the CLI's handler does, inside the commit
        link(tmp, path)
    monkeypatch.setattr(atomic, "_link_exclusive", interrupted_link)
    flat = tmp_path / "flat.usdc"
    assert cli.main(["flatten", str(shot["out"]), "--out", str(flat)]) == 0
    assert f"wrote {flat}" in capsys.readouterr().out
    assert same_as_single(shot, flat)
    monkeypatch.undo()
    export = atomic.atomic_path.commit

    def interrupted_before(self, final=False):
        atomic.interrupt(Interrupted(15))

    monkeypatch.setattr(atomic.atomic_path, "commit", interrupted_before)
    other = tmp_path / "other.usdc"
    try:
        assert cli.main(["flatten", str(shot["out"]), "--out", str(other)]) == 143
    finally:
        atomic.reset_interrupt()  # (recorded for this process, as the CLI's handler does)
    assert not other.exists() and export is not None


def test_flatten_of_a_name_with_brackets(shot, tmp_path):
    """``br[1].usda`` is a file, not a package path (errors named ``…/br``)."""
    src = tmp_path / "br[1].usda"
    bake(load(HUMANOID), src, shot["times"][:4], clips=False, normals=False, velocities=False)
    out = tmp_path / "flat.usda"
    out.write_text("#usda 1.0\n")
    assert flatten(src, out, overwrite=True) == out
    with pytest.raises(InputError, match=r"br\[1\].usda: refusing to overwrite an input"):
        flatten(src, src, overwrite=True)


def test_resume_refusals_name_options_as_typed(tmp_path, capsys):
    from dqskin.cli import main
    out = tmp_path / "shot.usd"
    base = ["skin", str(HUMANOID), "--out", str(out), "--frames", "0:7", "--clips", "--chunk",
            "4", "--no-normals"]
    assert main(base) == 0
    out.unlink()
    assert main(base + ["--resume", "--method", "dqs"]) == 2
    err = capsys.readouterr().err
    assert "with no --method (now --method dqs)" in err, err
    assert main(base + ["--resume", "--chunk", "2"]) == 2
    assert "with --chunk 4 (now --chunk 2)" in capsys.readouterr().err


# --- Dask ------------------------------------------------------------------------------------

@pytest.mark.parametrize("address", ["ucx://127.0.0.1:8786", "tls://127.0.0.1:8786",
                                     "inproc://x", "127.0.0.1:8786", "tcp://host"])
def test_scheduler_addresses_other_than_tcp_are_refused(address):
    with pytest.raises(InputError, match="expected tcp://HOST:PORT"):
        BakeSettings(scheduler=address)


def test_workers_beyond_the_limit_are_refused_before_anything_starts(monkeypatch):
    from dqskin.forkserver import max_workers
    with pytest.raises(LimitError, match="more than the limit of .* DQSKIN_MAX_WORKERS"):
        BakeSettings(workers=99999999999999999999)
    monkeypatch.setenv("DQSKIN_MAX_WORKERS", "3")
    assert max_workers() == 3
    BakeSettings(workers=3)
    with pytest.raises(LimitError, match="limit of 3 local"):
        BakeSettings(workers=4)


def test_a_scheduler_port_that_never_answers_is_bounded(tmp_path, monkeypatch):
    """Something accepts the connection and never speaks: refused after ``CONNECT_SECONDS``
    (Dask's own connect waited for ever), before anything is written."""
    import dqskin.distributed as dist
    server = socket.socket()
    server.bind(("127.0.0.1", 0))
    server.listen(4)
    held = []
    threading.Thread(target=lambda: held.append(server.accept()), daemon=True).start()
    monkeypatch.setattr(dist, "CONNECT_SECONDS", 1)
    address = "tcp://127.0.0.1:%d" % server.getsockname()[1]
    t0 = time.monotonic()
    try:
        with pytest.raises(DqskinError, match="no answer within 1 s"):
            bake(HUMANOID, tmp_path / "shot.usd", scheduler=address)
    finally:
        server.close()
    assert time.monotonic() - t0 < 30
    assert not (tmp_path / "shot.usd").exists() and not clips_folder(tmp_path / "shot.usd").exists()


def test_a_stopped_worker_does_not_hang_the_bake(tmp_path, monkeypatch):
    """One worker of ``--workers 2`` stops (SIGSTOP) in its first clip: the scheduler drops it
    after the worker TTL and its clips run on the other (it waited for ever), and the cache is
    exact."""
    import cloudpickle

    import dqskin.distributed as dist
    monkeypatch.setattr(dist, "WORKER_TTL", "3s")
    marker = tmp_path / "stopped"
    plugin = dist._worker_plugin

    def stopping_plugin(own_cluster):
        inner = plugin(own_cluster)
        setup = type(inner).setup

        def stop_once(self, worker):
            setup(self, worker)
            from dqskin.writers.usd_clips import ClipLayer
            finish = ClipLayer.finish

            def finish_then_stop(layer, times):
                try:
                    os.close(os.open(marker, os.O_CREAT | os.O_EXCL | os.O_WRONLY))
                except FileExistsError:
                    return finish(layer, times)
                os.kill(os.getpid(), 19)  # SIGSTOP
                return finish(layer, times)
            ClipLayer.finish = finish_then_stop
        type(inner).setup = stop_once
        return inner
    cloudpickle.register_pickle_by_value(sys.modules[__name__])
    try:
        monkeypatch.setattr(dist, "_worker_plugin", stopping_plugin)
        scene = load(HUMANOID)
        out = tmp_path / "shot.usd"
        t0 = time.monotonic()
        bake(HUMANOID, out, scene.times[:24], chunk=3, workers=2, normals=False,
             velocities=False)
    finally:
        cloudpickle.unregister_pickle_by_value(sys.modules[__name__])
    assert marker.exists() and time.monotonic() - t0 < 120
    single = tmp_path / "single.usdc"
    bake(scene, single, scene.times[:24], clips=False, normals=False, velocities=False)
    names = [m.name for m in scene.meshes]
    assert assert_same_animation(Usd.Stage.Open(str(single)), Usd.Stage.Open(str(out)), names,
                                 np.asarray(scene.times[:24])) > 0


# --- full disk -------------------------------------------------------------------------------

def _unshare_works():
    try:
        return subprocess.run(["unshare", "-rm", "true"], capture_output=True,
                              timeout=30).returncode == 0
    except (OSError, subprocess.TimeoutExpired):
        return False


@pytest.mark.skipif(not _unshare_works(), reason="needs user namespaces (unshare -rm) to mount "
                    "a small tmpfs as a full disk")
@pytest.mark.parametrize("what", ["x.usda", "x.usdc", "x.usd --clips", "flatten", "x.npz",
                                  "f_{:04d}.obj"])
def test_a_full_disk_is_one_line_naming_the_file(shot, tmp_path, what):
    """A 256 KB tmpfs fills up: one line naming the output and "No space left on device" (a
    27,340-line error for .usda and flatten; the message without the file elsewhere)."""
    mount = tmp_path / "full"
    mount.mkdir()
    if what == "flatten":
        cmd = ["flatten", str(shot["single"]), "--out", f"{mount}/x.usda"]
        name = f"{mount}/x.usda"
    else:
        out, *extra = what.split()
        cmd = ["skin", str(HUMANOID), "--out", f"{mount}/{out}", *extra]
        name = f"{mount}/{out}" if not extra else str(mount)
        name = name.split("{")[0]
    script = ('mount -t tmpfs -o size=256k tmpfs "$1" && shift && "$@"')
    proc = subprocess.run(["unshare", "-rm", "sh", "-c", script, "sh", str(mount),
                           sys.executable, "-m", "dqskin.cli", *cmd],
                          capture_output=True, text=True, timeout=300)
    lines = proc.stderr.strip().splitlines()
    assert proc.returncode == 2 and len(lines) == 1, proc.stderr[:2000]
    assert name in lines[0] and "No space left on device" in lines[0], lines[0]
