"""The HTML report of ``dqskin compare``: one self-contained file (CSS inline, every image a
``data:image/png;base64`` URI, the animated viewer's scripts and data inline, no network
reference) built from the metrics dictionary of :func:`dqskin.report.compare.run_compare` and the
panels it rendered. Plots are drawn with Matplotlib's Agg canvas (no pyplot, no display).
"""

import base64
import html
import io
import os
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from ..metrics import worst

if TYPE_CHECKING:
    from matplotlib.figure import Figure

__all__ = ["METRIC_TITLES", "build_html", "frame_plot_png", "method_color", "method_label",
           "sweep_plot_png"]

METRIC_TITLES = {
    "volume_ratio": "volume ratio",
    "min_section_ratio": "min section ratio",
    "max_bulge_ratio": "max bulge ratio",
}
"""Display names of the per-frame metrics."""

_COLORS = {"lbs": "#d62728", "dqs": "#1f77b4", "blend": "#9467bd", "cor": "#2ca02c"}
_NAMES = {"lbs": "LBS", "dqs": "DQS", "blend": "Blend", "cor": "CoR"}
_PALETTE = ("#ff7f0e", "#8c564b", "#e377c2", "#7f7f7f", "#bcbd22", "#17becf")


def _blend_note(m: dict) -> str:
    """The methods row's note on the blend's DQS fractions."""
    if m.get("blend_weight") is None:
        return ""
    own = m.get("blend_per_vertex") or {}
    if not own:
        return f" (blend: DQS fraction {m['blend_weight']:g} on every vertex)"
    means = ", ".join(f"{_esc(k)} mean {v:.3g}" for k, v in own.items())
    return (f" (blend: the asset's per-vertex DQS fractions: {means}; "
            f"{m['blend_weight']:g} on every vertex of other meshes)")


def method_label(method: str) -> str:
    """Display name of a skinning method (its upper-cased key when it has none)."""
    return _NAMES.get(method, str(method).upper())


def method_color(method: str) -> str:
    """Plot colour of a skinning method: fixed for the known ones, else from a palette."""
    if method in _COLORS:
        return _COLORS[method]
    return _PALETTE[sum(map(ord, str(method))) % len(_PALETTE)]

_MAX_WORST_FRAMES = 4
_ADAPTIVE_NOTE = " at edges (adaptive: one ray per pixel elsewhere)"

_CSS = """
body { font-family: system-ui, -apple-system, "Segoe UI", Roboto, sans-serif; margin: 24px;
       color: #222; max-width: 1400px; }
h1 { font-size: 1.6em; margin-bottom: 0.2em; }
h2 { margin-top: 1.6em; border-bottom: 1px solid #ccc; }
table { border-collapse: collapse; margin: 0.6em 0; font-size: 0.92em; }
th, td { border: 1px solid #ccc; padding: 4px 8px; text-align: right; vertical-align: top; }
th { background: #f3f3f3; } td.l, th.l { text-align: left; }
td.win { background: #e6f4ea; font-weight: 600; }
img { max-width: 100%; height: auto; display: block; margin: 6px 0 14px; border: 1px solid #eee; }
.note { color: #555; font-size: 0.9em; } .meta td { text-align: left; }
figure { margin: 0; } figcaption { font-size: 0.9em; color: #444; }
"""


def _esc(x: object) -> str:
    return html.escape(str(x), quote=True)


def _data_uri(png: bytes) -> str:
    return "data:image/png;base64," + base64.b64encode(png).decode("ascii")


def _img(png: bytes, alt: str) -> str:
    return f'<img src="{_data_uri(png)}" alt="{_esc(alt)}">'


def _fmt(v: float | None, digits: int = 4) -> str:
    return "—" if v is None else f"{v:.{digits}g}"


def _figure_png(fig: "Figure") -> bytes:
    from matplotlib.backends.backend_agg import FigureCanvasAgg

    FigureCanvasAgg(fig)
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=100)
    return buf.getvalue()


def _array(values: Sequence[float | None]) -> np.ndarray:
    return np.array([np.nan if v is None else v for v in values], dtype=np.float64)


def _scene_series(metrics: dict[str, Any], metric: str, method: str) -> np.ndarray:
    """Per-frame scene-wide extreme of a metric over the meshes (NaN where none is defined)."""
    rows = []
    for per_method in metrics["meshes"].values():
        v = per_method[method][metric]
        if v is not None:
            rows.append(_array(v))
    frames = len(metrics["frames"])
    if not rows:
        return np.full(frames, np.nan)
    a = np.stack(rows)
    out = np.full(frames, np.nan)
    for f in range(frames):
        w = worst(metric, a[:, f])
        if w is not None:
            out[f] = a[w[0], f]
    return out


def frame_plot_png(metrics: dict[str, Any]) -> bytes:
    """Per-frame plots of each metric (scene-wide worst over meshes) and of the LBS↔DQS distance.

    Returns
    -------
    bytes
        PNG image.
    """
    from matplotlib.figure import Figure

    t = np.asarray(metrics["frames"], dtype=np.float64)
    panels = list(METRIC_TITLES) + (["distance"] if metrics.get("lbs_dqs_distance") else [])
    fig = Figure(figsize=(5.2 * len(panels), 3.6))  # fixed margins: a layout engine is slow
    fig.subplots_adjust(left=0.04, right=0.99, bottom=0.14, top=0.91, wspace=0.2)
    for ax, metric in zip(fig.subplots(1, len(panels), squeeze=False)[0], panels):
        if metric == "distance":
            d = np.stack([_array(v["max"]) for v in metrics["lbs_dqs_distance"].values()])
            m = np.stack([_array(v["mean"]) for v in metrics["lbs_dqs_distance"].values()])
            ax.plot(t, d.max(axis=0), "o-", color="k", label="max")
            ax.plot(t, m.mean(axis=0), "s--", color="0.5", label="mean")
            ax.set_title("|LBS − DQS| vertex distance")
            ax.set_ylabel("% of height")
        else:
            for meth in metrics["methods"]:
                ax.plot(t, _scene_series(metrics, metric, meth), "o-", color=method_color(meth),
                        label=method_label(meth))
            ax.axhline(1.0, color="0.6", lw=0.8, ls=":")
            ax.set_title(METRIC_TITLES[metric])
        ax.set_xlabel("time")
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8)
    return _figure_png(fig)


def sweep_plot_png(sweeps: dict[str, Any]) -> bytes | None:
    """Min section, max bulge and volume ratios against the joint angle on the procedural rigs,
    every method measured (solid) and the closed-form LBS references (dashed).

    Returns
    -------
    bytes or None
        PNG image; None when every rig was skipped.
    """
    from matplotlib.figure import Figure

    rigs = [(k, v) for k, v in sweeps.items() if isinstance(v, dict) and "angle_deg" in v]
    if not rigs:
        return None
    fig = Figure(figsize=(15, 3.6 * len(rigs)))
    fig.subplots_adjust(left=0.05, right=0.99, bottom=0.14 / len(rigs), top=1 - 0.09 / len(rigs),
                        wspace=0.2, hspace=0.45)
    axes = fig.subplots(len(rigs), 3, squeeze=False)
    for row, (name, rig) in zip(axes, rigs):
        theta = np.asarray(rig["angle_deg"], dtype=np.float64)
        for ax, metric in zip(row, ("min_section_ratio", "max_bulge_ratio", "volume_ratio")):
            for meth in rig.get("methods", ("lbs", "dqs")):
                v = rig[meth][metric]
                if v is not None:
                    ax.plot(theta, _array(v), "-", marker=".", color=method_color(meth),
                            label=f"{method_label(meth)} measured")
            ref = rig["reference"].get(f"lbs_{metric}")
            if ref is not None:
                ax.plot(theta, _array(ref), "--", color="k", lw=1.2,
                        label=f"LBS closed form {rig['formulas'][f'lbs_{metric}']}")
            ax.set_title(f"{name} ({rig['asset']}): {METRIC_TITLES[metric]}")
            ax.set_xlabel(f"{name} angle (degrees)")
            ax.set_ylim(bottom=0 if metric == "min_section_ratio" else None)
            lo, hi = ax.get_ylim()
            if hi - lo < 0.02:  # float noise around 1: don't magnify it
                ax.set_ylim(min(lo, 0.98), max(hi, 1.02))
            ax.grid(alpha=0.3)
            ax.legend(fontsize=8)
    return _figure_png(fig)


def _ties_all(summary: dict[str, Any], methods: Sequence[str]) -> bool:
    """Whether every method (two or more) ties on a metric's summary entry."""
    return (len(methods) > 1 and summary["winner"] == "tie"
            and len(summary.get("leaders", [])) == len(methods))


def _summary_table(metrics: dict[str, Any]) -> str:
    methods = metrics["methods"]
    head = "".join(f"<th>{method_label(m)} worst</th>" for m in methods)
    rows = []
    for metric, s in metrics["summary"].items():
        if all(r is None for r in s["by_method"].values()):
            why = s.get("unmeasured") or "no value"
            rows.append(f"<tr><th class=l>{METRIC_TITLES[metric]}</th><td class=l "
                        f"colspan={len(methods) + 1}>not measured: {_esc(why)}</td></tr>")
            continue
        leaders = s.get("leaders", []) if s["winner"] == "tie" else [s["winner"]]
        cells = []
        for m in methods:
            r = s["by_method"][m]
            if r is None:
                cells.append("<td>—</td>")
                continue
            where = f"t = {r['time']:g}, {r['mesh']}" + (f", {r['joint']}" if r["joint"] else "")
            if r.get("bend_deg") is not None:
                where += f" (bend {r['bend_deg']:.0f}°, twist {r['twist_deg']:.0f}°)"
            win = ' class="win"' if m in leaders else ""
            cells.append(f"<td{win}><b>{r['value']:.4f}</b><br><span class=note>"
                         f"{_esc(where)}</span></td>")
        winner = s["winner"]
        if _ties_all(s, methods):
            winner = f"tie: every method within {metrics.get('tie', 0.01):g}"
        elif winner == "tie":
            winner = "tie: " + ", ".join(method_label(x) for x in leaders)
        else:
            winner = method_label(winner)
        rows.append(f"<tr><th class=l>{METRIC_TITLES[metric]}</th>{''.join(cells)}"
                    f"<td class=l>{_esc(winner)}</td></tr>")
    return (f"<table><tr><th class=l>metric</th>{head}<th class=l>best</th></tr>"
            f"{''.join(rows)}</table>")


def _mesh_table(metrics: dict[str, Any]) -> str:
    methods = metrics["methods"]
    head = "".join(f"<th>{METRIC_TITLES[k]}<br>{method_label(m)}</th>" for k in METRIC_TITLES
                   for m in methods)
    rows = []
    for name, per in metrics["meshes"].items():
        cells = []
        for k in METRIC_TITLES:
            for m in methods:
                v = per[m][k]
                if v is None:
                    reason = per[m].get(f"{k}_reason") or "undefined"
                    cells.append(f'<td title="{_esc(reason)}">n/a</td>')
                else:
                    w = worst(k, _array(v))
                    cells.append(f"<td>{_fmt(None if w is None else v[w[0]])}</td>")
        rows.append(f"<tr><td class=l>{_esc(name)}</td>{''.join(cells)}</tr>")
    reasons = sorted({per[m]["volume_ratio_reason"] for per in metrics["meshes"].values()
                      for m in methods if per[m]["volume_ratio_reason"]})
    note = ("" if not reasons else "<p class=note>Volume ratio n/a: "
            + "; ".join(_esc(r) for r in reasons) + ".</p>")
    return (f"<table><tr><th class=l>mesh</th>{head}</tr>{''.join(rows)}</table>{note}")


def _worst_frames(metrics: dict[str, Any]) -> list[tuple[int, list[str]]]:
    """Frame indices to show: each metric's worst frame (worst method first; none where every
    method ties), then the frame of the largest LBS↔DQS distance; at most
    :data:`_MAX_WORST_FRAMES`, with the reasons."""
    picks = []
    for metric, s in metrics["summary"].items():
        if _ties_all(s, metrics["methods"]):
            continue  # nothing tells the methods apart
        ranked = sorted(((r["severity"], m, r) for m, r in s["by_method"].items()
                         if r is not None), key=lambda x: -x[0])
        for _, method, r in ranked[:1]:
            picks.append((r["frame"], f"worst {METRIC_TITLES[metric]} ({method_label(method)} "
                          f"{r['value']:.3f})"))
    dist = metrics.get("lbs_dqs_distance")
    if dist:
        d = np.nanmax(np.stack([_array(v["max"]) for v in dist.values()]), axis=0)
        if np.isfinite(d).any():
            picks.append((int(np.nanargmax(d)), f"largest LBS↔DQS distance "
                          f"({np.nanmax(d):.3g}% of height)"))
    frames: dict[int, list[str]] = {}
    for f, why in picks:
        frames.setdefault(f, []).append(why)
    return sorted(frames.items())[:_MAX_WORST_FRAMES]


def _viewer_section(m: dict[str, Any],
                    viewer: tuple[np.ndarray, tuple[dict[str, Any], bytes]]) -> str:
    """The animated viewer (:mod:`.viewer`) for ``viewer = (times, (meta, blob))``."""
    from .render import colormap_lut
    from .viewer import viewer_html

    times, (meta, blob) = viewer
    methods = m["methods"]
    blend = ("Blend (per-vertex DQS)" if m.get("blend_per_vertex")
             else f"Blend ({m['blend_weight']:g} DQS)" if m.get("blend_weight") is not None
             else "")
    labels = [blend if x == "blend" else method_label(x) for x in methods]
    heat_label = (f"|{labels[0]} − {labels[1]}|" if len(methods) == 2
                  else "largest distance between any two methods")
    worst_frames = [{"time": m["frames"][f], "why": "; ".join(why)}
                    for f, why in _worst_frames(m)]
    settings = {"times": [float(x) for x in times], "labels": labels,
                "colors": [method_color(x) for x in methods], "up_axis": m["up_axis"],
                "fps": m["time_codes_per_second"], "worst": worst_frames,
                "heat_label": heat_label, "heat_max": m.get("viewer", {}).get("heat_max"),
                "heat_unit": "% of height",
                "colormap": np.round(colormap_lut("viridis", 256), 4).tolist()}
    height = m["character_height"]
    step = f"{meta['step']:.3g} units" + (f" ({100 * meta['step'] / height:.2g}% of height)"
                                          if height > 0 else "")
    return ("<h2>Animated viewer</h2><p class=note>Every method plays in sync, "
            f"{len(times)} frames (the compared ones among them); drag to orbit, right-drag to "
            "pan, wheel to zoom. Show or hide each method with its box in the legend; "
            "<i>A/B</i> shows two methods in the same place, one at a time: <i>flip</i> (or the "
            "key F) switches between them. Heat map: per-vertex " + _esc(heat_label) + " in % of "
            "the character's height, over the same colour range in every frame. Rest pose: the "
            "character in its skeleton's rest pose (no animation), in the same space as the "
            f"frames, as a grey ghost. Positions are quantized to {step}.</p>"
            + viewer_html(meta, blob, settings))


def build_html(metrics: dict[str, Any], out_dir: str | os.PathLike, *,
               viewer: tuple[np.ndarray, tuple[dict[str, Any], bytes]] | None = None) -> str:
    """The report as one HTML string, images read from ``out_dir`` (paths in ``metrics``).

    ``viewer``: ``(times, (meta, blob))`` of :func:`dqskin.report.viewer.encode` for the
    animated viewer, or None to leave it out (the page then has no script)."""
    from .viewer import VIEWER_CSS

    out = Path(out_dir)
    m = metrics
    t = m["frames"]
    render = m["render"]
    adaptive = render.get("antialiasing") == "adaptive" and render["supersample"] > 1
    parts = [f"<!DOCTYPE html><html lang=en><head><meta charset=utf-8>"
             f"<title>dqskin compare: {_esc(Path(m['asset']).name)}</title>"
             f"<style>{_CSS}{VIEWER_CSS if viewer else ''}</style></head><body>",
             f"<h1>Skinning comparison: {_esc(Path(m['asset']).name)}</h1>",
             "<table class=meta>"
             f"<tr><th class=l>asset</th><td>{_esc(m['asset'])}</td></tr>"
             f"<tr><th class=l>meshes</th><td>{len(m['meshes'])} rendered together: "
             f"{render['vertices']} vertices, {render['faces']} triangles</td></tr>"
             f"<tr><th class=l>methods</th><td>{', '.join(method_label(x) for x in m['methods'])}"
             + _blend_note(m) + "</td></tr>"
             f"<tr><th class=l>frames</th><td>{len(t)} times: "
             f"{_esc(', '.join(f'{x:g}' for x in t))}"
             f" ({m['time_codes_per_second']:g} per second)</td></tr>"
             f"<tr><th class=l>views</th><td>{_esc(', '.join(m['views']))}; up axis "
             f"{_esc(m['up_axis'])}; {render['width']} px, {render['supersample']}× "
             f"supersampled{_ADAPTIVE_NOTE if adaptive else ''}"
             "</td></tr></table>"]
    if m.get("skipped_meshes"):
        parts.append("<p class=note>Not rendered: " + "; ".join(
            f"{_esc(k)} ({_esc(v)})" for k, v in m["skipped_meshes"].items()) + ".</p>")

    parts.append("<h2>Summary</h2>"
                 "<p class=note>Worst value of each metric over all meshes, joints and frames "
                 "(volume ratio furthest from 1, smallest section ratio, largest bulge ratio), "
                 "where it happens (with the joint's bend and twist relative to its parent), "
                 "and the method whose worst is mildest; methods within "
                 f"{m.get('tie', 0.01):g} of it tie (smaller differences are under a pixel "
                 "at this resolution).</p>" + _summary_table(m))
    parts.append("<h3>Per mesh (worst over frames)</h3>" + _mesh_table(m))
    if viewer is not None:
        parts.append(_viewer_section(m, viewer))

    parts.append("<h2>Per-frame metrics</h2><p class=note>Scene-wide worst per frame: the "
                 "smallest section ratio, the largest bulge, the volume ratio furthest from "
                 "1.</p>" + _img(frame_plot_png(m), "per-frame metric plots"))

    c = m.get("closeup")
    if c and m["images"].get("closeup"):
        png = (out / m["images"]["closeup"]).read_bytes()
        parts.append(f"<h2>Close-up: worst joint</h2><p>{_esc(c['joint'])} of {_esc(c['mesh'])} "
                     f"at t = {t[c['frame']]:g}: {method_label(c['method'])} min section ratio "
                     f"{c['value']:.4f} ({_esc(c['view'])} view).</p>"
                     + _img(png, f"close-up of {c['joint']}"))

    parts.append("<h2>Worst frames</h2>")
    heat = m["images"].get("heat_range")
    if heat:
        parts.append(f"<p class=note>Heat map: per-vertex distance between the LBS and DQS "
                     f"results drawn on the DQS surface, colour range 0 – {heat[1]:.3g}% of the "
                     "character's height (same for every frame).</p>")
    worst_frames = _worst_frames(m)
    if not worst_frames:
        parts.append("<p class=note>No frame stands out: the methods tie on every measured "
                     "metric.</p>")
    for f, reasons in worst_frames:
        parts.append(f"<h3>t = {t[f]:g}: {_esc('; '.join(reasons))}</h3>")
        for view, paths in m["images"]["frames"].items():
            png = (out / paths[f]).read_bytes()
            parts.append(f"<figure>{_img(png, f'{view} view at t = {t[f]:g}')}"
                         f"<figcaption>{_esc(view)} view, t = {t[f]:g}</figcaption></figure>")
    parts.append("<p class=note>Every compared frame is in <code>frames/</code> next to this "
                 "report.</p>")

    parts.append("<h2>Angle sweeps on the procedural rigs</h2>")
    sw = m.get("sweeps")
    if sw is None:
        parts.append("<p class=note>Sweeps left out (not asked for).</p>")
    elif "skipped" in sw:
        parts.append(f"<p class=note>Sweeps skipped: {_esc(sw['skipped'])}.</p>")
    else:
        for name, rig in sw.items():
            if "skipped" in rig:
                parts.append(f"<p class=note>{_esc(name)} sweep skipped: "
                             f"{_esc(rig['skipped'])}.</p>")
        png = sweep_plot_png(sw)
        if png is not None:
            parts.append("<p class=note>Every frame of each rig, skinned with LBS, DQS and every "
                         "compared method; the "
                         "angle is the rotation of the animated joint. Dashed: continuum LBS "
                         "closed forms for a linear weight ramp of width f·L (section of the ring "
                         "w = ½: k = √(1 − 2w(1−w)(1 − cos θ)) = |cos(θ/2)| in the twist, √k in "
                         "the bend; volume 1 − f(1 − cos θ)/3 for the twist, 1 − f(1 − cos θ)/6 "
                         "for the bend). DQS moves every ring rigidly: section and bulge stay at "
                         "1 in both rigs.</p>" + _img(png, "twist and bend sweeps"))
    parts.append(
        "<h2>Definitions</h2><ul class=note>"
        "<li>All measures in skeleton space; blend shapes are not applied.</li>"
        f"<li><b>distances</b> (LBS↔DQS, heat maps) are in % of the character's height: the "
        "largest extent of the bounding box of every rendered mesh in its rest pose, "
        f"{m['character_height']:.4g} scene units here.</li>"
        "<li><b>volume ratio</b>: enclosed volume over rest volume (closed meshes only).</li>"
        "<li><b>joint region and rings</b>: a joint's region is the vertices whose two largest "
        "weights are the joint and its parent; each is put in a <i>ring</i> by its share of "
        "the pair, w = w<sub>joint</sub> / (w<sub>joint</sub> + w<sub>parent</sub>), rounded to "
        f"a multiple of {m['ring_width']:g}. The vertices of a ring get the same blend, so a "
        "method that keeps the flesh intact moves each ring rigidly, at any bend.</li>"
        "<li><b>min section ratio</b>: each ring is measured in its own frame: the covariance "
        "of its vertices about their centroid has eigenvalues λ1 ≥ λ2 ≥ λ3, and √(λ1λ2) is "
        "proportional to the ring's cross-section area. The ratio is (posed area / rest "
        "area)<sup>½</sup> (an equivalent-radius ratio): 1 intact at any bend angle, 0 "
        "collapsed (candy wrapper). Under LBS a circular ring of share w shrinks to "
        "k = √(1 − 2w(1−w)(1 − cos θ)) in a twist by θ and to √k in a bend by θ. The smallest "
        "ring over all joints is reported, with that joint's bend and twist relative to its "
        "parent (swing-twist split about the joint's bone).</li>"
        "<li><b>max bulge ratio</b>: the largest per-vertex distance from its ring's centroid, "
        "posed over rest (vertices at least ¼ of the ring's RMS radius from it), over all rings "
        "(&gt; 1 bulges out; LBS and DQS keep ≤ 1 on a circular two-joint ring).</li></ul>"
        f"<p class=note>Timing: skinning {m['timing_s']['skin']:.2f} s, metrics "
        f"{m['timing_s']['metrics']:.2f} s, rendering {m['timing_s']['render']:.2f} s, viewer "
        f"data {m['timing_s']['viewer']:.2f} s, sweeps {m['timing_s']['sweeps']:.2f} s.</p>"
        "</body></html>")
    return "\n".join(parts)

