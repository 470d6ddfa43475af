"""Hostile UsdSkel input: every fault is one ValueError line naming the file, the prim and the
field, and USD's own C++ diagnostics never reach the terminal."""

import os
import subprocess
import sys
from concurrent.futures import ThreadPoolExecutor

import numpy as np
import pytest
from pxr import Gf, Tf, Usd, UsdSkel, Vt
from test_usd import build_rig

from dqskin.errors import InputError
from dqskin.readers import usd as usd_format
from dqskin.readers.usd import load_usd

BODY, SKEL, ANIM = "/Root/Geo/Body", "/Root/Rig/Skel", "/Root/Rig/Skel/Anim"


def edited_rig(tmp_path, edit, name="bad.usda"):
    """:func:`test_usd.build_rig` saved after ``edit(stage)``."""
    path = build_rig(tmp_path / name)
    stage = Usd.Stage.Open(str(path))
    edit(stage)
    stage.GetRootLayer().Save()
    return path


def assert_refused(path, capfd, *needles):
    """``load_usd`` raises dqskin's InputError (a ValueError, not a library's), one line
    starting with the file and containing every needle; USD printed nothing."""
    capfd.readouterr()
    with pytest.raises(ValueError) as err:
        load_usd(path)
    msg = str(err.value)
    assert isinstance(err.value, InputError), repr(err.value)
    assert "\n" not in msg and msg.startswith(str(path)), msg
    for needle in needles:
        assert needle in msg, msg
    out, errs = capfd.readouterr()
    assert out == "" and errs == "", errs
    return msg


def _anim(stage):
    return UsdSkel.Animation(stage.GetPrimAtPath(ANIM))


def _skel(stage):
    return UsdSkel.Skeleton(stage.GetPrimAtPath(SKEL))


def _body_attr(stage, name):
    return stage.GetPrimAtPath(BODY).GetAttribute(f"primvars:skel:{name}")


def _only_samples(attr):
    value = attr.Get()
    attr.Clear()
    attr.Set(value, 0.0)


# -- 1. joint influence primvars that are missing or have no value -----------------------------

PRIMVAR_CASES = {
    "weights missing": (lambda st: st.GetPrimAtPath(BODY).RemoveProperty(
        "primvars:skel:jointWeights"), "primvars:skel:jointWeights is missing"),
    "indices missing": (lambda st: st.GetPrimAtPath(BODY).RemoveProperty(
        "primvars:skel:jointIndices"), "primvars:skel:jointIndices is missing"),
    "indices without value": (lambda st: _body_attr(st, "jointIndices").Clear(),
                              "primvars:skel:jointIndices is authored without a value"),
    "weights blocked": (lambda st: _body_attr(st, "jointWeights").Block(),
                        "primvars:skel:jointWeights is authored without a value"),
    "weights only time samples": (lambda st: _only_samples(_body_attr(st, "jointWeights")),
                                  "primvars:skel:jointWeights has only time samples"),
}


@pytest.mark.parametrize("case", sorted(PRIMVAR_CASES))
def test_missing_influence_primvars(tmp_path, capfd, case):
    """These gave 'RuntimeError: Accessed invalid attribute as a primvar'."""
    edit, message = PRIMVAR_CASES[case]
    assert_refused(edited_rig(tmp_path, edit), capfd, f"{BODY}: {message}")


# -- 2., 3. skeletons: singular or non-finite bind transforms, duplicate or no joints ----------

def _singular_bind(clear_rest):
    def edit(stage):
        skel = _skel(stage)
        bind = list(skel.GetBindTransformsAttr().Get())
        bind[1] = Gf.Matrix4d(1.0).SetScale(Gf.Vec3d(1.0, 0.0, 1.0))
        skel.GetBindTransformsAttr().Set(Vt.Matrix4dArray(bind))
        if clear_rest:
            skel.GetRestTransformsAttr().Clear()
    return edit


def _set_bind_entry(value):
    def edit(stage):
        skel = _skel(stage)
        bind = np.array(skel.GetBindTransformsAttr().Get())
        bind[2, 1, 1] = value
        skel.GetBindTransformsAttr().Set(Vt.Matrix4dArray([Gf.Matrix4d(m.tolist()) for m in bind]))
    return edit


SKELETON_CASES = {
    "singular bind, derived rest": (_singular_bind(True),
                                    "bindTransforms: singular bind transform at joint 'a/b'"),
    "singular bind, authored rest": (_singular_bind(False),
                                     "bindTransforms: singular bind transform at joint 'a/b'"),
    "NaN bind": (_set_bind_entry(np.nan),
                 "bindTransforms: NaN or infinite entries at joint 'a/b/c'"),
    "duplicate joints": (lambda st: _skel(st).GetJointsAttr().Set(["a", "a/b", "a/b"]),
                         "joints has duplicate joint name 'a/b'"),
    "no joints": (lambda st: _skel(st).GetJointsAttr().Set([]),
                  "joints is empty or missing (a Skeleton needs at least one joint)"),
    "short restTransforms": (lambda st: _skel(st).GetRestTransformsAttr().Set(
        Vt.Matrix4dArray([Gf.Matrix4d(1.0)])), "restTransforms has 1 matrices for 3 joints"),
    "short bindTransforms": (lambda st: _skel(st).GetBindTransformsAttr().Set(
        Vt.Matrix4dArray([Gf.Matrix4d(1.0)])), "bindTransforms has 1 matrices for 3 joints"),
}


@pytest.mark.parametrize("case", sorted(SKELETON_CASES))
def test_bad_skeletons(tmp_path, capfd, case):
    """Singular binds gave a bare LinAlgError, duplicates loaded, short arrays made USD warn."""
    edit, message = SKELETON_CASES[case]
    assert_refused(edited_rig(tmp_path, edit), capfd, f"{SKEL}: {message}")


# -- 4. SkelAnimation arrays that do not fit their joints or blend shapes ----------------------

def _set_at(attr_name, values, time=None):
    def edit(stage):
        attr = _anim(stage).GetPrim().GetAttribute(attr_name)
        attr.Set(values) if time is None else attr.Set(values, time)
    return edit


ANIMATION_CASES = {
    "short translations": (_set_at("translations", Vt.Vec3fArray([Gf.Vec3f(0.0)])),
                           "translations has 1 values for 2 joints"),
    "short rotations at a sample": (_set_at("rotations", Vt.QuatfArray([Gf.Quatf(1.0)]), 2.0),
                                    "rotations has 1 values for 2 joints at time 2"),
    "long scales": (_set_at("scales", Vt.Vec3hArray([Gf.Vec3h(1.0)] * 3)),
                    "scales has 3 values for 2 joints"),
    "short blendShapeWeights": (_set_at("blendShapeWeights", Vt.FloatArray([0.5, 0.5]), 3.0),
                                "blendShapeWeights has 2 values for 3 blendShapes at time 3"),
    "NaN translation": (_set_at("translations", Vt.Vec3fArray([Gf.Vec3f(0.0),
                                                               Gf.Vec3f(np.nan, 0.0, 0.0)])),
                        "translations has NaN or infinite values for joint 'a/b'"),
    "zero quaternion": (_set_at("rotations", Vt.QuatfArray([Gf.Quatf(0.0), Gf.Quatf(1.0)]), 1.0),
                        "rotations has a zero quaternion for joint 'a' at time 1"),
    "duplicate animated joints": (_set_at("joints", ["a", "a"]), "joints has duplicate names 'a'"),
}


@pytest.mark.parametrize("case", sorted(ANIMATION_CASES))
def test_bad_animations(tmp_path, capfd, case):
    """Short arrays used to print a screenful of USD warnings and drop the animation (exit 0)."""
    edit, message = ANIMATION_CASES[case]
    assert_refused(edited_rig(tmp_path, edit), capfd, f"{ANIM}: {message}")


class _WarningQuery:
    """A skeleton query whose UsdSkel posts a warning and falls back, as it does when it cannot
    compose an animation (at every time, or only at time ``at``)."""

    def __getattr__(self, name):
        return getattr(self.query, name)

    def __init__(self, query, at=None, none_at=None):
        self.query, self.at, self.none_at = query, at, none_at

    def ComputeJointLocalTransforms(self, time):  # noqa: N802 (UsdSkel's name)
        if self.at is None or time.GetValue() == self.at:
            Tf.Warn("failed composing transforms from components.")
        if time.GetValue() == self.none_at:
            return None
        return self.query.ComputeJointLocalTransforms(time)


def test_animation_usdskel_cannot_compose_later(tmp_path, capfd):
    """Past loading too, UsdSkel's warning that it fell back to the rest pose is a ValueError
    (where UsdSkel composes each time: samples the loader does not sample itself)."""
    scene = load_usd(build_rig(tmp_path / "rig.usda"))
    anim = scene.animations[0]
    anim._tracks = None
    anim._query = _WarningQuery(anim._query)
    capfd.readouterr()
    with pytest.raises(ValueError, match=r"rig.usda: /Root/Rig/Skel/Anim: cannot compute joint "
                                         r"transforms at time 2 \(USD: failed composing"):
        anim.local_transforms([2.0])
    assert capfd.readouterr().err == ""
    anim._query = _WarningQuery(anim._query.query, at=3.0)  # warnings are checked per call
    with pytest.raises(ValueError, match=r"Anim: cannot compute joint transforms at time 3 "
                                         r"\(USD: failed composing"):
        anim.local_transforms([1.0, 2.0, 3.0, 4.0])
    assert capfd.readouterr().err == ""
    anim._query = _WarningQuery(anim._query.query, at=2.0, none_at=3.0)  # the warning came first
    with pytest.raises(ValueError, match=r"Anim: cannot compute joint transforms at time 2 "):
        anim.local_transforms([1.0, 2.0, 3.0, 4.0])
    anim._query = _WarningQuery(anim._query.query, at=-1.0, none_at=3.0)  # no warning
    with pytest.raises(ValueError, match=r"Anim: cannot compute joint transforms at time 3$"):
        anim.local_transforms([1.0, 2.0, 3.0, 4.0])
    assert capfd.readouterr().err == ""


# -- stage metadata --------------------------------------------------------------------------

METADATA_CASES = {
    "timeCodesPerSecond": (lambda st: st.SetTimeCodesPerSecond(0.0),
                           "layer metadata timeCodesPerSecond 0: must be a positive number"),
    "upAxis": (lambda st: st.SetMetadata("upAxis", "X"), "layer metadata upAxis 'X'"),
    "huge time range": (lambda st: st.SetEndTimeCode(1e12), "spans more than 10000000 time codes"),
    "NaN start": (lambda st: st.SetStartTimeCode(float("nan")), "startTimeCode nan"),
}


@pytest.mark.parametrize("case", sorted(METADATA_CASES))
def test_bad_stage_metadata(tmp_path, capfd, case):
    edit, message = METADATA_CASES[case]
    assert_refused(edited_rig(tmp_path, edit), capfd, message)


# -- 5. USD's diagnostics are trapped --------------------------------------------------------

@pytest.mark.parametrize("trap", [True, False], ids=["DiagnosticTrap", "stderr-redirect"])
def test_usd_diagnostics_never_reach_stderr(tmp_path, capfd, monkeypatch, trap):
    """'Warning: in _Init at line 99 …' (bindTransforms size) used to be printed by USD. Without
    ``Tf.DiagnosticTrap`` (older USD) the C-level stderr is redirected, and restored after."""
    if not trap:
        monkeypatch.setattr(usd_format, "_TRAP", None)
    elif usd_format._TRAP is None:
        pytest.skip("this USD has no Tf.DiagnosticTrap")
    path = edited_rig(tmp_path, SKELETON_CASES["short bindTransforms"][0])
    assert_refused(path, capfd, "bindTransforms has 1 matrices")
    load_usd(build_rig(tmp_path / "good.usda"))
    os.write(2, b"still here\n")
    assert capfd.readouterr().err == "still here\n"


def test_fallback_redirect_is_shared_by_threads(tmp_path, capfd, monkeypatch):
    """Without the trap, overlapping users on several threads share one redirection of file
    descriptor 2, and the last one out restores it."""
    monkeypatch.setattr(usd_format, "_TRAP", None)
    anim = load_usd(build_rig(tmp_path / "rig.usda")).animations[0]
    with ThreadPoolExecutor(4) as pool:
        frames = list(pool.map(anim.local_transforms, [[t] for t in np.linspace(0, 4, 16)]))
    assert all(f.shape == (1, 3, 4, 4) for f in frames)
    os.write(2, b"restored\n")
    assert capfd.readouterr().err == "restored\n"


# -- the CLI ---------------------------------------------------------------------------------

@pytest.mark.parametrize("command,case,needle", [
    ("info", "weights missing", "primvars:skel:jointWeights is missing"),
    ("skin", "short rotations at a sample", "rotations has 1 values for 2 joints at time 2"),
])
def test_cli_reports_one_line(tmp_path, command, case, needle):
    cases = {**PRIMVAR_CASES, **ANIMATION_CASES}
    path = edited_rig(tmp_path, cases[case][0])
    args = [command, str(path)] + (["--out", str(tmp_path / "o.npz")] if command == "skin" else [])
    proc = subprocess.run([sys.executable, "-m", "dqskin.cli", *args], capture_output=True,
                          text=True, timeout=300)
    assert proc.returncode == 2, proc.stderr
    assert proc.stderr.startswith("dqskin: error:") and proc.stderr.count("\n") == 1, proc.stderr
    assert str(path) in proc.stderr and needle in proc.stderr, proc.stderr
