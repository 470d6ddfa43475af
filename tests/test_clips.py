"""Value-clip caches (dqskin.writers.usd_clips), baked in this process.

What USD shows through ``Usd.Stage.Open`` is checked against two references: a float64 oracle
written from USD's own rule (linear interpolation between the bracketing samples, held outside
the range) applied to :meth:`Scene.skin`'s frames, and today's single-layer cache, which it must
equal exactly, sub-frames between two clips included. Pixar's own baked baseline checks the
rigid prims. Resume, interruption, flattening and refusals too.
"""

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from pxr import Sdf, Usd, UsdGeom, Vt

from dqskin import SkinOptions, bake
from dqskin.readers import load
from dqskin.writers.clip_lock import LOCK_FILE, bake_lock
from dqskin.writers.usd_clips import (
    chunk_bounds,
    clips_folder,
    flatten,
    verify_chunk,
)

HUMANOID = Path(__file__).resolve().parents[1] / "assets" / "humanoid.usda"
BAKE = "openusd/pxr/usd/usdSkel/testenv/testUsdSkelBakeSkinning"
ATTRS = ("points", "normals", "velocities", "extent")
CHUNK = 7


def probe_times(times, chunk):
    """Every frame; sub-frames inside each interval between two clips and inside clips;
    times before and after the range."""
    t = np.asarray(times, np.float64)
    probes = set(t.tolist()) | {t[0] - 1.5, t[-1] + 2.25}
    for lo, _ in chunk_bounds(len(t), chunk):
        for k in (lo - 1, lo):
            if 0 <= k < len(t) - 1:
                for a in (0.01, 0.25, 0.5, 0.99):
                    probes.add(float(t[k] + a * (t[k + 1] - t[k])))
    return sorted(probes)


def attribute(stage, name, what):
    prim = stage.GetPrimAtPath(name)
    if what == "normals" and UsdGeom.PrimvarsAPI(prim).HasPrimvar("normals"):
        return prim.GetAttribute("primvars:normals")
    return prim.GetAttribute(what)


def assert_same_animation(stage_a, stage_b, names, times):
    """Every attribute of ``ATTRS`` on every prim equal (bit for bit) in both stages at
    ``times``; returns how many values were compared."""
    n = 0
    for name in names:
        for what in ATTRS:
            a, b = attribute(stage_a, name, what), attribute(stage_b, name, what)
            if not a.HasAuthoredValue() and not a.GetTimeSamples():
                continue
            for t in times:
                va, vb = a.Get(t), b.Get(t)
                assert vb is not None, f"{name}.{what} at {t}: no value"
                np.testing.assert_array_equal(np.asarray(vb), np.asarray(va),
                                              err_msg=f"{name}.{what} at {t}")
                n += 1
    return n


def oracle(frames, times, t):
    """USD's value at ``t`` from samples ``frames`` (F, ...) at ``times``: linear between the
    bracketing samples, held outside (float64)."""
    k = int(np.searchsorted(times, t, side="right")) - 1
    if k < 0:
        return frames[0].astype(np.float64)
    if k >= len(times) - 1:
        return frames[-1].astype(np.float64)
    a = (t - times[k]) / (times[k + 1] - times[k])
    return (1 - a) * frames[k].astype(np.float64) + a * frames[k + 1].astype(np.float64)


@pytest.fixture(scope="module")
def humanoid(tmp_path_factory):
    """The bundled humanoid baked three ways: skinned in memory, single layer, clips."""
    tmp = tmp_path_factory.mktemp("humanoid")
    scene = load(HUMANOID)
    ref = scene.skin(normals=True, velocities=True)
    single = tmp / "single.usdc"
    bake(scene, single, clips=False)
    shot = tmp / "shot.usd"
    summary = bake(scene, shot, chunk=CHUNK, clips=True)
    return dict(scene=scene, ref=ref, single=single, shot=shot, summary=summary, tmp=tmp)


def test_unsorted_and_repeated_times_give_the_sorted_cache(tmp_path):
    """Times in any order, some repeated: the clip cache equals the single-layer one (a cache is
    keyed by time) at every frame and sub-frame, chunk boundaries included. (The clip metadata was
    built in the given order: wrong at almost every time, or no values at all.)"""
    scene = load(HUMANOID)
    t = scene.times[:13]
    shuffled = np.concatenate([t[::-1][:5], t[3:9], t[:4], t[10:]])  # reversed, repeated
    single, clipped = tmp_path / "single.usda", tmp_path / "clips.usda"
    bake(scene, single, t, method="dqs", clips=False)
    said = bake(scene, clipped, shuffled, method="dqs", chunk=3, clips=True)
    assert f"× {len(t)} frames" in said and len(shuffled) > len(t), said  # each time once
    a = Usd.Stage.Open(str(single))
    names = [str(p.GetPath()) for p in a.Traverse() if p.IsA(UsdGeom.Mesh)]
    probe = np.concatenate([t, t[:-1] + 0.5])
    assert assert_same_animation(a, Usd.Stage.Open(str(clipped)), names, probe) > 0


def test_force_removes_the_top_level_reading_the_clips_it_replaces(tmp_path):
    """A ``--force`` clip bake over an earlier one removes the earlier top level as it clears the
    clip layers that file reads: interrupted, it leaves no file showing a mix of two bakes."""
    from dqskin.writers.usd_clips import ClipBake
    scene = load(HUMANOID)
    out = tmp_path / "shot.usd"
    bake(scene, out, scene.times[:6], method="lbs", chunk=3, clips=True)
    assert out.is_file()
    ClipBake(scene, out, scene.times[:6], 3, SkinOptions.baking(method="dqs"),
             force=True)
    assert not out.exists() and not list(clips_folder(out).glob("chunk_*"))


def test_bake_clips_counts_clips_baked_and_kept(tmp_path):
    """:func:`dqskin.distributed.bake_clips` returns the clips in total, baked by this run and
    kept from an earlier one (9 frames in clips of 3: three; a resume keeps them all)."""
    from dqskin.baking import BakeSettings
    from dqskin.distributed import bake_clips
    scene = load(HUMANOID)
    out, opts = tmp_path / "shot.usd", SkinOptions.baking(method="lbs")
    done = bake_clips(scene, out, scene.times[:9], opts, BakeSettings(chunk=3))
    assert (done["clips"], done["baked"], done["kept"]) == (3, 3, 0)
    again = bake_clips(scene, out, scene.times[:9], opts, BakeSettings(chunk=3, resume=True))
    assert (again["clips"], again["baked"], again["kept"]) == (3, 0, 3)
    assert sorted(p.name for p in clips_folder(out).glob("chunk_*.usdc")) == [
        f"chunk_{k:05d}.usdc" for k in range(3)]


@pytest.mark.parametrize("kind", ["folder", "link to a folder"])
def test_a_non_file_where_the_bake_writes_is_refused_before_anything_is_removed(tmp_path, kind):
    """A folder (or a link to one) in the clip folder where the bake writes a layer: ``--force``
    and ``--resume`` refuse it at the start, naming it, and leave the earlier bake as it was (it
    was removed, then the bake failed on that chunk with IsADirectoryError). A folder named like a
    layer this bake does not write, and layers that are links to files, are fine."""
    scene = load(HUMANOID)
    out = tmp_path / "shot.usd"
    bake(scene, out, scene.times[:6], method="lbs", chunk=3, clips=True)
    folder = clips_folder(out)
    layers = sorted(folder.glob("chunk_*.usdc"))
    assert len(layers) == 2
    before = {p.name: p.read_bytes() for p in folder.iterdir()} | {out.name: out.read_bytes()}
    odd = layers[1].with_name(layers[1].name.replace("1", "2"))  # chunk 2 of a longer bake
    if kind == "folder":
        odd.mkdir()
    else:
        (tmp_path / "elsewhere").mkdir()
        odd.symlink_to(tmp_path / "elsewhere")
    for opts in ({"force": True}, {"resume": True}):
        with pytest.raises(ValueError, match=f"{odd.name}: not a file"):
            bake(scene, out, scene.times[:9], method="lbs", chunk=3, clips=True, **opts)
        now = {p.name: p.read_bytes() for p in folder.iterdir() if p != odd}
        assert now | {out.name: out.read_bytes()} == before
    odd.rename(tmp_path / "moved")  # out of the way: a folder past the bake's chunks is kept
    stray = folder / layers[1].name.replace("1", "9")
    stray.mkdir()
    keep = tmp_path / "kept"
    keep.mkdir()
    for p in layers:  # layers as links to files (an annexed or deduplicated folder)
        p.rename(keep / p.name)
        p.symlink_to(keep / p.name)
    done = bake(scene, out, scene.times[:6], method="lbs", chunk=3, clips=True, resume=True)
    assert "2 kept" in done and stray.is_dir()


def test_flatten_refuses_to_overwrite_one_of_its_clip_layers(tmp_path):
    """A clip layer is an input of the cache too (opened only when values are read): flattening
    onto one is refused and leaves it as it was."""
    out = tmp_path / "shot.usd"
    bake(load(HUMANOID), out, chunk=8, clips=True, normals=False, velocities=False)
    layer = sorted(clips_folder(out).glob("chunk_*.usdc"))[1]
    before = layer.read_bytes()
    with pytest.raises(ValueError, match="refusing to overwrite an input"):
        flatten(out, layer, overwrite=True)
    assert layer.read_bytes() == before


def test_flatten_refuses_a_missing_or_damaged_clip_layer(tmp_path):
    """USD skips a missing clip (holding the samples around it) and copies a damaged one: flatten
    checks every clip layer against the size and checksum the top level lists first, and writes
    nothing."""
    out = tmp_path / "shot.usd"
    bake(load(HUMANOID), out, chunk=8, clips=True, normals=False, velocities=False)
    layer = sorted(clips_folder(out).glob("chunk_*.usdc"))[2]
    good = layer.read_bytes()
    layer.unlink()
    with pytest.raises(ValueError, match=f"shot.clips/{layer.name}: missing, damaged or not the "
                                         "clip layer shot.usd was written with"):
        flatten(out, tmp_path / "a.usdc")
    flipped = bytearray(good)
    flipped[len(good) // 2] ^= 1
    for n, damaged in enumerate([bytes(flipped), good[:1000]]):
        layer.write_bytes(damaged)
        with pytest.raises(ValueError, match=f"{layer.name}: missing, damaged or not the clip"):
            flatten(out, tmp_path / f"b{n}.usdc")
    assert sorted(p.name for p in tmp_path.glob("*.usdc")) == []
    layer.write_bytes(good)
    assert Sdf.Layer.FindOrOpen(str(flatten(out, tmp_path / "c.usdc"))) is not None


def _clip_stage(folder, sidecar=None):
    """A two-clip stage written with Sdf (another tool's clips), optionally with a ``.json`` of
    another tool's beside each clip."""
    folder.mkdir()
    for k in range(2):
        clip = Sdf.Layer.CreateNew(str(folder / f"clip.{k}.usda"))
        prim = Sdf.CreatePrimInLayer(clip, "/A")
        attr = Sdf.AttributeSpec(prim, "x", Sdf.ValueTypeNames.Float)
        for t in (k, k + 1):
            clip.SetTimeSample(attr.path, t, float(t))
        clip.Save()
        if sidecar is not None:
            (folder / f"clip.{k}.json").write_text(sidecar)
    top = Sdf.Layer.CreateNew(str(folder.parent / "top.usda"))
    prim = Sdf.PrimSpec(top, "A", Sdf.SpecifierDef)
    Sdf.AttributeSpec(prim, "x", Sdf.ValueTypeNames.Float)
    prim.SetInfo("clips", {"default": {
        "assetPaths": Sdf.AssetPathArray([f"./{folder.name}/clip.0.usda",
                                          f"./{folder.name}/clip.1.usda"]),
        "primPath": "/A", "active": Vt.Vec2dArray([(0.0, 0.0), (1.0, 1.0)])}})
    top.Save()
    return folder.parent / "top.usda"


@pytest.mark.parametrize("sidecar", [None, '{"frames": 10}', "[1, 2]", "not json"])
def test_flatten_takes_other_tools_clips_and_their_files(tmp_path, sidecar):
    """Clips of another tool, with or without a ``.json`` of its own beside each (not a dqskin
    record: no layer name, plan and checksum), flatten as USD composes them."""
    top = _clip_stage(tmp_path / "c", sidecar)
    flat = Usd.Stage.Open(str(flatten(top, tmp_path / "flat.usda")))
    assert [flat.GetAttributeAtPath("/A.x").Get(t) for t in (0, 0.5, 1, 2)] == [0, 0.5, 1, 2]


def test_flatten_of_clips_in_a_package_and_of_bad_clips_metadata(tmp_path):
    from pxr import UsdUtils
    top = _clip_stage(tmp_path / "c")
    package = tmp_path / "pkg.usdz"
    assert UsdUtils.CreateNewUsdzPackage(Sdf.AssetPath(str(top)), str(package))
    flat = Usd.Stage.Open(str(flatten(package, tmp_path / "flat.usda")))
    assert flat.GetAttributeAtPath("/A.x").Get(1.5) == 1.5
    bad = tmp_path / "bad.usda"
    bad.write_text('#usda 1.0\ndef "A" (clips = {dictionary default = {double x = 5}}) {}\n')
    with pytest.raises(ValueError, match="bad.usda: cannot flatten"):
        flatten(bad, tmp_path / "y.usda")


def test_flatten_of_a_file_usd_cannot_open_is_a_clean_error(tmp_path):
    bad = tmp_path / "bad.usd"
    bad.write_text("garbage\n")
    proc = subprocess.run([sys.executable, "-m", "dqskin.cli", "flatten", str(bad), "--out",
                           str(tmp_path / "y.usdc")], capture_output=True, text=True, timeout=300)
    assert proc.returncode == 2 and "Traceback" not in proc.stderr, proc.stderr
    assert "bad.usd: cannot open as USD" in proc.stderr
    assert not (tmp_path / "y.usdc").exists()



def test_flatten_of_a_stage_without_clips(tmp_path):
    # any stage flattens, not only clip caches: its time samples are copied as they are
    src = tmp_path / "plain.usda"
    stage = Usd.Stage.CreateNew(str(src))
    op = UsdGeom.Xform.Define(stage, "/Root").AddTranslateOp()
    for t, x in ((1.0, 0.5), (2.0, 2.5)):
        op.Set((x, 0.0, 0.0), t)
    stage.Save()
    out = flatten(src, tmp_path / "flat.usda")
    flat = Usd.Stage.Open(str(out))
    attr = flat.GetAttributeAtPath("/Root.xformOp:translate")
    assert attr.GetTimeSamples() == [1.0, 2.0] and attr.Get(2.0)[0] == 2.5

def test_a_running_bake_holds_its_clip_folder(tmp_path):
    """While a bake of ``out`` runs (its lock held), another bake of ``out`` fails at once,
    --resume and --force included, and changes nothing (they used to remove or rewrite the
    running bake's files, which then failed); the lock goes with the bake, and a lock file a
    killed run left behind (held by nobody) stops nothing."""
    scene = load(HUMANOID)
    out = tmp_path / "shot.usd"
    args = dict(chunk=4, clips=True, normals=False, velocities=False)
    bake(scene, out, scene.times[:8], **args)
    folder = clips_folder(out)
    before = {p.name: p.read_bytes() for p in folder.iterdir()}
    assert LOCK_FILE not in before
    with bake_lock(out):
        for extra in ({}, {"resume": True}, {"force": True}):
            with pytest.raises(FileExistsError, match="another dqskin run"):
                bake(scene, out, scene.times[:8], **args, **extra)
        assert {p.name: p.read_bytes() for p in folder.iterdir() if p.name != LOCK_FILE} == before
    assert not (folder / LOCK_FILE).exists()
    (folder / LOCK_FILE).write_text("12345\n")
    bake(scene, out, scene.times[:8], **args, force=True)
    assert not (folder / LOCK_FILE).exists()


def test_a_link_where_the_lock_goes_is_refused_not_followed(tmp_path):
    """``SHOT.clips/.lock`` is never followed: a dangling link is an error (it looped for ever),
    and the file a link points to is not truncated."""
    out = tmp_path / "shot.usd"
    folder = clips_folder(out)
    folder.mkdir()
    target = tmp_path / "precious.txt"
    for exists in (False, True):
        if exists:
            target.write_text("keep")
        (folder / LOCK_FILE).symlink_to(target)
        with pytest.raises(OSError):
            bake(load(HUMANOID), out, chunk=4, clips=True)
        assert target.read_text() == "keep" if exists else not target.exists()
        (folder / LOCK_FILE).unlink()


def test_the_lock_holds_across_processes_and_names_the_holder(tmp_path):
    out = tmp_path / "shot.usd"
    code = ("import sys\nfrom dqskin.writers.clip_lock import bake_lock\n"
            "with bake_lock(sys.argv[1]):\n"
            "    print('held', flush=True)\n    sys.stdin.readline()\n")
    holder = subprocess.Popen([sys.executable, "-c", code, str(out)], stdin=subprocess.PIPE,
                              stdout=subprocess.PIPE, text=True)
    try:
        assert holder.stdout.readline().strip() == "held"
        with pytest.raises(FileExistsError, match=f"pid {holder.pid}"):
            bake(load(HUMANOID), out, chunk=4, clips=True, resume=True)
        assert not out.exists()
    finally:
        holder.stdin.close()
        holder.wait(60)
    assert not clips_folder(out).exists()  # the holder made it: left empty, removed
    bake(load(HUMANOID), out, load(HUMANOID).times[:6], chunk=4, clips=True)
    assert out.is_file()


def test_a_bake_failing_before_any_chunk_leaves_nothing_to_resume(tmp_path, monkeypatch):
    """A first bake that fails before it keeps a chunk leaves no plan behind (the next bake of
    the output used to be told to --resume one that never baked a frame)."""
    import dqskin.distributed as dist
    out = tmp_path / "shot.usd"

    def fail(*a, **k):
        raise ValueError("no frame could be skinned")
    monkeypatch.setattr(dist, "run_here", fail)
    with pytest.raises(ValueError, match="no frame could be skinned"):
        bake(load(HUMANOID), out, chunk=4, clips=True)
    assert not clips_folder(out).exists() and not out.exists()
    monkeypatch.undo()
    bake(load(HUMANOID), out, load(HUMANOID).times[:6], chunk=4, clips=True)
    assert out.is_file()


def test_a_single_layer_over_a_clip_bake_replaces_it_whole(tmp_path):
    """A single-layer bake to the output of a clip bake: refused over an unfinished one without
    --force (a later --resume would have replaced the single layer); with --force the single
    layer replaces it and dqskin's clip files go (they were hundreds of MB nothing read), a file
    of the user's in the folder stays, and --resume no longer overwrites the single layer."""
    scene = load(HUMANOID)
    out = tmp_path / "shot.usd"
    bake(scene, out, scene.times[:8], chunk=4, clips=True, normals=False, velocities=False)
    folder = clips_folder(out)
    (folder / "notes.txt").write_text("mine")
    out.unlink()  # unfinished
    with pytest.raises(FileExistsError, match="holds a clip bake of shot.usd; complete it"):
        bake(scene, out, scene.times[:8], clips=False)
    assert not out.exists() and (folder / "plan.json").is_file()
    inside = folder / "chunk_00099.usdc"  # an input under a name --force would remove
    assert Sdf.Layer.FindOrOpen(str(HUMANOID)).Export(str(inside))
    kept = inside.read_bytes()
    top = tmp_path / "top.usda"  # and a layer the input reads
    top.write_text(f'#usda 1.0\n(subLayers = [@./shot.clips/{inside.name}@])\n')
    for src in (inside, top):
        with pytest.raises(ValueError, match="inside .*shot.clips, where a clip bake of shot.usd"):
            bake(src, out, scene.times[:8], clips=False, force=True)
        assert inside.read_bytes() == kept and (folder / "plan.json").is_file()
    inside.unlink()
    bake(scene, out, scene.times[:8], clips=False, force=True)
    assert sorted(p.name for p in folder.iterdir()) == ["notes.txt"]
    before = out.read_bytes()
    assert Sdf.Layer.FindOrOpen(str(out)).GetPrimAtPath("/Humanoid").HasInfo("clips") is False
    with pytest.raises(FileExistsError, match="exists"):
        bake(scene, out, scene.times[:8], chunk=4, clips=True, resume=True, normals=False,
             velocities=False)
    assert out.read_bytes() == before


def test_the_top_level_is_written_only_over_chunks_of_this_bake(tmp_path, monkeypatch):
    """A chunk whose record is of another plan when the bake finishes (a late write by a remote
    worker of a stopped bake) fails the bake: no SHOT.usd reads it."""
    from dqskin.writers import usd_clips
    real = usd_clips.ClipBake.finish

    def late(self):
        record = self.clip_path(1).with_suffix(".json")
        record.write_text(record.read_text().replace(self.key, "0" * 64))
        return real(self)
    monkeypatch.setattr(usd_clips.ClipBake, "finish", late)
    out = tmp_path / "shot.usd"
    with pytest.raises(ValueError, match="chunk_00001.usdc: its record is missing or of another"):
        bake(load(HUMANOID), out, load(HUMANOID).times[:8], chunk=4, clips=True)
    assert not out.exists()


def test_an_input_inside_the_clip_folder_is_refused_and_left_alone(tmp_path):
    folder = clips_folder(tmp_path / "shot.usd")
    folder.mkdir()
    src = folder / "chunk_00000.usdc"  # the name of the first clip layer
    assert Sdf.Layer.FindOrOpen(str(HUMANOID)).Export(str(src))
    before = src.read_bytes()
    for force in (False, True):
        with pytest.raises(ValueError, match="inside .*shot.clips, where a clip bake of shot.usd"):
            bake(src, tmp_path / "shot.usd", chunk=7, clips=True, force=force)
        assert src.read_bytes() == before
    assert sorted(p.name for p in folder.iterdir()) == ["chunk_00000.usdc"]


def test_resume_over_other_settings_says_what_differs(tmp_path):
    scene = load(HUMANOID)
    out = tmp_path / "shot.usd"
    bake(scene, out, scene.times[:8], chunk=4, clips=True, method="lbs", normals=False)
    out.unlink()  # unfinished, as after an interrupt
    with pytest.raises(ValueError, match=r"with chunk=4 \(now chunk=3\), with method='lbs' "
                                         r"\(now method='dqs'\), with normals=False "
                                         r"\(now normals=True\)"):
        bake(scene, out, scene.times[:8], chunk=3, clips=True, method="dqs", resume=True)
    with pytest.raises(ValueError, match=r"of 8 frames from 0 to 7 \(now 6 from 0 to 5"):
        bake(scene, out, scene.times[:6], chunk=4, clips=True, method="lbs", normals=False,
             resume=True)


@pytest.mark.parametrize("force", [False, True])
def test_two_outputs_sharing_a_clip_folder_are_refused(tmp_path, force):
    """``shot.usda`` beside a clip bake of ``shot.usd`` would use the same ``shot.clips/``: the
    second is refused (with ``--force`` too, which would have turned the first file's clips into
    the second bake's), naming the first, which keeps reading its own samples."""
    scene = load(HUMANOID)
    first, second = tmp_path / "shot.usd", tmp_path / "shot.usda"
    bake(scene, first, scene.times[:6], method="lbs", chunk=3, clips=True)
    ref = tmp_path / "ref.usda"
    bake(scene, ref, scene.times[:6], method="lbs", clips=False)
    with pytest.raises(ValueError, match="shot.usd, another output"):
        bake(scene, second, scene.times[:6], method="dqs", chunk=3, clips=True, force=force)
    assert not second.exists()
    ref_stage = Usd.Stage.Open(str(ref))
    names = [str(p.GetPath()) for p in ref_stage.Traverse() if p.IsA(UsdGeom.Mesh)]
    assert assert_same_animation(ref_stage, Usd.Stage.Open(str(first)), names,
                                 scene.times[:6]) > 0


def test_two_clip_bakes_to_one_output_one_wins_whole(tmp_path):
    """Two clip bakes to the same output at once without force (an LBS and a DQS one): exactly
    one finishes and the other fails with FileExistsError, and the cache holds only the winner's
    samples. (Both used to pass the existence check, then write each other's chunks: 7 runs in 10
    left frames of the loser's method in the winner's file.)"""
    import threading
    scene = load(HUMANOID)
    times = scene.times[:12]
    out = tmp_path / "shot.usda"
    barrier, outcome = threading.Barrier(2), {}

    def run(method):
        barrier.wait()
        try:
            bake(scene, out, times, method=method, chunk=2, clips=True, normals=False,
                 velocities=False)
            outcome[method] = "ok"
        except FileExistsError as exc:
            outcome[method] = exc
    threads = [threading.Thread(target=run, args=(m,)) for m in ("lbs", "dqs")]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    winners = [m for m, r in outcome.items() if r == "ok"]
    assert len(winners) == 1 and len(outcome) == 2, outcome
    loser = next(r for r in outcome.values() if r != "ok")
    assert "clip bake" in str(loser) and "force=True" in str(loser), loser
    ref = tmp_path / "ref.usda"
    bake(load(HUMANOID), ref, times, method=winners[0], clips=False, normals=False,
         velocities=False)
    ref_stage = Usd.Stage.Open(str(ref))
    names = [str(p.GetPath()) for p in ref_stage.Traverse() if p.IsA(UsdGeom.Mesh)]
    assert assert_same_animation(ref_stage, Usd.Stage.Open(str(out)), names, times) > 0


def test_clips_equal_oracle_and_single_layer_at_frames_and_sub_frames(humanoid):
    scene, ref, shot = humanoid["scene"], humanoid["ref"], humanoid["shot"]
    t = scene.times
    assert "as 7 clips" in humanoid["summary"]
    stage = Usd.Stage.Open(str(shot))
    names = [m.name for m in scene.meshes]
    probes = probe_times(t, CHUNK)
    for name in names:
        p = ref.points[name]
        extent = np.stack([p.min(axis=1), p.max(axis=1)], axis=1)
        for what, frames in (("points", p), ("normals", ref.normals.get(name)),
                             ("velocities", ref.velocities[name]), ("extent", extent)):
            if frames is None:
                continue
            attr = attribute(stage, name, what)
            for tt in probes:
                want = oracle(frames, t, tt)
                got = np.asarray(attr.Get(tt), np.float64)
                err = np.abs(got - want).max() / max(np.abs(want).max(), 1.0)
                assert err < 1e-6, f"{name}.{what} at {tt}: {err:.2e}"
    n = assert_same_animation(Usd.Stage.Open(str(humanoid["single"])), stage, names, probes)
    assert n > 4 * len(names) * len(probes) - len(names) * len(probes)  # normals may be absent


def test_layout_boundary_samples_and_metadata(humanoid):
    scene, shot = humanoid["scene"], humanoid["shot"]
    folder = clips_folder(shot)
    t = scene.times
    bounds = chunk_bounds(len(t), CHUNK)
    clips = sorted(folder.glob("chunk_*.usdc"))
    assert [p.name for p in clips] == [f"chunk_{k:05d}.usdc" for k in range(len(bounds))]
    assert not [p for p in folder.iterdir() if p.name.startswith(".")]  # no temporary file
    plan = json.loads((folder / "plan.json").read_text())
    name = scene.meshes[0].name
    for k, ((lo, hi), path) in enumerate(zip(bounds, clips)):
        assert verify_chunk(path, plan["key"])
        layer = Sdf.Layer.FindOrOpen(str(path))
        samples = layer.ListTimeSamplesForPath(Sdf.Path(name).AppendProperty("points"))
        # its own frames and, except for the last chunk, the next chunk's first frame
        assert list(samples) == t[lo:min(hi + 1, len(t))].tolist(), k
    top = Sdf.Layer.FindOrOpen(str(shot))
    assert os.path.getsize(shot) < min(p.stat().st_size for p in clips)
    root = Sdf.Path(name).GetPrefixes()[0]
    info = top.GetPrimAtPath(root).GetInfo("clips")["default"]
    assert [tuple(a) for a in info["active"]] == [(t[lo], k) for k, (lo, _) in enumerate(bounds)]
    assert [a.path for a in info["assetPaths"]] == [f"./{folder.name}/{p.name}" for p in clips]
    # no default on clip-driven attributes in the top level (it would hide the clips)
    assert not top.GetAttributeAtPath(Sdf.Path(name).AppendProperty("points")).HasDefaultValue()
    stage = Usd.Stage.Open(str(shot))
    assert (stage.GetStartTimeCode(), stage.GetEndTimeCode()) == (t[0], t[-1])
    for prim in stage.Traverse():
        assert not prim.GetTypeName() == "SkelRoot"
        assert not [p for p in prim.GetAuthoredPropertyNames() if p.startswith("skel:")]


def test_each_clip_holds_a_bit_identical_copy_of_the_next_clips_first_frame(humanoid):
    """Between the last frame of chunk k and the first of chunk k+1 a reader interpolates either
    within clip k (up to its copy of the boundary frame) or, as usd-core 26.11 does, across to
    clip k+1's first sample; both copies are the same bits, so every reader sees one animation."""
    scene, folder = humanoid["scene"], clips_folder(humanoid["shot"])
    t = scene.times
    bounds = chunk_bounds(len(t), CHUNK)
    layers = [Sdf.Layer.FindOrOpen(str(folder / f"chunk_{k:05d}.usdc"))
              for k in range(len(bounds))]
    compared = 0
    for k in range(len(bounds) - 1):
        tb = float(t[bounds[k + 1][0]])
        for spec_path in _sampled_attributes(layers[k]):
            a = np.asarray(layers[k].QueryTimeSample(spec_path, tb))
            b = np.asarray(layers[k + 1].QueryTimeSample(spec_path, tb))
            np.testing.assert_array_equal(a, b, err_msg=f"{spec_path} at {tb}")
            compared += 1
    assert compared >= (len(bounds) - 1) * 4 * len(scene.meshes) - (len(bounds) - 1) * len(
        scene.meshes)


def _sampled_attributes(layer):
    paths = []
    layer.Traverse(Sdf.Path.absoluteRootPath, lambda p: paths.append(p) if (
        p.IsPropertyPath() and layer.GetNumTimeSamplesForPath(p)) else None)
    return paths


def test_flatten_gives_one_layer_with_the_same_animation(humanoid, tmp_path):
    scene = humanoid["scene"]
    flat = flatten(humanoid["shot"], tmp_path / "flat.usdc")
    layer = Sdf.Layer.FindOrOpen(str(flat))
    assert not layer.GetPrimAtPath(Sdf.Path(scene.meshes[0].name).GetPrefixes()[0]).HasInfo(
        "clips")
    assert layer.GetExternalReferences() == [] or all(
        "chunk_" not in r for r in layer.GetExternalReferences())
    names = [m.name for m in scene.meshes]
    assert_same_animation(Usd.Stage.Open(str(humanoid["single"])), Usd.Stage.Open(str(flat)),
                          names, probe_times(scene.times, CHUNK))
    with pytest.raises(FileExistsError, match="flat.usdc: exists .use overwrite=True to overwrite"):
        flatten(humanoid["shot"], flat)


def test_records_hold_the_layers_checksum_and_older_records_verify(humanoid, tmp_path):
    """Each record holds its layer's checksum, taken as the layer was written: XXH3-128 of the
    bytes after the crate bootstrap, then the bootstrap, computed here from the whole file read
    back. Records of earlier bakes holding ``xxh3_128`` (the whole file in order, as
    ``xxh128sum`` prints it) or ``sha256`` verify by those; a record with none, a wrong digest,
    or damaged, does not."""
    import hashlib
    import shutil

    import xxhash
    src = clips_folder(humanoid["shot"])
    plan = json.loads((src / "plan.json").read_text())
    records = sorted(src.glob("chunk_*.json"))
    assert records
    for record in records:
        data = (src / json.loads(record.read_text())["layer"]).read_bytes()
        assert json.loads(record.read_text())["xxh3_128_crate"] == \
            xxhash.xxh3_128(data[88:] + data[:88]).hexdigest()
    layer, record = tmp_path / "chunk_00000.usdc", tmp_path / "chunk_00000.json"
    shutil.copy(src / layer.name, layer)
    old = json.loads((src / record.name).read_text())
    del old["xxh3_128_crate"]
    data = layer.read_bytes()
    for name, digest, ok in (("xxh3_128", xxhash.xxh3_128(data).hexdigest(), True),
                             ("xxh3_128", xxhash.xxh3_128(data[88:] + data[:88]).hexdigest(),
                              False),
                             ("sha256", hashlib.sha256(data).hexdigest(), True),
                             ("sha256", hashlib.sha256(b"another file").hexdigest(), False),
                             (None, None, False)):
        record.write_text(json.dumps(old if digest is None else dict(old, **{name: digest})))
        assert verify_chunk(layer, plan["key"]) is ok, (name, digest)
    for damaged in ("5", "null", '["xxh3_128_crate"]', '{"xxh3_128_crate": null}', "{"):
        record.write_text(damaged)
        assert verify_chunk(layer, plan["key"]) is False, damaged


def test_resume_keeps_verified_chunks_and_redoes_missing_or_corrupt(humanoid, tmp_path):
    scene = humanoid["scene"]
    shot = tmp_path / "shot.usdc"
    bake(scene, shot, chunk=CHUNK, clips=True)
    folder = clips_folder(shot)
    before = {p.name: p.stat().st_mtime_ns for p in folder.glob("chunk_*.usdc")}
    shot.unlink()  # as if interrupted before the top level was written
    (folder / "chunk_00002.usdc").unlink()
    data = bytearray((folder / "chunk_00004.usdc").read_bytes())
    data[len(data) // 2] ^= 0xFF
    (folder / "chunk_00004.usdc").write_bytes(bytes(data))
    time.sleep(0.01)
    with pytest.raises(FileExistsError, match="resume=True"):
        bake(scene, shot, chunk=CHUNK, clips=True)
    with pytest.raises(ValueError, match=rf"with chunk={CHUNK} \(now chunk={CHUNK + 1}\)"):
        bake(scene, shot, chunk=CHUNK + 1, resume=True)
    summary = bake(scene, shot, chunk=CHUNK, resume=True)
    assert "5 kept from the earlier run" in summary
    after = {p.name: p.stat().st_mtime_ns for p in folder.glob("chunk_*.usdc")}
    changed = sorted(n for n in after if after[n] != before.get(n))
    assert changed == ["chunk_00002.usdc", "chunk_00004.usdc"]
    names = [m.name for m in scene.meshes]
    assert_same_animation(Usd.Stage.Open(str(humanoid["single"])), Usd.Stage.Open(str(shot)),
                          names, probe_times(scene.times, CHUNK))


def test_refusals(humanoid, tmp_path):
    scene, shot = humanoid["scene"], humanoid["shot"]
    with pytest.raises(FileExistsError, match="exists"):
        bake(scene, shot, chunk=CHUNK, clips=True)
    with pytest.raises(ValueError, match="USD caches"):
        bake(scene, tmp_path / "x.npz", workers=2)
    with pytest.raises(ValueError, match="need value clips"):
        bake(scene, tmp_path / "x.usd", clips=False, resume=True)
    with pytest.raises(ValueError, match="workers=0"):
        bake(scene, tmp_path / "x.usd", workers=0)
    with pytest.raises(ValueError, match="resume=True and force=True: give one"):
        bake(scene, tmp_path / "x.usd", resume=True, force=True)
    with pytest.raises(ValueError, match="workers and scheduler: give one"):
        bake(scene, tmp_path / "x.usd", workers=2, scheduler="tcp://127.0.0.1:1")
    assert not (tmp_path / "x.usd").exists() and not clips_folder(tmp_path / "x.usd").exists()
    import shutil
    src = Path(shutil.copy(HUMANOID, tmp_path / "rig.usda"))
    before = src.read_bytes()
    with pytest.raises(ValueError, match="input"):
        bake(src, src, clips=True, force=True)
    assert src.read_bytes() == before


def test_a_single_layer_is_one_layer_of_any_size_and_usda_is_bounded(humanoid, tmp_path,
                                                                     monkeypatch):
    """A .usdc/.usd out is one layer unless clips are asked for, however many samples (it used to
    turn into value clips silently above 512 MiB: the file alone held no points), and leaves no
    folder; a .usda beyond ``USDA_MAX_BYTES`` (a text layer is held in memory whole) is refused
    before skinning, naming clips."""
    import dqskin.baking as baking
    from dqskin.errors import LimitError
    scene = humanoid["scene"]
    need = baking.sample_bytes(scene, len(scene.times))
    per_point = 12 * (2 * sum(len(m.points) for m in scene.meshes)
                      + sum(len(m.normals) for m in scene.meshes if m.normals is not None))
    assert need == per_point * len(scene.times)
    monkeypatch.setattr(baking, "USDA_MAX_BYTES", need - 1)
    for name in ("one.usd", "one.usdc"):
        assert "clips" not in bake(scene, tmp_path / name, chunk=30)
        assert not clips_folder(tmp_path / name).exists()
        assert not Sdf.Layer.FindOrOpen(str(tmp_path / name)).GetPrimAtPath(
            "/Humanoid").HasInfo("clips")
    with pytest.raises(LimitError, match=r"one.usda.?: 9 MiB of samples, more than the 8 MiB "
                                         r"a .usda layer takes .*clips=True"):
        bake(scene, tmp_path / "one.usda", chunk=30)
    assert not (tmp_path / "one.usda").exists() and not clips_folder(tmp_path / "one.usda").exists()
    assert "clips in" in bake(scene, tmp_path / "one.usda", chunk=30, clips=True)
    monkeypatch.setattr(baking, "USDA_MAX_BYTES", need)
    assert "clips" not in bake(scene, tmp_path / "two.usda", chunk=30)


def test_default_clip_length_holds_clip_bytes_of_samples(humanoid, tmp_path, monkeypatch):
    """Without ``chunk``, a clip holds ``CLIP_CHUNK`` frames, or as many more as make
    ``CLIP_BYTES`` of samples (closed form: the layers' frame counts)."""
    from dqskin.writers import usd_clips
    scene = humanoid["scene"]
    F = len(scene.times)
    per_frame = 12 * (2 * sum(len(m.points) for m in scene.meshes)
                      + sum(len(m.normals) for m in scene.meshes if m.normals is not None))
    monkeypatch.setattr(usd_clips, "CLIP_CHUNK", 3)
    for fit, expect in ((7, 7), (2, 3)):  # frames CLIP_BYTES holds → frames per clip
        monkeypatch.setattr(usd_clips, "CLIP_BYTES", fit * per_frame + per_frame // 2)
        out = tmp_path / f"fit{fit}.usd"
        assert f"as {-(-F // expect)} clips" in bake(scene, out, clips=True)
        records = sorted(clips_folder(out).glob("chunk_*.json"))
        frames = [json.loads(r.read_text())["frames"] for r in records]
        assert frames == [min(expect, F - a) + (a + expect < F) for a in range(0, F, expect)]


def test_default_clip_length_leaves_each_worker_four_clips(humanoid, monkeypatch):
    """``clip_frames``: points only counts 12 bytes a point, normals and velocities add theirs;
    with N slots a clip is at most ``ceil(F / 4N)`` frames (not under ``CLIP_CHUNK``), then
    shortened to share the frames evenly among the clips that makes."""
    from dqskin.writers import usd_clips
    from dqskin.writers.usd_clips import clip_frames
    scene = humanoid["scene"]
    points = sum(len(m.points) for m in scene.meshes)
    monkeypatch.setattr(usd_clips, "CLIP_CHUNK", 2)
    monkeypatch.setattr(usd_clips, "CLIP_BYTES", 12 * points * 100)
    assert clip_frames(scene, 1000, normals=False, velocities=False) == 100
    assert clip_frames(scene, 1000, normals=False, velocities=True) == 50
    assert clip_frames(scene, 1000, normals=False, velocities=False, workers=2) == 100
    assert clip_frames(scene, 1000, normals=False, velocities=False, workers=3) == 84  # 12 × 84
    assert clip_frames(scene, 10, normals=False, velocities=False, workers=2) == 2
    monkeypatch.setattr(usd_clips, "CLIP_BYTES", 12 * points * 90)
    assert clip_frames(scene, 1000, normals=False, velocities=False) == 90  # in one process
    assert clip_frames(scene, 1000, normals=False, velocities=False, workers=1) == 84  # 12 clips
    assert clip_frames(scene, 1000, normals=False, velocities=False, workers=5) == 50  # 20 clips
    assert clip_frames(scene, 1292, normals=False, velocities=False, workers=2) == 81  # 15 → 16


def test_default_clip_length_fills_every_wave_of_workers(humanoid, monkeypatch):
    """With the real ``CLIP_CHUNK`` (128) and ``CLIP_BYTES``: the slot with the most clips
    (``k``) bakes fewer than ``F / N + k`` frames (the last wave is full, to within a frame a
    clip), the clips are never longer than without workers, and never under ``CLIP_CHUNK``
    frames unless evened out."""
    from dqskin.writers import usd_clips
    from dqskin.writers.usd_clips import CLIP_CHUNK, clip_frames
    scene = humanoid["scene"]
    for F in (*range(1, 3000, 7), 1292, 10000, 123457):
        alone = clip_frames(scene, F, normals=False, velocities=False)
        for n in (1, 2, 3, 4, 8, 64):
            size = clip_frames(scene, F, normals=False, velocities=False, workers=n)
            clips = -(-F // size)
            k = -(-clips // n)
            assert 1 <= size <= alone and k * size < F / n + k, (F, n, size)
            if F >= 4 * n * CLIP_CHUNK:  # long enough for four clips a slot
                assert k >= 4 and size > CLIP_CHUNK * (k - 1) / k, (F, n, size)
    # 63,624 bytes a frame: 527 frames hold 32 MB, four clips a slot cap them at 162
    assert clip_frames(scene, 1292, normals=False, velocities=False, workers=2) == 162
    # 1,000 frames on 4 slots: four clips each would be 63 frames, under CLIP_CHUNK: 8 of 125
    assert clip_frames(scene, 1000, normals=False, velocities=False, workers=4) == 125
    monkeypatch.setattr(usd_clips, "CLIP_BYTES", 1)  # a mesh of 128-frame clips: 11 → 12 of 108
    assert clip_frames(scene, 1292, normals=False, velocities=False) == 128
    assert clip_frames(scene, 1292, normals=False, velocities=False, workers=2) == 108


def test_resume_without_chunk_continues_with_the_earlier_bakes_chunks(humanoid, tmp_path):
    """A bake started with ``chunk=4`` and interrupted (its top level missing, one layer lost)
    is completed by ``resume`` without ``chunk``, though the default would differ now."""
    scene = humanoid["scene"]
    out = tmp_path / "shot.usd"
    bake(scene, out, clips=True, chunk=4)
    out.unlink()
    layers = sorted(clips_folder(out).glob("chunk_*.usdc"))
    layers[1].unlink()
    summary = bake(scene, out, resume=True)
    assert f"{len(layers) - 1} kept" in summary, summary
    assert_same_animation(Usd.Stage.Open(str(out)), Usd.Stage.Open(str(humanoid["shot"])),
                          [m.name for m in scene.meshes], scene.times)


def test_rigid_prims_match_pixars_baseline(shared_assets, tmp_path):
    """``lbs.usda``: skinned meshes and rigidly bound prims (Cube, Sphere, Cylinder) through
    clips of 4 frames equal UsdSkel's own bake (``baseline/lbs.baked.usda``) at every frame."""
    src = shared_assets / BAKE / "lbs.usda"
    scene = load(src)
    shot = tmp_path / "lbs.usd"
    bake(scene, shot, chunk=4, clips=True, velocities=False)
    stage = Usd.Stage.Open(str(shot))
    base = Usd.Stage.Open(str(shared_assets / BAKE / "baseline" / "lbs.baked.usda"))
    checked = 0
    rigid = ["/Root/Cube", "/Root/Cylinder", "/Root/Sphere"]
    for name in rigid + [m.name for m in scene.meshes]:
        for attr in ["xformOp:transform"] if name in rigid else ["points", "extent"]:
            for t in scene.times:
                ours = np.array(stage.GetPrimAtPath(name).GetAttribute(attr).Get(t), np.float64)
                ref = np.array(base.GetPrimAtPath(name).GetAttribute(attr).Get(t), np.float64)
                err = np.abs(ours - ref).max() / max(np.abs(ref).max(), 1.0)
                assert err < 1e-5, f"{name}.{attr} at {t}: {err:.2e}"
                checked += 1
    assert checked > 3 * len(scene.times)


def _wait_for(predicate, timeout):
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        if predicate():
            return True
        time.sleep(0.02)
    return False


def test_ctrl_c_then_resume_completes_the_same_cache(humanoid, tmp_path):
    """SIGINT to ``dqskin skin --clips`` mid-bake: exit 130, no top level, no temporary file,
    some chunks done; ``--resume`` completes it, keeping those, equal to the single layer."""
    shot = tmp_path / "shot.usd"
    folder = clips_folder(shot)
    args = [sys.executable, "-m", "dqskin.cli", "skin", str(HUMANOID), "--out", str(shot),
            "--clips", "--chunk", "4", "--substeps", "6", "--max-frames", "100000"]
    proc = subprocess.Popen(args, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        assert _wait_for(lambda: len(list(folder.glob("chunk_*.json"))) >= 3, 120), \
            "the bake never started"
        proc.send_signal(signal.SIGINT)
        out, err = proc.communicate(timeout=60)
    finally:
        proc.kill()
    done = len(list(folder.glob("chunk_*.usdc")))
    total = -(-(48 * 6 + 1) // 4)
    assert proc.returncode == 130, err
    # how many clips are kept, and the command that completes the bake (issue 29, item 8)
    said = f"dqskin: interrupted; {done} of {total} clips are kept in {folder}; to complete " \
           "the bake: dqskin "
    last = err.strip().splitlines()[-1]
    assert last.startswith(said), last
    assert not shot.exists()
    assert not [p for p in folder.iterdir() if p.name.startswith(".")]
    assert 0 < done < total, (done, total)
    import shlex
    assert shlex.split(last[len(said):]) == args[3:] + ["--resume"]
    proc = subprocess.run(args[:3] + shlex.split(last[len(said):]), capture_output=True,
                          text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr
    assert f"{total} clips" in proc.stdout and f"{done} kept" in proc.stdout, proc.stdout
    scene = humanoid["scene"]
    names = [m.name for m in scene.meshes]
    stage = Usd.Stage.Open(str(shot))
    times = np.array(stage.GetPrimAtPath(names[0]).GetAttribute("points").GetTimeSamples())
    assert len(times) == 48 * 6 + 1
    single = tmp_path / "single.usdc"
    bake(scene, single, times=times, clips=False)
    probes = probe_times(times, 4)[::7]
    assert_same_animation(Usd.Stage.Open(str(single)), stage, names, probes)


def test_skinning_options_reach_the_clips_and_their_plan(humanoid, tmp_path):
    """``sign_reference`` (a :meth:`Scene.skin` option) gives the same clips as the single layer,
    and resuming with another value is refused (it is part of the plan key)."""
    scene = humanoid["scene"]
    opts = dict(method="dqs", sign_reference="running_sum", velocities=False)
    single, shot = tmp_path / "single.usdc", tmp_path / "shot.usd"
    bake(scene, single, clips=False, **opts)
    bake(scene, shot, chunk=CHUNK, clips=True, **opts)
    names = [m.name for m in scene.meshes]
    assert_same_animation(Usd.Stage.Open(str(single)), Usd.Stage.Open(str(shot)), names,
                          probe_times(scene.times, CHUNK)[::3])
    with pytest.raises(ValueError, match="with sign_reference='running_sum' "
                                         r"\(now sign_reference='largest_weight'\)"):
        bake(scene, shot, chunk=CHUNK, resume=True, **dict(opts, sign_reference="largest_weight"))


def test_skin_chunks_of_given_sizes_cover_the_frames_in_order(humanoid):
    """``Scene.skin_chunks`` with a list of sizes (what in-process clip bakes stream: each clip's
    frames in chunks, across clips) gives those slices, each equal to skinning those frames."""
    scene = humanoid["scene"]
    t = np.asarray(scene.times[:9], np.float64)
    got = list(scene.skin_chunks(t, [3, 1, 5], normals=False, velocities=False))
    assert [sl for sl, _ in got] == [slice(0, 3), slice(3, 4), slice(4, 9)]
    for sl, res in got:
        want = scene.skin(t[sl], normals=False, velocities=False)
        for name, p in want.points.items():
            np.testing.assert_array_equal(res.points[name], p)
    for bad in ([3, 1], [4, 0, 5], []):
        with pytest.raises(ValueError, match=r"chunk=\[|add up to \d+ frames, not 9"):
            list(scene.skin_chunks(t, bad))


@pytest.mark.parametrize("sign", ["largest_weight", "running_sum"])  # one launch; per mesh
def test_chunks_whose_poses_are_sampled_in_blocks_equal_skinning_their_frames(humanoid,
                                                                            monkeypatch, sign):
    """``chunk_skinner`` (what ``Scene.skin_chunks`` skins with) samples the poses of several
    chunks at once, in blocks cut by chunk count and by bytes: each chunk's points, normals and
    velocities are bit for bit those of skinning its frames alone, chunks taken in any order."""
    from dqskin import pipeline

    scene = humanoid["scene"]
    assert len(scene.meshes) > 1  # (the one-launch batch)
    t = np.asarray(scene.times[:11], np.float64)
    opts = SkinOptions(method="dqs", sign_reference=sign, normals=True, velocities=True)
    joints = sum(s.joint_count for s in scene.skeletons)
    for chunks, most in ((2, 1 << 30), (8, 4 * 320 * joints)):  # blocks of 2 chunks; 4 frames
        monkeypatch.setattr(pipeline, "POSE_BLOCK_CHUNKS", chunks)
        monkeypatch.setattr(pipeline, "POSE_BLOCK_BYTES", most)
        slices = [slice(0, 3), slice(3, 4), slice(4, 6), slice(6, 9), slice(9, 11)]
        skin = pipeline.chunk_skinner(scene, t, slices, opts, scene._skinners)
        for k in (3, 0, 1, 4, 2, 2):
            got, want = skin(k), scene.skin(t[slices[k]], options=opts)
            np.testing.assert_array_equal(got.times, t[slices[k]])
            for what in ("points", "normals", "velocities"):
                assert getattr(got, what).keys() == getattr(want, what).keys()
                for name, a in getattr(want, what).items():
                    np.testing.assert_array_equal(getattr(got, what)[name], a)
    with pytest.raises(ValueError, match="does not start where"):
        pipeline.chunk_skinner(scene, t, [slice(0, 2), slice(4, 6), slice(2, 4)], opts,
                               scene._skinners)
    # a bad pose at frame 7, in the block of chunks 1 to 4: the chunks before it come out, and
    # the error is raised by the chunk that holds it
    monkeypatch.setattr(pipeline, "POSE_BLOCK_CHUNKS", 8)
    monkeypatch.setattr(pipeline, "POSE_BLOCK_BYTES", 1 << 30)  # chunks 1 to 4: one block
    local = type(scene).local_transforms

    def bad_at_7(self, times, *args, **kwargs):
        if np.any(np.asarray(times) >= t[7]):
            raise ValueError(f"a bad pose at {t[7]:g}")
        return local(self, times, *args, **kwargs)
    monkeypatch.setattr(type(scene), "local_transforms", bad_at_7)
    got = []
    with pytest.raises(ValueError, match="a bad pose"):
        for sl, _ in scene.skin_chunks(t, [3, 1, 2, 3, 2], options=opts):
            got.append(sl)
    assert got == [slice(0, 3), slice(3, 4), slice(4, 6)]
    assert list(scene.skin_chunks(t[:0], 4, options=opts)) == []


def test_skin_chunks_reuse_the_buffers_of_chunks_the_caller_dropped(humanoid, monkeypatch):
    """``Scene.skin_chunks`` skins each chunk into the buffers of chunks the caller has dropped
    (:func:`dqskin.kernels.buffers.reusing`; every buffer pooled here): a stream of eight chunks
    dropped one by one allocates as a few chunks do, and chunks the caller keeps are never
    overwritten (each equals skinning its frames on its own)."""
    from dqskin.kernels import buffers as KB
    scene = humanoid["scene"]
    t = np.asarray(scene.times[:24], np.float64)
    opts = dict(method="dqs", normals=True, velocities=True)
    made, new = [], KB._new
    monkeypatch.setattr(KB, "MIN_BYTES", 1)
    monkeypatch.setattr(KB, "_new", lambda *a: made.append(a) or new(*a))
    scene.skin(t[:3], **opts)
    per_chunk = len(made)
    assert per_chunk >= 2
    made.clear()
    for _ in scene.skin_chunks(t, 3, **opts):
        pass
    assert len(made) <= 3 * per_chunk  # the one consumed, the one skinned ahead, one in passing
    kept = list(scene.skin_chunks(t, 3, **opts))
    for sl, res in kept:
        want = scene.skin(t[sl], **opts)
        for got, ref in ((res.points, want.points), (res.normals, want.normals),
                         (res.velocities, want.velocities)):
            assert got.keys() == ref.keys()
            for name in ref:
                np.testing.assert_array_equal(got[name], ref[name])


@pytest.mark.parametrize("failure", ["check", "interrupt", "finish"])
def test_a_failure_filling_the_next_clip_keeps_the_finished_one(humanoid, tmp_path, monkeypatch,
                                                                failure):
    """In-process bake, clip 1 fails while being filled (a failed check, or Ctrl-C as the CLI
    records it, raised in the main thread; or its layer cannot be finished, a full disk): clip
    0, finished and hashed as it was written, is recorded and renamed, as the one-by-one bake
    had it; ``--resume`` keeps it. Never a temporary file left, nor clip 1."""
    import dqskin.distributed as distributed
    from dqskin.files import atomic
    from dqskin.writers import usd_clips
    scene = humanoid["scene"]
    shot = tmp_path / "shot.usd"
    calls = []
    if failure == "interrupt":
        chunks = scene.skin_chunks

        def skin_chunks(*args, **kwargs):
            for i, item in enumerate(chunks(*args, **kwargs)):
                if i == 1:  # the first chunk of clip 1 (one chunk a clip here)
                    atomic.interrupt(KeyboardInterrupt())
                yield item
        monkeypatch.setattr(scene, "skin_chunks", skin_chunks)
    elif failure == "check":
        check = distributed.check_skinned

        def failing_check(path, res):
            calls.append(path)
            if len(calls) == 2:
                raise ValueError("NaN in clip 1")
            return check(path, res)
        monkeypatch.setattr(distributed, "check_skinned", failing_check)
    if failure == "finish":  # clip 1's layer cannot be finished: the disk is full
        close, closed = usd_clips.CrateSamples.close, []

        def full(self, start, end):
            closed.append(start)
            if len(closed) == 2:
                raise OSError(28, "No space left on device")
            return close(self, start, end)
        monkeypatch.setattr(usd_clips.CrateSamples, "close", full)
    errors = {"interrupt": KeyboardInterrupt, "finish": OSError}
    try:
        with pytest.raises(errors.get(failure, ValueError)):
            bake(scene, shot, chunk=CHUNK, clips=True)
    finally:
        atomic.reset_interrupt()
    folder = clips_folder(shot)
    assert not [p.name for p in folder.iterdir() if p.name.startswith(".")]
    assert not (folder / "chunk_00001.usdc").exists()
    layer, record = folder / "chunk_00000.usdc", folder / "chunk_00000.json"
    assert verify_chunk(layer, json.loads(record.read_text())["plan"])
    monkeypatch.undo()
    assert "1 kept from the earlier run" in bake(scene, shot, chunk=CHUNK, resume=True)
    names = [m.name for m in scene.meshes]
    assert_same_animation(Usd.Stage.Open(str(humanoid["single"])), Usd.Stage.Open(str(shot)),
                          names, scene.times)
