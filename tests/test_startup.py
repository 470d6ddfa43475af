"""What the command line loads before it needs it (checked by the modules a fresh interpreter
has loaded, not by timing): ``--help`` and usage errors answer without Warp, USD or Dask;
``info`` reads a scene without Warp when a float64 bound proves its skinned points finite
(:func:`dqskin.validation.points_stay_finite`) and skins them when it cannot."""

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from test_cli import usda
from test_cli_hostile import overflow_rig

import dqskin
from dqskin.validation import points_stay_finite

ROOT = Path(__file__).resolve().parents[1]
HEAVY = ("warp", "pxr", "dask")


def loaded(*argv):
    """``(exit status, heavy packages loaded, stdout)`` of ``dqskin.cli.main(argv)`` run in a
    fresh interpreter."""
    code = f"""
import contextlib, io, sys
from dqskin.cli import main
out = io.StringIO()
try:
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(io.StringIO()):
        status = main({[str(a) for a in argv]!r})
except SystemExit as exc:
    status = exc.code
print(status)
print(" ".join(sorted({{m.split(".")[0] for m in sys.modules}} & set({HEAVY!r}))))
print(out.getvalue(), end="")
"""
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                          cwd=ROOT, timeout=300, check=True)
    status, heavy, text = proc.stdout.split("\n", 2)
    return int(status), heavy.split(), text


@pytest.mark.parametrize("argv", [
    ("--help",), ("skin", "--help"), ("skin",), ("bogus",),
    ("skin", "in.usda", "--out", "o.usdc", "--method", "nope"),
    ("compare", "in.usda", "--out", "r", "--width", "wide")])
def test_help_and_usage_errors_load_nothing_heavy(argv):
    status, heavy, _ = loaded(*argv)
    assert status == (0 if argv[-1] == "--help" else 2)
    assert heavy == [], f"dqskin {' '.join(argv)} loads {heavy}"


def test_refusals_answer_before_warp_usd_or_dask(tmp_path):
    """``skin``, ``rig`` and ``compare`` refuse an existing output without --force, bad option
    values and a report over its input before importing Warp, USD or Dask (and leave the
    existing output as it was)."""
    src = usda(tmp_path)
    taken = tmp_path / "taken.usdc"
    taken.write_bytes(b"not replaced")
    for argv in [("skin", src, "--out", taken), ("skin", src, "--out", taken, "--workers", "1"),
                 ("skin", src, "--out", tmp_path / "o.usdc", "--chunk", "0"),
                 ("skin", src, "--out", tmp_path / "o.usdc", "--workers", "100000"),
                 ("skin", src, "--out", tmp_path / "o.obj", "--workers", "2"),
                 ("rig", src, "--out", taken),
                 ("compare", src, "--out", tmp_path)]:
        status, heavy, _ = loaded(*argv)
        assert status == 2, argv
        assert heavy == [], f"dqskin {' '.join(map(str, argv))} loads {heavy}"
    assert taken.read_bytes() == b"not replaced"


def overflow_free_rig(tmp_path, y):
    """test_cli's rig with joint 'a/b' translated to ``y`` (float32 all along), in a folder of
    its own."""
    (tmp_path / f"{y:g}").mkdir()
    path = usda(tmp_path / f"{y:g}")
    text = path.read_text()
    old = "float3[] translations = [(0,0,0), (0,1,0)]"
    assert old in text
    path.write_text(text.replace(old, f"float3[] translations = [(0,0,0), (0,{y:g},0)]"))
    return path


def test_info_skins_only_what_the_bound_cannot_prove(tmp_path):
    """The bundled humanoid and test_cli's rig: proven finite, no Warp. Joints 10²⁵ away: the
    points are finite (so no problem), but the bound cannot tell, so info skins them (Warp)."""
    for path, skins in ((ROOT / "assets" / "humanoid.usda", False),
                        (usda(tmp_path), False),
                        (overflow_free_rig(tmp_path, 1e25), True)):
        status, heavy, text = loaded("info", path)
        assert status == 0, text
        assert "problems: none" in text
        assert heavy == (["pxr", "warp"] if skins else ["pxr"]), (path.name, heavy)


def test_bound_refuses_to_prove_an_overflow(tmp_path):
    """A rig whose points overflow float32 when skinned (test_cli_hostile's): not proven, so the
    skinning check runs and finds it; the same rig a little smaller is proven."""
    for path, proven in ((overflow_rig(tmp_path), False),
                         (overflow_free_rig(tmp_path, 1.0), True)):
        scene = dqskin.load(path)
        t = np.asarray(scene.times)
        local = {s: scene.local_transforms(t, s) for s in range(len(scene.skeletons))}
        assert points_stay_finite(scene, t, local) == proven, path
        if not proven:
            with np.errstate(over="ignore"):
                assert not np.isfinite(scene.skin(t, device="cpu").points[
                    scene.meshes[0].name]).all()  # (the bound was right not to prove it)
