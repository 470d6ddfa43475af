"""The report's animated viewer, Python side: the compact vertex data decodes to the skinned points
within half a quantization step, the heat map is the methods' largest pairwise distance, the
frame times, the inlined scripts are safe in HTML, and the size budget (≤ 20 MB for a 35k-point
character × 48 frames × 3 methods). The browser side is in test_report_browser.py."""

import base64
import importlib.util
import json
import re
import zlib
from pathlib import Path

import numpy as np
import pytest

from dqskin.report.compare import run_compare
from dqskin.report.viewer import decode, encode, viewer_html, viewer_times

ROOT = Path(__file__).resolve().parents[1]


def _motion(rng, frames, count):
    """Smooth random motion: rest points turned and moved a little more each frame."""
    rest = rng.normal(size=(count, 3)) * [0.3, 0.9, 0.2]
    t = np.linspace(0, 1, frames)[:, None, None]
    wobble = np.sin(3 * t + rest[None, :, :1]) * 0.05
    return rest, rest[None] + wobble + t * [0.4, 0.0, -0.2]


def test_round_trip_and_heat():
    rng = np.random.default_rng(7)
    rest, lbs = _motion(rng, 9, 500)
    posed = {"lbs": lbs, "dqs": lbs + rng.normal(scale=0.01, size=lbs.shape),
             "cor": lbs - 0.02}
    faces = rng.integers(0, 500, size=(300, 3))
    meta, blob = encode(posed, rest, faces)
    assert meta["vertices"] == 500 and meta["frames"] == 9 and meta["faces"] == 300
    assert meta["methods"] == ["lbs", "dqs", "cor"]
    out = decode(meta, blob)
    np.testing.assert_array_equal(out["faces"], faces)
    # half a grid step, plus float32 rounding of the inputs (|p| < 4: 4 ulp ≈ 1e-6)
    half = 0.5 * meta["step"] + 1e-6
    np.testing.assert_allclose(out["rest"], rest, atol=half)
    for name, p in posed.items():
        np.testing.assert_allclose(out["positions"][name], p, atol=half)
    # grid step: the largest extent over 2¹⁶ − 1 steps
    every = np.concatenate([rest[None]] + list(posed.values()))
    assert meta["step"] == pytest.approx(np.ptp(every.reshape(-1, 3), axis=0).max() / 65535)
    # heat: the largest distance between any two methods, per vertex and frame (NumPy oracle)
    a = np.stack(list(posed.values()))
    spread = np.linalg.norm(a[:, None] - a[None], axis=-1).max(axis=(0, 1))
    assert meta["heat_max"] == pytest.approx(spread.max(), rel=1e-5)
    np.testing.assert_allclose(out["heat"], spread, atol=0.5 * spread.max() / 255 + 1e-6)
    # one method: no heat section
    single, data = encode({"dqs": lbs}, rest, faces)
    assert single["heat_max"] is None and "heat" not in single["sections"]
    assert decode(single, data)["heat"] is None


def test_viewer_times():
    clip = np.arange(0, 101, 1.0)
    t = viewer_times(clip, [3.5, 50.0], count=48)
    assert t[0] == 0 and t[-1] == 100 and 3.5 in t and 50.0 in t
    assert len(t) <= 50 and np.all(np.diff(t) > 0)
    np.testing.assert_array_equal(viewer_times(np.arange(5.0), [2.0], count=48), np.arange(5.0))
    np.testing.assert_array_equal(viewer_times(clip, [7.0, 2.0], count=0), [2.0, 7.0])
    np.testing.assert_array_equal(viewer_times([], [1.0], count=10), [1.0])
    with pytest.raises(ValueError, match="viewer frames"):
        viewer_times(clip, [0.0], count=-1)


def test_fragment_is_safe_inline():
    vendor = ROOT / "dqskin" / "report" / "vendor"
    three = (vendor / "three.min.js").read_text(encoding="utf-8")
    assert "</script" not in three.lower() and "<!--" not in three
    assert (vendor / "THREE_LICENSE").read_text(encoding="utf-8").startswith("The MIT License")
    rest, lbs = _motion(np.random.default_rng(1), 2, 10)
    meta, blob = encode({"lbs": lbs}, rest, [[0, 1, 2]])
    html = viewer_html(meta, blob, {"labels": ["</script><!--"], "times": [0.0, 1.0]})
    assert html.count("</script>") == 4 and "<!--" not in html
    assert "Copyright © 2010-2026 three.js authors" in html  # the MIT notice travels with the code
    config = json.loads(re.search(r'id="dqv-config">(.*?)</script>', html, re.S).group(1))
    assert config["labels"] == ["</script><!--"] and config["meta"] == meta
    data = re.search(r'id="dqv-data">(.*?)</script>', html, re.S).group(1)
    assert base64.b64decode(data, validate=True) == blob
    zlib.decompress(blob)  # the zlib format DecompressionStream("deflate") reads


def test_no_viewer(tmp_path):
    result = run_compare(ROOT / "assets" / "bending_arm.usda", tmp_path, frames=[0, 30],
                         width=32, supersample=1, progress=False, sweeps_dir=None,
                         viewer_frames=0, device="cpu")
    assert "viewer" not in result
    assert "<script" not in (tmp_path / "report.html").read_text(encoding="utf-8")


def _bench_character():
    """The benchmark's 35.6k-vertex humanoid (tools/bench_compare.py)."""
    spec = importlib.util.spec_from_file_location("bench_compare", ROOT / "tools" /
                                                  "bench_compare.py")
    bench = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(bench)
    return bench.character()


def test_size_budget():
    scene = _bench_character()
    times = viewer_times(scene.times, [], count=48)
    assert len(times) == 48
    posed, offsets = {}, np.cumsum([0] + [len(m.points) for m in scene.meshes])
    for method in ("lbs", "dqs", "blend"):
        p = scene.skin(times, method, device="cpu", space="skeleton", blend_shapes=False).points
        posed[method] = np.concatenate([p[m.name] for m in scene.meshes], axis=1)
    faces = np.concatenate([m.faces + o for m, o in zip(scene.meshes, offsets[:-1])])
    rest = np.concatenate([m.points for m in scene.meshes])
    assert len(rest) >= 35000
    meta, blob = encode(posed, rest, faces)
    inlined = len(base64.b64encode(blob))
    print(f"viewer data: {inlined / 1e6:.1f} MB inlined for {len(rest)} points × 48 frames × 3 "
          "methods")
    assert inlined <= 20e6
    np.testing.assert_allclose(decode(meta, blob)["positions"]["dqs"], posed["dqs"],
                               atol=0.51 * meta["step"])


def test_cli_viewer_frames(tmp_path):
    from dqskin.cli import main

    out = tmp_path / "r"
    assert main(["compare", str(ROOT / "assets" / "twist_cylinder.usda"), "--out", str(out),
                 "--frames", "0,24", "--width", "32", "--supersample", "1", "--no-sweeps",
                 "--viewer-frames", "5", "--quiet", "--device", "cpu", "--full-supersample"]) == 0
    saved = json.loads((out / "metrics.json").read_text(encoding="utf-8"))
    assert saved["viewer"]["frames"] == [0.0, 6.0, 12.0, 18.0, 24.0]
    assert saved["render"]["antialiasing"] == "full"

