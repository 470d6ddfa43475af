"""``dqskin compare``: outputs and their schema, metric values on the procedural rigs against the
closed forms of assets/README.md's geometry, the self-contained report, the sweeps, bad input and
``--force``.

Oracles: the twist rig is a radius-1 cylinder along +X, ``root/twist`` at x = 2 turning 7.5° per
frame about +X, weights ``(1 − w, w)`` on a linear ramp of width f·L = 2 (f = ½) centred at the
joint, 65 rings over 0 ≤ x ≤ 4 (assets/README.md). A ring of weight w is turned by the blended
transform: LBS maps it to ``((1 − w) + w·e^{iθ})·p`` in the complex (y, z) plane, radius factor
``k = √(1 − 2w(1−w)(1 − cos θ))``; DQS turns it rigidly by the angle of the normalized blend of
the two rotation quaternions, ``ψ(w) = 2·atan2(w sin(θ/2), 1 − w + w cos(θ/2))``.
"""

import base64
import io
import json
import re
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import trimesh
from PIL import Image

import dqskin
from dqskin.cli import build_parser
from dqskin.report.compare import run_compare, sweeps
from dqskin.report.render import VIEWS
from dqskin.times import parse_frames

ASSETS = Path(__file__).resolve().parents[1] / "assets"
TWIST = ASSETS / "twist_cylinder.usda"
MESH = "/TwistCylinder/Cylinder"
FRAMES = [0.0, 12.0, 24.0]
DEG_PER_FRAME = {"twist": 7.5, "bend": 5.0}
FRACTION = {"twist": 0.5, "bend": 0.25}
# Ring spacing in weight units: (length / 64 ring intervals) / ramp width f·L.
RING_DW = {"twist": (4 / 64) / 2, "bend": (4 / 64) / 1}
SEGMENTS = 32  # vertices around each ring


def _lbs_factor(w, theta):
    return np.sqrt(np.maximum(1 - 2 * w * (1 - w) * (1 - np.cos(theta)), 0.0))


def _dqs_angle(w, theta):
    return 2 * np.arctan2(w * np.sin(theta / 2), 1 - w + w * np.cos(theta / 2))


def _max_ring_turn(theta, method, dw):
    """Largest turn between consecutive rings (weights k·dw) about the axis; a ring shrunk to a
    point turns nothing (the bands next to it are cones)."""
    w = np.arange(round(1 / dw) + 1) * dw
    if method == "lbs":
        phi = np.arctan2(w * np.sin(theta), 1 - w + w * np.cos(theta))
        radius = _lbs_factor(w, theta)
    else:
        phi, radius = _dqs_angle(w, theta), np.ones_like(w)
    turn = np.abs(np.angle(np.exp(1j * np.diff(phi))))
    return turn[(radius[:-1] > 1e-9) & (radius[1:] > 1e-9)].max()


def _volume_tolerance(theta, method, rig="twist"):
    """Meshed vs continuum volume ratio on the ramp (a fraction f of the volume).

    A band between two rings ``a·p_j`` and ``b·p_j`` (complex scale factors, ``p_j = e^{iβj}``,
    β = 2π/N, turned by Δ relative to each other) is a prismatoid, ``V = h(A₁ + 4A_m + A₂)/6``.
    Its mid-section runs through the midpoints of the ring-to-ring edges, ``(a + b)p_j/2``, and
    of the quad diagonals, ``(a p_j + b p_{j+1})/2``: per quad its area is
    ``|a+b|² sin β/8 − |a||b| sin Δ (1 − cos β)/2`` (shoelace formula), so the diagonals change the
    band's volume by at most ``(2/3)|Δ| tan(β/2)`` of it, and the ruled mid-section
    ``|a+b|²/4`` differs from the turned ring's by ``O(Δ²)`` (≤ Δ² relative). Integrating k²
    ring by ring costs ≤ Δw²·max|d²k²/dw²|/12 ≤ (1 − cos θ)Δw². Float32 skinning adds ~1e-6.
    """
    dw, turn = RING_DW[rig], _max_ring_turn(theta, method, RING_DW[rig])
    return FRACTION[rig] * ((2 / 3) * turn * np.tan(np.pi / SEGMENTS) + turn ** 2
                            + (1 - np.cos(theta)) * dw ** 2) + 1e-5


def _twist_oracle_volume(theta):
    """Volume ratio of the twist rig skinned in float64 straight from the blend equations (README
    motion: ``root/twist`` turns about +X), measured by trimesh (independent of dqskin)."""
    from pxr import Usd, UsdGeom

    stage = Usd.Stage.Open(str(TWIST))
    mesh = UsdGeom.Mesh(stage.GetPrimAtPath(MESH))
    p = np.array(mesh.GetPointsAttr().Get(), dtype=np.float64)
    counts = np.array(mesh.GetFaceVertexCountsAttr().Get())
    flat = np.array(mesh.GetFaceVertexIndicesAttr().Get())
    starts = np.concatenate([[0], np.cumsum(counts)[:-1]])
    faces = np.array([[flat[s], flat[s + k], flat[s + k + 1]] for s, n in zip(starts, counts)
                      for k in range(1, n - 1)])
    w = np.clip((p[:, 0] - 1) / 2, 0, 1)  # linear ramp x ∈ [1, 3]
    yz = p[:, 1] + 1j * p[:, 2]
    posed = {"lbs": ((1 - w) + w * np.exp(1j * theta)) * yz,
             "dqs": np.exp(1j * _dqs_angle(w, theta)) * yz}
    rest = trimesh.Trimesh(p, faces, process=False).volume
    return {m: trimesh.Trimesh(np.stack([p[:, 0], q.real, q.imag], 1), faces,
                               process=False).volume / rest for m, q in posed.items()}


def _lbs_ring_section(theta, rig):
    """LBS min section ratio: the ring of share w = ½ (a ring of both rigs, alone in its ring of
    width 1/32) shrinks to k = |cos(θ/2)| in a twist (both axes) and to √k in a bend (one axis);
    every other ring shrinks less (float32 skinning: ~1e-6)."""
    k = abs(np.cos(theta / 2))
    return k if rig == "twist" else np.sqrt(k)


def _reject_nan(name):
    raise AssertionError(f"metrics.json holds {name}")


@pytest.fixture(scope="module")
def twist(tmp_path_factory):
    out = tmp_path_factory.mktemp("twist")
    result = run_compare(TWIST, out, frames=FRAMES, width=48, supersample=1, progress=False,
                         device="cpu")
    return out, result


def test_outputs_and_schema(twist):
    out, result = twist
    assert (out / "report.html").is_file()
    saved = json.loads((out / "metrics.json").read_text(encoding="utf-8"),
                       parse_constant=_reject_nan)
    assert saved == json.loads(json.dumps(result))
    assert saved["asset"].endswith("twist_cylinder.usda")
    assert saved["methods"] == ["lbs", "dqs"] and saved["frames"] == FRAMES
    assert list(saved["meshes"]) == [MESH]
    for method in ("lbs", "dqs"):
        m = saved["meshes"][MESH][method]
        assert m["volume_ratio_reason"] is None
        for key in ("volume_ratio", "min_section_ratio", "max_bulge_ratio"):
            assert len(m[key]) == len(FRAMES) and all(isinstance(v, float) for v in m[key])
        assert m["min_section_joint"] == ["root/twist"] * len(FRAMES)
    for view in VIEWS:
        paths = saved["images"]["frames"][view]
        assert paths == [f"frames/{view}_{k:03d}.png" for k in range(len(FRAMES))]
        for p in paths:
            with Image.open(out / p) as img:
                img.verify()
    assert saved["images"]["closeup"] == "frames/closeup.png"
    assert sorted(p.name for p in (out / "frames").iterdir()) == sorted(
        [f"{v}_{k:03d}.png" for v in VIEWS for k in range(len(FRAMES))] + ["closeup.png"])


def test_twist_metrics_match_closed_forms(twist):
    _, result = twist
    theta = np.radians(DEG_PER_FRAME["twist"] * np.array(FRAMES))
    lbs, dqs = result["meshes"][MESH]["lbs"], result["meshes"][MESH]["dqs"]
    for k, th in enumerate(theta):
        assert lbs["min_section_ratio"][k] == pytest.approx(_lbs_ring_section(th, "twist"),
                                                           abs=1e-3)
        assert dqs["min_section_ratio"][k] == pytest.approx(1.0, abs=1e-4)
        assert lbs["volume_ratio"][k] == pytest.approx(
            1 - FRACTION["twist"] * (1 - np.cos(th)) / 3, abs=_volume_tolerance(th, "lbs"))
        assert dqs["volume_ratio"][k] == pytest.approx(1.0, abs=_volume_tolerance(th, "dqs"))
        exact = _twist_oracle_volume(th)  # the same polyhedra, float64
        assert lbs["volume_ratio"][k] == pytest.approx(exact["lbs"], abs=2e-5)
        assert dqs["volume_ratio"][k] == pytest.approx(exact["dqs"], abs=2e-5)
        # Neither method pushes a ring outward: LBS rings only shrink, DQS rings keep radius 1.
        assert lbs["max_bulge_ratio"][k] <= 1 + 1e-5
        assert dqs["max_bulge_ratio"][k] == pytest.approx(1.0, abs=1e-4)
    # The joint's twist beside the value: 90° at frame 12, bend 0.
    assert lbs["min_section_twist_deg"][1] == pytest.approx(90.0, abs=1e-3)
    assert lbs["min_section_bend_deg"][1] == pytest.approx(0.0, abs=1e-3)
    # Largest LBS↔DQS distance per frame: |(1 − w) + w·e^{iθ} − e^{iψ(w)}| over the ring weights
    # (cap vertices have w ∈ {0, 1}: distance 0).
    w = np.arange(33)[None] / 32
    th = theta[:, None]
    gap = np.abs((1 - w) + w * np.exp(1j * th) - np.exp(1j * _dqs_angle(w, th))).max(axis=1)
    # in % of the character's height: the rig's largest extent, its length 4 (0 ≤ x ≤ 4)
    assert result["character_height"] == pytest.approx(4.0, abs=1e-6)
    assert result["distance_unit"] == "% of character_height"
    gap = gap / 4.0 * 100
    np.testing.assert_allclose(result["lbs_dqs_distance"][MESH]["max"], gap, atol=1e-3)
    # Summary: DQS keeps volume and sections; the worst LBS frame is the 180° one.
    s = result["summary"]
    assert s["min_section_ratio"]["winner"] == "dqs" and s["volume_ratio"]["winner"] == "dqs"
    assert s["min_section_ratio"]["by_method"]["lbs"]["time"] == FRAMES[-1]
    assert s["min_section_ratio"]["by_method"]["lbs"]["joint"] == "root/twist"
    assert result["closeup"]["method"] == "lbs" and result["closeup"]["joint"] == "root/twist"
    assert result["closeup"]["frame"] == len(FRAMES) - 1
    assert result["images"]["heat_range"][1] == pytest.approx(gap.max(), abs=1e-3)


def test_report_is_self_contained(twist):
    out, _ = twist
    text = (out / "report.html").read_text(encoding="utf-8")
    # The only URLs are XML namespace names in three.js (identifiers, never fetched).
    urls = set(re.findall(r"https?://[^\s\"'`)]*", text, re.IGNORECASE))
    assert urls <= {"http://www.w3.org/1999/xhtml", "http://www.w3.org/2000/svg"}, urls
    assert not re.search(r"<(link|iframe|object|embed)\b", text, re.IGNORECASE)
    # Scripts only inline: three.js, the viewer and its data; none with a src.
    scripts = re.findall(r"<script\b[^>]*>", text, re.IGNORECASE)
    assert len(scripts) == 4 and not any("src" in tag for tag in scripts)
    assert "url(" not in text
    refs = re.findall(r"""\b(?:src|href)\s*=\s*["']([^"']*)["']""", text, re.IGNORECASE)
    images = re.findall(r"<img\b[^>]*>", text, re.IGNORECASE)
    # frame plots, close-up, sweeps, and the three views of each worst frame
    assert len(images) >= 6 and len(refs) == len(images)
    for tag in images:
        src = re.search(r'src="data:image/png;base64,([A-Za-z0-9+/=]+)"', tag)
        assert src, tag[:80]
        with Image.open(io.BytesIO(base64.b64decode(src.group(1), validate=True))) as img:
            assert img.format == "PNG"
            img.load()
            assert img.width > 0 and img.height > 0


def _bend_oracle_volume(theta):
    """LBS volume ratio of the bending arm in float64 from README's motion alone: the elbow turns
    about +Z through (2, 0, 0); measured by trimesh (independent of dqskin.metrics)."""
    scene = dqskin.load(ASSETS / "bending_arm.usda")
    m = scene.meshes[0]
    p = np.asarray(m.points, dtype=np.float64)
    w = np.where(m.joint_indices == 1, m.joint_weights, 0).sum(axis=1)[:, None]
    c, s = np.cos(theta), np.sin(theta)
    q = p - [2.0, 0, 0]
    turned = np.stack([c * q[:, 0] - s * q[:, 1], s * q[:, 0] + c * q[:, 1], q[:, 2]], 1)
    turned += [2.0, 0, 0]
    posed = (1 - w) * p + w * turned
    return (trimesh.Trimesh(posed, m.faces, process=False).volume
            / trimesh.Trimesh(p, m.faces, process=False).volume)


def test_sweeps_reproduce_the_classic_curves(twist):
    _, result = twist
    sw = result["sweeps"]
    twist_rig, bend = sw["twist"], sw["bend"]
    np.testing.assert_allclose(twist_rig["angle_deg"], 7.5 * np.arange(25), atol=1e-3)
    np.testing.assert_allclose(bend["angle_deg"], 5.0 * np.arange(31), atol=1e-3)
    for k, th in enumerate(np.radians(twist_rig["angle_deg"])):
        assert twist_rig["lbs"]["min_section_ratio"][k] == pytest.approx(
            _lbs_ring_section(th, "twist"), abs=1e-3)
        assert twist_rig["dqs"]["min_section_ratio"][k] == pytest.approx(1.0, abs=1e-4)
        assert twist_rig["lbs"]["volume_ratio"][k] == pytest.approx(
            1 - FRACTION["twist"] * (1 - np.cos(th)) / 3, abs=_volume_tolerance(th, "lbs"))
        assert twist_rig["dqs"]["volume_ratio"][k] == pytest.approx(
            1.0, abs=_volume_tolerance(th, "dqs"))
    np.testing.assert_allclose(twist_rig["reference"]["lbs_min_section_ratio"],
                               np.abs(np.cos(np.radians(7.5 * np.arange(25)) / 2)), atol=1e-6)
    theta = np.radians(bend["angle_deg"])
    # Bend: rings measured in their own frame, so the closed forms hold at any angle.
    np.testing.assert_allclose(bend["lbs"]["min_section_ratio"],
                               [_lbs_ring_section(th, "bend") for th in theta], atol=1e-4)
    np.testing.assert_allclose(bend["reference"]["lbs_min_section_ratio"],
                               np.sqrt(np.abs(np.cos(theta / 2))), atol=1e-9)
    np.testing.assert_allclose(bend["dqs"]["min_section_ratio"], 1.0, atol=1e-4)
    np.testing.assert_allclose(bend["dqs"]["max_bulge_ratio"], 1.0, atol=1e-4)
    assert np.all(np.array(bend["lbs"]["max_bulge_ratio"]) <= 1 + 1e-4)
    lbs = np.array(bend["lbs"]["volume_ratio"])
    # Exact polyhedron (float64 oracle), then the continuum curve 1 − f(1 − cos θ)/6 (derived in
    # dqskin.compare.SWEEP_RIGS): the meshed deficit stays within O(Δw²) of it, Δw = 1/16 (the
    # bound 4Δw² ≈ 1.6% relative is chosen, not derived, for the bend; DQS likewise reuses the
    # twist's band bound with the bend's ring turns).
    for k in (10, 30):
        assert lbs[k] == pytest.approx(_bend_oracle_volume(theta[k]), abs=2e-5)
    deficit = FRACTION["bend"] * (1 - np.cos(theta)) / 6
    np.testing.assert_allclose(np.array(bend["reference"]["lbs_volume_ratio"]), 1 - deficit,
                               atol=1e-9)
    np.testing.assert_allclose(1 - lbs, deficit, rtol=4 * RING_DW["bend"] ** 2, atol=1e-5)
    dqs_tol = [_volume_tolerance(th, "dqs", "bend") for th in theta]
    assert np.all(np.abs(np.array(bend["dqs"]["volume_ratio"]) - 1) <= dqs_tol)


def test_multi_mesh_scene_renders_together(tmp_path, device):
    result = run_compare(ASSETS / "humanoid.usda", tmp_path, methods=("dqs", "blend"),
                         frames=[0, 12], views=("front",), width=32, supersample=1,
                         progress=False, sweeps_dir=None, device=device)
    names = ["Body", "Arm_L", "Arm_R", "Leg_L", "Leg_R", "Foot_L", "Foot_R"]
    assert sorted(result["meshes"]) == sorted(f"/Humanoid/{n}" for n in names)
    assert result["render"]["vertices"] == 5302  # assets/README.md
    assert result["blend_weight"] == 0.5 and result["lbs_dqs_distance"] is None
    for name in ("Foot_L", "Foot_R"):  # rigid: one influence, no joint region
        assert result["meshes"][f"/Humanoid/{name}"]["dqs"]["min_section_ratio"] == [None, None]
    for per in result["meshes"].values():
        assert per["blend"]["volume_ratio"] is not None  # every mesh is closed
    assert (tmp_path / "frames" / "front_001.png").is_file()
    html = (tmp_path / "report.html").read_text(encoding="utf-8")
    assert "Sweeps left out (not asked for)" in html and "--no-sweeps" not in html


def _write_faceless(path):
    """A copy of the twist rig without topology (edits the copy: never the shared asset's
    in-memory layer, which other open stages would then see)."""
    import shutil

    from pxr import Usd

    shutil.copyfile(TWIST, path)
    stage = Usd.Stage.Open(str(path))
    prim = stage.GetPrimAtPath(MESH)
    for name in ("faceVertexCounts", "faceVertexIndices", "normals", "primvars:st",
                 "primvars:st:indices"):
        prim.RemoveProperty(name)
    stage.GetRootLayer().Save()


def test_bad_input(tmp_path):
    out = tmp_path / "out"
    with pytest.raises(ValueError, match="no such file"):
        run_compare(tmp_path / "missing.usda", out, progress=False)
    faceless = tmp_path / "faceless.usda"
    _write_faceless(faceless)
    with pytest.raises(ValueError, match="no faces"):
        run_compare(faceless, out, progress=False)
    scene = dqskin.load(TWIST)
    empty = replace(scene.meshes[0], points=np.zeros((0, 3), np.float32),
                    faces=np.zeros((0, 3), np.int32), joint_indices=np.zeros((0, 2), np.int32),
                    joint_weights=np.zeros((0, 2), np.float32))
    with pytest.raises(ValueError, match="no points"):
        run_compare(replace(scene, meshes=[empty]), out, progress=False)
    assert not out.exists()  # nothing written for bad input
    for kwargs, needle in ((dict(methods=("lbs", "magic")), "methods"),
                           (dict(views=("top",)), "views"), (dict(width=0), "width"),
                           (dict(frames=[]), "frames"), (dict(frames=[0, np.nan]), "frames")):
        with pytest.raises(ValueError, match=needle):
            run_compare(TWIST, out, progress=False, **kwargs)
    for text in ("a:b", "0:1:2:3", "5:1", "0:4:0", "1,x"):
        with pytest.raises(ValueError, match="^frames="):
            parse_frames(text)


def _tree(folder):
    """Every file under ``folder`` (hidden ones too) → its bytes."""
    return {p.relative_to(folder).as_posix(): p.read_bytes()
            for p in sorted(folder.rglob("*")) if p.is_file()}


def test_existing_report_needs_force(tmp_path, device):
    """The report folder is written whole: an earlier report blocks it without force and is
    replaced whole (its stale panels gone) with it; a folder holding anything else is never
    replaced; an empty folder is fine."""
    small = dict(frames=[0, 24], views=("front",), width=24, supersample=1, progress=False,
                 sweeps_dir=None, viewer_frames=0, device=device)
    out = tmp_path / "out"
    frames = out / "frames"
    out.mkdir()
    run_compare(TWIST, out, **small)  # an empty folder
    assert sorted(p.name for p in frames.iterdir()) == ["closeup.png", "front_000.png",
                                                        "front_001.png"]
    (frames / "front_099.png").write_bytes(b"stale panel")
    before = _tree(out)
    with pytest.raises(FileExistsError, match="use force=True to overwrite"):
        run_compare(TWIST, out, **small)
    assert _tree(out) == before and sorted(p.name for p in tmp_path.iterdir()) == ["out"]
    run_compare(TWIST, out, force=True, **small)
    assert not (frames / "front_099.png").exists()  # replaced whole: no stale panel
    assert (out / "report.html").read_text(encoding="utf-8").startswith("<!DOCTYPE html>")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out"]  # nothing left beside it
    (frames / "notes.txt").write_text("mine")
    before = _tree(out)
    for force in (False, True):
        with pytest.raises(FileExistsError, match=r"not a dqskin report \('frames/notes.txt'\)"):
            run_compare(TWIST, out, force=force, **small)
        assert _tree(out) == before


@pytest.mark.parametrize("stage", ["render", "report"])
def test_interrupted_compare_leaves_nothing(tmp_path, monkeypatch, device, stage):
    """An interrupt (here raised where a signal would land: after the first panel, or while the
    page is built) leaves no new file: a new report folder is not created, and an earlier
    report with other methods stays exactly as it was under force."""
    import signal

    import dqskin.report.compare as compare
    from dqskin.errors import Interrupted

    small = dict(frames=[0, 24], views=("front",), width=24, supersample=1, progress=False,
                 sweeps_dir=None, viewer_frames=0, device=device)
    old = tmp_path / "old"
    run_compare(TWIST, old, methods=("lbs",), **small)
    before = _tree(old)

    def interrupt(*args, **kwargs):
        raise Interrupted(signal.SIGINT)

    if stage == "render":
        save_png = compare.save_png

        def first_then_interrupt(path, image):
            save_png(path, image)
            interrupt()
        monkeypatch.setattr(compare, "save_png", first_then_interrupt)
    else:
        monkeypatch.setattr(compare, "build_html", interrupt)
    for out, force in ((tmp_path / "new", False), (old, True)):
        with pytest.raises(Interrupted):
            run_compare(TWIST, out, methods=("lbs", "dqs", "blend"), force=force, **small)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["old"]
    assert _tree(old) == before


def test_command_line(tmp_path, capsys, device):
    parser = build_parser()
    args = parser.parse_args(["compare", str(TWIST), "--out", str(tmp_path), "--frames",
                              "0:24:12", "--views", "front,side", "--methods", "lbs,dqs,blend",
                              "--width", "24", "--supersample", "1", "--no-sweeps", "--quiet",
                              "--device", device])
    assert args.run(args) == 0
    assert "report.html" in capsys.readouterr().out
    saved = json.loads((tmp_path / "metrics.json").read_text(encoding="utf-8"))
    assert saved["frames"] == FRAMES and saved["views"] == ["front", "side"]
    assert saved["methods"] == ["lbs", "dqs", "blend"] and saved["sweeps"] is None
    np.testing.assert_allclose(parse_frames("0, 6.5,12"), [0, 6.5, 12])
    bad = parser.parse_args(["compare", str(TWIST), "--out", str(tmp_path / "x"), "--methods",
                             "lbs,nope"])
    with pytest.raises(ValueError, match="nope"):
        bad.run(bad)


def test_progress_bar_only_on_a_terminal(tmp_path, capsys, monkeypatch, device):
    """Without --quiet, the bar is drawn on a terminal and nowhere else (a log gets none)."""
    import sys
    args = ["compare", str(TWIST), "--frames", "0:24:12", "--views", "front", "--methods",
            "lbs", "--width", "16", "--supersample", "1", "--no-sweeps", "--device", device]
    for tty, out in ((False, "a"), (True, "b")):
        monkeypatch.setattr(sys.stderr, "isatty", lambda tty=tty: tty)
        parsed = build_parser().parse_args([*args, "--out", str(tmp_path / out)])
        assert parsed.run(parsed) == 0
        err = capsys.readouterr().err
        assert ("compare" in err) is tty, err


def test_cameras_use_the_skeleton_spaces_up_axis(shared_assets):
    """usd-wg's CesiumMan keeps its skeleton under a Z_UP group (−90° about x) on a Y-up stage,
    so its skeleton space is Z-up; the glTF's skeleton space is the Y-up world."""
    from dqskin.report.compare import skeleton_up_axis
    usdz = dqskin.load(shared_assets / "usd-wg" / "CesiumMan" / "CesiumMan.usdz")
    glb = dqskin.load(shared_assets / "khronos-gltf" / "CesiumMan" / "CesiumMan.glb")
    assert usdz.up_axis == "Y" and skeleton_up_axis(usdz) == "Z"
    assert skeleton_up_axis(glb) == "Y"
    assert skeleton_up_axis(dqskin.load(TWIST)) == "Y"


def test_sweeps_show_every_method():
    sw = sweeps(ASSETS, methods=("blend",), options=dqskin.SkinOptions(device="cpu"))
    for rig in ("twist", "bend"):
        entry = sw[rig]
        assert entry["methods"] == ["lbs", "dqs", "blend"]
        lbs, dqs, blend = (np.array(entry[m]["min_section_ratio"]) for m in entry["methods"])
        # the 50/50 blend of the two results lies between them, strictly once LBS collapses
        assert np.all(lbs - 1e-6 <= blend) and np.all(blend <= dqs + 1e-6)
        assert blend[-1] > lbs[-1] + 0.1
