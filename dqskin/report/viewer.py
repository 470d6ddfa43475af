"""The animated WebGL viewer inside ``report.html``: compact vertex data and the page fragment.

Every compared method plays in sync in one three.js view (side by side or overlaid), one orbit
camera shared by all. The page stays one self-contained file: three.js (vendored in ``vendor/``,
inlined with its MIT licence notice) and :file:`viewer.js` are inlined, and the vertex data is one
zlib-compressed, base64 blob inside a ``<script type="application/octet-stream">`` element,
decompressed in the browser with ``DecompressionStream``.

The blob (before compression) holds these sections, each byte-aligned, offsets in the metadata:

* ``faces``: (T, 3) uint32 triangles, once for all methods and frames;
* ``rest``: (V, 3) positions of the rest pose, quantized (below);
* ``positions``: for each method ``m`` (in order) and frame ``f``, (V, 3) quantized positions as
  differences modulo 2¹⁶: method 0 against its previous frame (frame 0 against 0), every other
  method against method 0 at the same frame — small numbers where the motion is smooth and
  where the methods agree;
* ``heat``: (F, V) uint8, the per-vertex spread between the methods (the largest distance
  between any two of them), 0–255 over ``[0, heat_max]``; absent for a single method.

Positions are quantized on one grid for everything: ``q = round((p − origin) / step)`` in
uint16, ``step = largest extent / 65535`` (about 3·10⁻⁵ of the character's size). Each uint16
section is stored as two byte planes (all low bytes, then all high bytes), which deflate compresses
far better than interleaved bytes. 35k points × 48 frames × 3 methods come to a few MB.
"""

import base64
import json
import zlib
from collections.abc import Mapping
from importlib.resources import files
from typing import Any

import numpy as np
import numpy.typing as npt

from ..errors import InputError
from .defaults import VIEWER_FRAMES

__all__ = ["VIEWER_FRAMES", "decode", "encode", "viewer_html", "viewer_times"]


_GRID = 65535


def viewer_times(clip_times: npt.ArrayLike, compared: npt.ArrayLike,
                 count: int = VIEWER_FRAMES) -> np.ndarray:
    """The viewer's frame times: ``count`` evenly spaced times over the clip's range (all of the
    clip's own times when it has no more), merged with the compared times.

    Parameters
    ----------
    clip_times : (N,) float
        The asset's times (may be empty for a static scene).
    compared : (F,) float
    count : int
        ≥ 0; 0 gives the compared times alone.

    Returns
    -------
    (F',) float64, sorted, unique.
    """
    if int(count) != count or count < 0:
        raise InputError(f"viewer frames: expected an integer >= 0, got {count!r}")
    clip = np.asarray(clip_times, dtype=np.float64).reshape(-1)
    extra = np.zeros(0)
    if count and clip.size:
        extra = clip if clip.size <= count else np.linspace(clip.min(), clip.max(), int(count))
    return np.union1d(np.asarray(compared, dtype=np.float64).reshape(-1), extra)


def _planes(q: np.ndarray) -> bytes:
    """uint16 array → its low-byte plane followed by its high-byte plane."""
    b = np.ascontiguousarray(q, dtype="<u2").reshape(-1).view(np.uint8).reshape(-1, 2)
    return np.ascontiguousarray(b.T).tobytes()


def _spread(posed: Mapping[str, np.ndarray]) -> np.ndarray:
    """(F, V) largest distance between any two methods' points (float32)."""
    arrays = list(posed.values())
    out = np.zeros(arrays[0].shape[:2], dtype=np.float32)
    for i in range(len(arrays)):
        for j in range(i + 1, len(arrays)):
            d = arrays[i] - arrays[j]
            np.maximum(out, np.sqrt(np.einsum("...k,...k->...", d, d)), out=out)
    return out


def encode(posed: Mapping[str, npt.ArrayLike], rest: npt.ArrayLike, faces: npt.ArrayLike, *,
           level: int = 1) -> tuple[dict[str, Any], bytes]:
    """The viewer's metadata and compressed vertex data.

    Parameters
    ----------
    posed : dict method → (F, V, 3) float
        Every method's points at the viewer's frames, same space and vertex order.
    rest : (V, 3) float
    faces : (T, 3) int
    level : int
        zlib compression level (1: much faster than 6 for slightly more bytes).

    Returns
    -------
    meta : dict
        JSON-safe: ``vertices``, ``faces``, ``frames``, ``methods``, ``origin`` (3,), ``step``,
        ``heat_max`` (None for one method), ``sections``: name → ``[offset, length]`` in bytes
        of the decompressed blob.
    blob : bytes
        zlib stream (RFC 1950) of the sections.
    """
    methods = list(posed)
    arrays = [np.asarray(posed[m], dtype=np.float32) for m in methods]
    frames, count = arrays[0].shape[:2]
    r = np.asarray(rest, dtype=np.float32).reshape(count, 3)
    lo = np.minimum(r.min(axis=0), np.min([a.min(axis=(0, 1)) for a in arrays], axis=0))
    hi = np.maximum(r.max(axis=0), np.max([a.max(axis=(0, 1)) for a in arrays], axis=0))
    lo, hi = lo.astype(np.float64), hi.astype(np.float64)
    step = max(float(np.max(hi - lo)) / _GRID, 1e-30)
    origin, scale = lo.astype(np.float32), np.float32(1.0 / step)

    def quantize(p):  # float32 is exact enough: 16-bit results
        out = np.subtract(p, origin, dtype=np.float32)
        out *= scale
        np.rint(out, out=out)
        np.clip(out, 0, _GRID, out=out)
        return out.astype(np.uint16)

    q = np.stack([quantize(a) for a in arrays])  # (M, F, V, 3) uint16
    diff = q.copy()  # uint16 arithmetic wraps modulo 2¹⁶
    diff[0, 1:] -= q[0, :-1]
    diff[1:] -= q[0][None]
    sections = {"faces": np.ascontiguousarray(faces, dtype="<u4").tobytes(),
                "rest": _planes(quantize(r)), "positions": _planes(diff)}
    heat_max = None
    if len(methods) > 1:
        spread = _spread(dict(zip(methods, arrays)))
        heat_max = float(spread.max()) if spread.size else 0.0
        scale = 255.0 / heat_max if heat_max > 0 else 0.0
        sections["heat"] = np.rint(spread * scale).astype(np.uint8).tobytes()
    offsets: dict[str, list[int]] = {}
    raw: list[bytes] = []
    at = 0
    for name, data in sections.items():
        offsets[name] = [at, len(data)]
        raw.append(data)
        at += len(data)
    meta = {"vertices": int(count), "faces": int(np.shape(faces)[0]), "frames": int(frames),
            "methods": methods, "origin": [float(v) for v in lo], "step": step,
            "heat_max": heat_max, "sections": offsets}
    return meta, zlib.compress(b"".join(raw), level)


def decode(meta: Mapping[str, Any], blob: bytes) -> dict[str, Any]:
    """Inverse of :func:`encode` (what ``viewer.js`` does), for tests and tools.

    Returns
    -------
    dict
        ``faces`` (T, 3) int64, ``rest`` (V, 3) float64, ``positions`` method → (F, V, 3)
        float64, ``heat`` (F, V) float64 or None.
    """
    raw = zlib.decompress(blob)
    v, f, t = meta["vertices"], meta["frames"], meta["faces"]

    def section(name):
        at, n = meta["sections"][name]
        return np.frombuffer(raw, np.uint8, n, at)

    def unplane(b):
        half = b.size // 2
        return b[:half].astype(np.int64) | (b[half:].astype(np.int64) << 8)

    origin, step = np.array(meta["origin"]), meta["step"]
    d = unplane(section("positions")).reshape(len(meta["methods"]), f, v, 3)
    q = d.copy()
    q[0] = np.cumsum(d[0], axis=0) % 65536
    q[1:] = (d[1:] + q[0][None]) % 65536
    heat = None
    if "heat" in meta["sections"]:
        heat = section("heat").reshape(f, v) * (meta["heat_max"] / 255.0)
    return {"faces": np.frombuffer(raw, "<u4", 3 * t, meta["sections"]["faces"][0])
            .reshape(t, 3).astype(np.int64),
            "rest": origin + unplane(section("rest")).reshape(v, 3) * step,
            "positions": {m: origin + q[i] * step for i, m in enumerate(meta["methods"])},
            "heat": heat}


def _asset(*parts: str) -> str:
    return files("dqskin.report").joinpath(*parts).read_text(encoding="utf-8")


def _script_json(value: object) -> str:
    """JSON safe inside a ``<script>`` element (no ``</``, no ``<!--``)."""
    return json.dumps(value, ensure_ascii=False, allow_nan=False).replace("<", "\\u003c")


def viewer_html(meta: Mapping[str, Any], blob: bytes, settings: Mapping[str, Any]) -> str:
    """The viewer's HTML fragment: a canvas, its controls, three.js, the data and viewer.js.

    Parameters
    ----------
    meta, blob
        From :func:`encode`.
    settings : dict
        JSON-safe page settings read by viewer.js: ``times`` (F,), ``labels`` and ``colors``
        (per method), ``up_axis``, ``fps`` (time codes per second), ``worst`` (list of
        ``{"time", "why"}``), ``heat_label``; optionally ``heat_max`` and ``heat_unit`` (the
        heat range as the legend states it: the report gives % of the character's height).

    Returns
    -------
    str
    """
    data = base64.b64encode(blob).decode("ascii")
    config = dict(settings, meta=meta)
    return (
        '<div id="dqskin-viewer" class="viewer">'
        '<div class="viewer-bar">'
        '<button type="button" id="dqv-play">Pause</button>'
        '<input type="range" id="dqv-frame" min="0" value="0" step="1" '
        'aria-label="frame">'
        '<span id="dqv-time" class="note"></span>'
        '<label><input type="checkbox" id="dqv-heat"> heat map</label>'
        '<label><input type="checkbox" id="dqv-rest"> rest pose</label>'
        '<label><input type="checkbox" id="dqv-overlay"> overlaid</label>'
        '<label><input type="checkbox" id="dqv-ab"> A/B</label>'
        '<select id="dqv-a" aria-label="method A"></select>'
        '<select id="dqv-b" aria-label="method B"></select>'
        '<button type="button" id="dqv-flip" title="show the other method (key F)">flip</button>'
        '</div>'
        '<div class="viewer-bar"><span id="dqv-methods" class="legend"></span>'
        '<span id="dqv-legend" class="legend"></span>'
        '<span id="dqv-worst"></span></div>'
        '<div id="dqv-stage"><canvas id="dqv-canvas"></canvas>'
        '<div id="dqv-status" class="note">loading the viewer…</div></div>'
        '</div>\n'
        f'<script type="application/json" id="dqv-config">{_script_json(config)}</script>\n'
        f'<script type="application/octet-stream" id="dqv-data">{data}</script>\n'
        f'<script>/*! three.js r187 (npm three@0.187.0), bundled by esbuild.\n'
        f'{_asset("vendor", "THREE_LICENSE").replace("*/", "* /")}*/\n'
        f'{_asset("vendor", "three.min.js")}</script>\n'
        f'<script>{_asset("viewer.js")}</script>\n')


VIEWER_CSS = """
.viewer { margin: 0.6em 0 1.2em; }
.viewer-bar { display: flex; gap: 12px; align-items: center; flex-wrap: wrap; margin: 4px 0; }
.viewer-bar input[type=range] { flex: 1 1 300px; }
.viewer-bar button { font: inherit; padding: 2px 10px; }
#dqv-stage { position: relative; width: 100%; height: 520px; border: 1px solid #ddd;
             background: #fafafa; }
#dqv-canvas { width: 100%; height: 100%; display: block; }
#dqv-status { position: absolute; left: 8px; bottom: 6px; }
.legend { display: flex; gap: 14px; flex-wrap: wrap; font-size: 0.92em; }
.legend span.sw { display: inline-block; width: 10px; height: 10px; margin-right: 4px; }
"""
"""Styles of the viewer fragment (added to the report's CSS)."""
