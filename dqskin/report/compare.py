"""Offscreen LBS-vs-DQS comparison: skin an asset with each method, measure the artifacts, render
side-by-side panels and write a self-contained HTML report (``dqskin compare``).

Everything is computed in skeleton (bind) space: rest points are the mesh points through their
geom-bind transform, posed points come from :class:`dqskin.Skinner` with the scene's skinning
transforms (blend shapes are not applied, so the comparison isolates skinning). Per mesh, method
and frame (see :mod:`dqskin.metrics`):

* ``volume_ratio``: enclosed volume / rest volume (closed meshes only; otherwise None and a
  reason);
* ``min_section_ratio``: smallest cross-section ratio of any joint ring (1 intact, 0 candy
  wrapper): each joint's region is cut into rings of equal weight share
  (:func:`~dqskin.metrics.joint_rings`) and every ring is measured in its own frame
  (:func:`~dqskin.metrics.ring_sections`), so a rigidly bent limb scores 1 at any angle;
* ``max_bulge_ratio``: largest per-vertex ratio of distance from the ring's centroid, posed over
  rest, in any ring (> 1 bulges).

Each joint value comes with the joint's bend and twist relative to its parent at that frame
(:func:`~dqskin.metrics.joint_bend_twist`).

The ``blend`` method mixes the two with each mesh's own per-vertex DQS fractions
(``Mesh.blend_weights``: an FBX file's DQ weights, ``primvars:dqskin:blendWeights``) and
:data:`BLEND_WEIGHT` on every vertex of the others.

All meshes are rendered together in skeleton space (up axis ``scene.up_axis`` unless given), one
camera per view framed once from the bounds over every frame and method, so the images line up.
The viewer's rest-pose ghost is the character in its skeleton's rest pose (no animation) skinned
the same way, so it lies in the frames' space for every input (a glTF skeleton space holds the
nodes above the joints). Distances are in % of the character's height (:data:`DISTANCE_UNIT`).

Outputs in ``DIR``: ``frames/<view>_<k>.png`` (one panel per compared frame ``k`` and view:
one image per method and a heat map of the per-vertex LBS↔DQS distance), ``frames/closeup.png``
(the joint with the worst ``min_section_ratio``), ``metrics.json`` and ``report.html`` (images
embedded as data URIs; opens from disk without a network). The folder is written whole
(:class:`dqskin.files.atomic.atomic_folder`): nothing appears until the report is complete.
"""

import json
import re
import time
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field, replace
from importlib.resources import files
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np
import numpy.typing as npt

from .. import metrics as M
from ..errors import InputError, LimitError, OutputExistsError, Param, output_exists
from ..files.atomic import atomic_folder
from ..metrics import METRICS, worst
from ..options import METHOD_NAMES, Method, SkinOptions, split_changes
from ..progress import progress_bar
from ..readers import load
from ..scene import DEFAULT_BLEND, Scene
from ..times import default_frames
from .defaults import MAX_RAYS
from .html import build_html, method_label
from .render import VIEWS, Camera, MeshRenderer, Shading, add_colorbar, save_png, side_by_side
from .viewer import VIEWER_FRAMES, encode, viewer_times

__all__ = ["BLEND_WEIGHT", "DISTANCE_UNIT", "MAX_RAYS", "SWEEP_RIGS", "TIE", "RenderSettings",
           "run_compare", "skeleton_up_axis", "summary_lines", "sweeps"]

BLEND_WEIGHT = DEFAULT_BLEND
"""DQS fraction of every vertex for ``method="blend"`` (0 = LBS, 1 = DQS) of meshes without their
own ``blend_weights``."""

SWEEP_RIGS = {
    "twist": ("twist_cylinder.usda", 0.5, 3.0),
    "bend": ("bending_arm.usda", 0.25, 6.0),
}
"""Procedural rigs of the sweeps: ``name → (file in assets/, f, d)``. ``f`` is the weight ramp's
width over the limb length (assets/README.md), ``d`` the divisor of the continuum LBS volume ratio
``1 − f(1 − cos θ)/d`` (linear ramp, cylinder; caps outside the ramp). Twist about the bone:
each cross-section shrinks by ``k² = 1 − 2w(1−w)(1−cos θ)``, whose mean over the ramp is
``1 − (1 − cos θ)/3``. Bend about an axis through the joint: the cross-section area term is the
same, but the Jacobian's rank-one part (the blend changing along the bone) adds back
``(1 − cos θ)x²/(2a²)`` on the half-width-``a`` ramp, a sixth over the ramp, hence ``d = 6``. DQS
keeps 1 in both (rigid rotation of each section)."""




def _label(method, per_vertex=False):
    """A method's label in images and text (the blend with its DQS fraction, or "per-vertex"
    when a mesh has its own ``blend_weights``)."""
    if method != "blend":
        return method_label(method)
    return "Blend (per-vertex DQS)" if per_vertex else f"Blend ({BLEND_WEIGHT:g} DQS)"


def _own_blend(scene, methods):
    """Mesh name → mean of its own blend weights, for the meshes that have them (when the blend
    is compared)."""
    if "blend" not in methods:
        return {}
    return {m.name: float(np.mean(m.blend_weights)) for m in scene.meshes
            if m.blend_weights is not None and len(m.blend_weights)}


_FRAME_FILE = re.compile(r"^(?:(?:%s)_\d{3}|closeup)\.png$" % "|".join(VIEWS))
_HEAT_SHADING = Shading(ambient=0.55, diffuse=0.45, rim=0.0)
_HEAT_COLORMAP = "viridis"


def _choice_list(name: str, values: str | Iterable[str],
                 allowed: Sequence[str]) -> tuple[Any, ...]:
    items = [values] if isinstance(values, str) else list(values)
    if not items:
        raise InputError(Param(name), f": empty; choose from {', '.join(allowed)}")
    for v in items:
        if v not in allowed:
            raise InputError(Param(name), f": unknown {v!r}; choose from {', '.join(allowed)}")
    if len(set(items)) != len(items):
        raise InputError(Param(name), f": repeated entries in {items}")
    return tuple(items)


@dataclass
class _SkinnedMesh:
    """One mesh's skeleton-space rest and posed points and what its metrics need."""

    name: str
    skeleton: int
    faces: np.ndarray  # (T, 3) int32
    rest: np.ndarray  # (V, 3) float64, bind points in skeleton space (what metrics compare)
    rings: np.ndarray  # (V,) int32, see metrics.joint_rings
    ring_share: np.ndarray  # (R,) float64
    ghost: np.ndarray  # (V, 3) float32: the rest pose in the posed points' space
    posed: dict = field(default_factory=dict)  # method → (F, V, 3) float32


def _renderable(scene):
    """The meshes with points and faces, and the others (name → reason); ValueError if none."""
    keep, skipped = [], {}
    for m in scene.meshes:
        if len(m.points) == 0:
            skipped[m.name] = "no points"
        elif len(m.faces) == 0:
            skipped[m.name] = "no faces (points only)"
        else:
            keep.append(m)
    if not keep:
        detail = "; ".join(f"{k}: {v}" for k, v in skipped.items()) or "no skinned meshes"
        raise InputError(f"{scene.path}: nothing to render ({detail})")
    return keep, skipped


def _skin(scene, times, methods, options):
    """Skin every renderable mesh in skeleton space with each method and ``options``, bind
    points (no blend shapes), through the engine's one path (meshes without faces are
    skipped)."""
    renderable, skipped = _renderable(scene)
    opts = options.replace(space="skeleton", blend_shapes=False, normals=False, tangents=False,
                           velocities=False)
    xforms = {s: scene.skinning_transforms(times, s, device=opts.device, interp=opts.interp)
              for s in sorted({m.skeleton for m in renderable})}
    posed = {meth: scene.skin(times, meth, options=opts).points for meth in methods}
    ghosts = _rest_pose(scene, opts)
    meshes = []
    for m in renderable:
        g = np.asarray(m.geom_bind_transform, dtype=np.float64)
        rest = np.asarray(m.points, dtype=np.float64) @ g[:3, :3].T + g[:3, 3]
        rings, share = M.joint_rings(m.joint_indices, m.joint_weights,
                                     scene.skeletons[m.skeleton].parents)
        sm = _SkinnedMesh(m.name, m.skeleton, np.asarray(m.faces, dtype=np.int32), rest, rings,
                          share, ghosts[m.name])
        sm.posed = {meth: posed[meth][m.name] for meth in methods}
        meshes.append(sm)
    return meshes, skipped, xforms


def _rest_pose(scene, options):
    """Every mesh in its skeleton's rest pose (no animation), skinned with LBS like the posed
    frames (``options``' space): name → (V, 3) float32. For USD the rest pose is usually the
    bind pose (identity skinning transforms); for glTF it holds the nodes above the joints (a
    Z-up node, say), as the posed frames do."""
    still = replace(scene, skeletons=[s.with_animation(None) for s in scene.skeletons])
    return {k: v[0] for k, v in still.skin([0.0], "lbs", options=options).points.items()}


def _nan_reduce(a, fn):
    """Per-frame reduction over joints of an (F, J) array; NaN where a frame has no value."""
    out = np.full(a.shape[0], np.nan)
    arg = np.full(a.shape[0], -1)
    for f in range(a.shape[0]):
        ok = np.flatnonzero(np.isfinite(a[f]))
        if ok.size:
            k = ok[fn(a[f, ok])]
            out[f], arg[f] = a[f, k], k
    return out, arg


def _per_joint(a, joints, reduce):
    """(F, J·R) ring values → (F, J) per joint (NaN where a joint has no valid ring)."""
    a = a.reshape(a.shape[0], joints, -1)
    out = np.full(a.shape[:2], np.nan)
    ok = np.isfinite(a).any(axis=2)
    out[ok] = reduce(np.where(np.isfinite(a), a, np.nan)[ok], axis=1)
    return out


def _measure(mesh, skeleton, methods, device):
    """Per-frame metrics of one mesh: method → dict of (F,) float64 arrays (NaN undefined) and
    the (F,) int joints they belong to (-1 none). Every method in one call of each measure (the
    mesh's closedness is checked once)."""
    frames = len(next(iter(mesh.posed.values())))
    posed = np.concatenate([mesh.posed[meth] for meth in methods])
    ratio, reason = M.volume_ratio(posed, mesh.rest, mesh.faces, device=device)
    joints = len(skeleton.parents)
    sec = M.ring_sections(mesh.rest, posed, mesh.rings, joints * len(mesh.ring_share))
    section, section_joint = _nan_reduce(_per_joint(sec.section_ratio, joints, np.nanmin),
                                         np.argmin)
    bulge, bulge_joint = _nan_reduce(_per_joint(sec.bulge_ratio, joints, np.nanmax), np.argmax)
    out = {}
    for k, meth in enumerate(methods):
        part = slice(k * frames, (k + 1) * frames)
        out[meth] = {"volume_ratio": None if ratio is None else np.asarray(ratio,
                                                                           np.float64)[part],
                     "volume_ratio_reason": reason,
                     "min_section_ratio": section[part], "min_section_joint": section_joint[part],
                     "max_bulge_ratio": bulge[part], "max_bulge_joint": bulge_joint[part]}
    return out


def _json_float(v):
    return float(v) if np.isfinite(v) else None


def _json_floats(a):
    return [float(v) if np.isfinite(v) else None for v in np.asarray(a, dtype=np.float64)]


DISTANCE_UNIT = "% of character_height"
"""Unit of every distance in the report and ``metrics.json`` (LBS↔DQS distances, the heat maps'
ranges): percent of the character's height, the largest extent of the bounding box of every
rendered mesh in its rest pose (``character_height``, in the scene's length unit)."""

TIE = 0.01
"""Methods whose worst values differ by less than this (a ratio: 1% of volume or radius, under a
pixel at report resolution) tie in the summary."""


def _summary(measures, meshes, skeletons, angles, times, methods, tie=TIE):
    """Worst frame and value of each metric per method over all meshes (with the joint's bend
    and twist there, from ``angles``: skeleton → (bend, twist) (F, J) degrees), and the winner:
    the method of least severity (see :func:`worst`), or ``"tie"`` within ``tie``."""
    out = {}
    for metric in METRICS:
        by_method = {}
        for meth in methods:
            best = None
            for mesh in meshes:
                values = measures[mesh.name][meth][metric]
                if values is None:
                    continue
                w = worst(metric, values)
                if w is not None and (best is None or w[1] > best[0]):
                    joint, bend, twist = None, None, None
                    if metric != "volume_ratio":
                        j = measures[mesh.name][meth][metric.replace("_ratio", "_joint")][w[0]]
                        if j >= 0:
                            joint = skeletons[mesh.skeleton].joint_names[j]
                            bend, twist = (_json_float(a[w[0], j])
                                           for a in angles[mesh.skeleton])
                    best = (w[1], mesh.name, int(w[0]), float(values[w[0]]), joint, bend, twist)
            by_method[meth] = None if best is None else {
                "value": best[3], "severity": best[0], "frame": best[2],
                "time": float(times[best[2]]), "mesh": best[1], "joint": best[4],
                "bend_deg": best[5], "twist_deg": best[6]}
        scored = {m: r["severity"] for m, r in by_method.items() if r is not None}
        winner, leaders, reason = None, [], None
        if scored:
            lowest = min(scored.values())
            leaders = [m for m, d in scored.items() if d <= lowest + tie]
            winner = leaders[0] if len(leaders) == 1 else "tie"
        elif metric == "volume_ratio":
            reason = "; ".join(sorted({str(measures[m.name][meth]["volume_ratio_reason"])
                                       for m in meshes for meth in methods})) or None
        else:
            reason = _NO_RINGS
        out[metric] = {"by_method": by_method, "winner": winner, "leaders": leaders,
                       "unmeasured": reason}
    return out


_NO_RINGS = ("no joint ring to measure (a ring: 4 or more vertices blended between a joint and "
             "its parent)")


def _closeup_target(measures, meshes, skeletons, xforms, methods):
    """(method, mesh, frame, joint) of the worst min_section_ratio over everything, or None."""
    best = None
    for mesh in meshes:
        for meth in methods:
            v = measures[mesh.name][meth]["min_section_ratio"]
            w = worst("min_section_ratio", v)
            if w is not None and (best is None or w[1] > best[0]):
                j = int(measures[mesh.name][meth]["min_section_joint"][w[0]])
                best = (w[1], meth, mesh, int(w[0]), j)
    if best is None:
        return None
    _, meth, mesh, f, j = best
    skel = skeletons[mesh.skeleton]
    x = np.asarray(xforms[mesh.skeleton][f], dtype=np.float64)
    bind = skel.bind_transforms[:, :3, 3]
    center = x[j, :3, :3] @ bind[j] + x[j, :3, 3]
    parent = skel.parents[j]
    bone = center - (x[parent, :3, :3] @ bind[parent] + x[parent, :3, 3]) if parent >= 0 else None
    members = mesh.rest[mesh.rings // len(mesh.ring_share) == j]
    radius = 1.4 * float(np.linalg.norm(members - bind[j], axis=1).max()) if len(members) else 0
    if not radius > 0:
        radius = 0.25 * float(np.linalg.norm(np.ptp(mesh.rest, axis=0)))
    return {"method": meth, "mesh": mesh.name, "frame": f, "joint": skel.joint_names[j],
            "value": float(measures[mesh.name][meth]["min_section_ratio"][f]),
            "center": center, "radius": radius, "bone": bone}


def _side_view(bone, up_axis):
    """The named view most perpendicular to a bone (the collapse shows in profile)."""
    if bone is None or not np.linalg.norm(bone) > 0:
        return "three_quarter"
    b = bone / np.linalg.norm(bone)

    def along(view):  # |cos| between the bone and the view direction
        cam = Camera.frame_point(np.zeros(3), 1.0, view, up_axis=up_axis)
        return abs(float(cam.basis()[0] @ b))

    return min(VIEWS, key=along)


def _aspect(camera, lo, hi, limits=(0.5, 2.0)):
    """Width / height of the box ``[lo, hi]`` as ``camera`` sees it (square image), clamped."""
    corners = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1])
                        for z in (lo[2], hi[2])])
    px = camera.project(corners, 1000, 1000)
    extent = np.ptp(px, axis=0)
    return float(np.clip(extent[0] / max(extent[1], 1e-9), *limits))


def _combined(meshes, methods):
    """All meshes as one: faces with offset indices, and each method's (F, V, 3) points."""
    offsets = np.cumsum([0] + [len(m.rest) for m in meshes])
    faces = np.concatenate([m.faces + o for m, o in zip(meshes, offsets[:-1])])
    posed = {meth: np.concatenate([m.posed[meth] for m in meshes], axis=1) for meth in methods}
    return faces, posed


def _render_count(times, methods, views, heat, closeup):
    """Images :func:`_render` makes (the progress bar's share of rendering)."""
    per_frame = len(methods) + bool(heat)
    return len(times) * len(views) * per_frame + per_frame * bool(closeup)


def _render(meshes, times, methods, render, frames_dir, closeup, distance, bar, device,
            per_vertex=False):
    """Render every panel to ``frames_dir`` with ``render`` (:class:`RenderSettings`, its up
    axis set); returns {view: [paths per frame]} and the close-up."""
    views, up_axis, width = render.views, render.up_axis, render.width
    supersample, adaptive = render.supersample, render.adaptive
    faces, posed = _combined(meshes, methods)
    lo = np.min([p.min(axis=(0, 1)) for p in posed.values()], axis=0).astype(np.float64)
    hi = np.max([p.max(axis=(0, 1)) for p in posed.values()], axis=0).astype(np.float64)
    cameras, sizes = {}, {}
    for v in views:  # one camera per view; the image (about width² pixels) hugs the bounds
        aspect = _aspect(Camera.frame(lo, hi, v, up_axis=up_axis), lo, hi)
        cameras[v] = Camera.frame(lo, hi, v, up_axis=up_axis, aspect=aspect)
        sizes[v] = {"width": max(16, int(round(width * np.sqrt(aspect)))),
                    "height": max(16, int(round(width / np.sqrt(aspect))))}
    heat = distance is not None
    dmax = float(np.nanmax(distance)) if heat and np.isfinite(distance).any() else 0.0
    heat_range = (0.0, dmax if dmax > 0 else 1.0)
    renderers = {meth: MeshRenderer(posed[meth][0], faces, device=device) for meth in methods}
    heat_renderer = renderers["dqs"] if heat else None
    labels = [_label(m, per_vertex) for m in methods] + (["|LBS - DQS|"] if heat else [])

    def panel(f, cams, dims):
        images: dict[str, list[np.ndarray]] = {v: [] for v in cams}
        heat_images = {}
        for meth in methods:
            renderers[meth].update(posed[meth][f])
            for v, cam in cams.items():
                # the heat map is drawn on the DQS surface: a second layer of the same rays
                second = None
                if heat and renderers[meth] is heat_renderer:
                    second = {"scalars": distance[f], "scalar_range": heat_range,
                              "colormap": _HEAT_COLORMAP, "shading": _HEAT_SHADING}
                img = renderers[meth].render(cam, supersample=supersample, adaptive=adaptive,
                                             second_layer=second, **dims[v])
                if isinstance(img, tuple):  # (the second layer's image too)
                    img, heat_images[v] = img
                    bar.update()
                images[v].append(img)
                bar.update()
        for v, img in heat_images.items():
            images[v].append(add_colorbar(img, heat_range, _HEAT_COLORMAP,
                                          label="% of height"))
        return {v: side_by_side(imgs, labels) for v, imgs in images.items()}

    paths: dict[str, list[Path]] = {v: [] for v in views}
    for f in range(len(times)):
        for v, img in panel(f, cameras, sizes).items():
            paths[v].append(save_png(frames_dir / f"{v}_{f:03d}.png", img))
    closeup_path = None
    if closeup:
        view = _side_view(closeup["bone"], up_axis)
        cam = Camera.frame_point(closeup["center"], closeup["radius"], view, up_axis=up_axis)
        closeup["view"] = view
        img = panel(closeup["frame"], {view: cam}, {view: {"width": width, "height": width}})[view]
        closeup_path = save_png(frames_dir / "closeup.png", img)
    return paths, closeup_path, dmax


def _rotation_angles(x):
    """Rotation angle in radians of each (…, 4, 4) transform's 3×3 block, in [0, π]:
    ``atan2(|axial(R − Rᵀ)|, (tr R − 1)/2)``, accurate near 0 and π alike."""
    r = np.asarray(x, dtype=np.float64)[..., :3, :3]
    axial = np.stack([r[..., 2, 1] - r[..., 1, 2], r[..., 0, 2] - r[..., 2, 0],
                      r[..., 1, 0] - r[..., 0, 1]], axis=-1)
    return np.arctan2(0.5 * np.linalg.norm(axial, axis=-1),
                      0.5 * (np.trace(r, axis1=-2, axis2=-1) - 1))


def sweeps(assets_dir: str | Path, *, methods: Sequence[Method] = ("lbs", "dqs"),
           options: SkinOptions | None = None) -> dict[str, Any]:
    """Artifact curves of the skinning methods against the joint angle on the procedural rigs.

    Every frame of ``twist_cylinder.usda`` (twist 0→180°) and ``bending_arm.usda`` (bend 0→150°)
    in ``assets_dir`` is skinned with LBS, DQS and ``methods`` (and ``options``' device, sign
    rule, interpolation); the angle is the rotation angle of the animated joint's skinning
    transform.

    Returns
    -------
    dict
        ``name → {"asset", "joint", "fraction", "angle_deg": [...], "methods": [...], method:
        {metric: [...]}, "reference": {"lbs_volume_ratio": [...], "lbs_min_section_ratio": [...]},
        "formulas": {...}}`` (JSON-safe; see :data:`SWEEP_RIGS` for the references), or
        ``{"skipped": reason}`` when a rig file is missing.
    """
    methods = tuple(dict.fromkeys(("lbs", "dqs") + tuple(methods)))
    options = SkinOptions() if options is None else options
    out: dict[str, Any] = {}
    for name, (file, fraction, divisor) in SWEEP_RIGS.items():
        path = Path(assets_dir) / file
        if not path.is_file():
            out[name] = {"skipped": f"{path}: not found"}
            continue
        scene = load(path)
        times = np.asarray(scene.times, dtype=np.float64)
        meshes, _, xforms = _skin(scene, times, methods, options)
        mesh = meshes[0]
        skel = scene.skeletons[mesh.skeleton]
        theta_all = _rotation_angles(xforms[mesh.skeleton])
        joint = int(np.argmax(theta_all[-1]))
        theta = theta_all[:, joint]
        entry = {"asset": file, "joint": skel.joint_names[joint], "fraction": fraction,
                 "angle_deg": _json_floats(np.degrees(theta)), "methods": list(methods)}
        for meth, m in _measure(mesh, skel, methods, options.device).items():
            entry[meth] = {k: (None if m[k] is None else _json_floats(m[k])) for k in METRICS}
        entry["reference"] = {"lbs_volume_ratio": _json_floats(
            1 - fraction * (1 - np.cos(theta)) / divisor)}
        entry["formulas"] = {"lbs_volume_ratio": f"1 − {fraction:g}(1 − cos θ)/{divisor:g}"}
        # the ring of share ½ (the ramp's middle) collapses most: k in a twist, √k in a bend
        k = np.sqrt(np.maximum(1 - 0.5 * (1 - np.cos(theta)), 0.0))
        entry["reference"]["lbs_min_section_ratio"] = _json_floats(
            k if name == "twist" else np.sqrt(k))
        entry["formulas"]["lbs_min_section_ratio"] = (
            "k = √(1 − 2w(1−w)(1 − cos θ)), w = ½" if name == "twist"
            else "√k, k = √(1 − 2w(1−w)(1 − cos θ)), w = ½")
        out[name] = entry
    return out


def _default_assets():
    return Path(str(files("dqskin.assets")))


_REPORT_FILES = ("report.html", "metrics.json")


def _check_out(out_dir, force):
    """``out_dir`` as a Path once it may be written: new, an empty folder, or (with ``force``) an
    earlier report (``report.html``, ``metrics.json``, ``frames/`` of panels named as this module
    names them, and nothing else: a folder holding anything else is never replaced)."""
    out = Path(out_dir)
    if out.exists() and not out.is_dir():
        raise InputError(f"{out}: exists and is not a directory")
    if not out.is_dir():
        return out
    entries = sorted(out.iterdir())
    if not entries:
        return out
    foreign = [p.name for p in entries if p.name not in _REPORT_FILES + ("frames",)]
    frames = out / "frames"
    if frames.exists():
        if not frames.is_dir() or frames.is_symlink():
            foreign.append("frames")
        else:
            foreign += [f"frames/{p.name}" for p in sorted(frames.iterdir())
                        if not (p.is_file() and _FRAME_FILE.match(p.name))]
    if foreign:
        shown = ", ".join(repr(n) for n in foreign[:5]) + (", ..." if len(foreign) > 5 else "")
        raise OutputExistsError(f"{out}: holds files that are not a dqskin report ({shown}); a "
                                "report is written as a whole folder: choose a new or empty one")
    if not force:
        raise output_exists(next(out / n for n in _REPORT_FILES + ("frames",)
                                 if (out / n).exists()))
    return out


def skeleton_up_axis(scene: Scene) -> str:
    """The skeleton-space axis ("Y" or "Z") that points closest to the stage's up direction.

    Rendering happens in skeleton space; a USD skeleton under a rotating transform (a converter's
    ``Z_UP`` group, say) has its own up axis. Uses the first skeleton's ``world_transform``.
    """
    if not scene.skeletons:
        return scene.up_axis
    world_up = np.eye(3)[1 if scene.up_axis == "Y" else 2]
    lin = np.asarray(scene.skeletons[0].world_transform, np.float64)[:3, :3]
    try:
        up = np.linalg.solve(lin, world_up)  # the world up direction in skeleton axes
    except np.linalg.LinAlgError:  # a degenerate (zero-scale) skeleton transform
        return scene.up_axis
    return "Y" if abs(up[1]) >= abs(up[2]) else "Z"


def run_compare(input_path: str | Path | Scene, out_dir: str | Path, *,
                methods: Method | Sequence[Method] = ("lbs", "dqs"),
                frames: npt.ArrayLike | None = None,
                options: SkinOptions | None = None, render: "RenderSettings | None" = None,
                progress: bool = True, force: bool = False,
                sweeps_dir: str | Path | None = "default", clip: str | int | None = None,
                viewer_frames: int = VIEWER_FRAMES, **changes: Any) -> dict[str, Any]:
    """Compare skinning methods on an asset and write ``report.html``, ``metrics.json`` and
    ``frames/*.png`` in ``out_dir``.

    Parameters
    ----------
    input_path : str, Path or dqskin.Scene
        A character file (:func:`dqskin.load`) or an already loaded scene.
    out_dir : str or Path
        The report's folder, written whole: everything goes to a temporary folder beside it,
        renamed to ``out_dir`` once complete (an error or an interrupt leaves nothing). It may
        be new or an empty folder; an earlier report there raises
        :class:`~dqskin.errors.OutputExistsError` (a FileExistsError) unless ``force``, which
        replaces it whole once the new one is complete; a folder holding anything but a
        report (``report.html``, ``metrics.json``, ``frames/*.png`` as named here) raises it
        even with ``force``.
    methods : sequence of {"lbs", "dqs", "blend", "cor"}
        The heat map of the per-vertex LBS↔DQS distance needs both ``lbs`` and ``dqs``.
    frames : sequence of float, optional
        Times in the asset's unit; default :func:`default_frames` of the asset's times.
    options : dqskin.SkinOptions, optional
        Device, sign rule, interpolation and centers-of-rotation settings of the skinning (its
        method, outputs and space are the report's: each of ``methods``, points only, skeleton
        space, no blend shapes).
    render : RenderSettings, optional
        Views, image size, anti-aliasing, the ray limit and the cameras' up axis.
    progress : bool
        One tqdm progress bar on stderr for the whole comparison (only when stderr is a
        terminal).
    sweeps_dir : str, Path or None
        Folder of the procedural rigs for the angle sweeps (:func:`sweeps`); ``"default"`` is
        the repository's ``assets/`` folder, None leaves the sweeps out. A missing folder or rig
        is noted in the report.
    clip : str or int, optional
        glTF animation to load.
    viewer_frames : int
        Frames of the animated viewer (:func:`dqskin.report.viewer.viewer_times`: evenly spaced
        over the clip, plus the compared frames); 0 leaves the viewer out.
    **changes
        Fields of :class:`dqskin.SkinOptions` (``device``, ``sign_reference``, ...) or of
        :class:`RenderSettings` (``width``, ``views``, ...) replacing those given.

    Returns
    -------
    dict
        The contents of ``metrics.json``.
    """
    t0 = time.perf_counter()
    skin_changes, render_changes = split_changes("run_compare", changes, SkinOptions,
                                                 RenderSettings)
    options = SkinOptions.build(options, **skin_changes)
    render = replace(RenderSettings() if render is None else render, **render_changes)
    methods = _choice_list("methods", methods, METHOD_NAMES)
    render = replace(render, views=_choice_list("views", render.views, VIEWS))
    width, supersample = render.width, render.supersample
    for name, v, low in (("width", width, 16), ("supersample", supersample, 1),
                         ("viewer_frames", viewer_frames, 0)):
        if isinstance(v, bool) or int(v) != v or v < low:
            raise InputError(Param(name), f": expected an integer >= {low}, got {v!r}")
    if width * supersample > render.max_rays:
        rays = width * supersample
        raise LimitError(Param("width", width), " × ", Param("supersample", supersample),
                         f" casts {rays:,} rays per image side, more than the limit of "
                         f"{render.max_rays:,}; raise ", Param("max_rays"), " to allow more")
    # one bar for the whole comparison, loading included (its total is set once frames are known)
    with progress_bar(enabled=progress, total=None, desc="compare", unit="step", leave=False,
                      dynamic_ncols=True) as bar:
        bar.set_postfix_str("loading")
        scene = input_path if isinstance(input_path, Scene) else load(input_path, clip=clip)
        up = skeleton_up_axis(scene) if render.up_axis is None else render.up_axis
        if up not in ("Y", "Z"):
            raise InputError(f"{scene.path}: up axis must be Y or Z, got {up!r}")
        if frames is None:
            times = default_frames(scene.times)
        else:
            times = np.asarray(frames, dtype=np.float64).reshape(-1)
            if times.size == 0 or not np.all(np.isfinite(times)):
                raise InputError(Param("frames"),
                                 f": expected finite times, got {times.tolist()!r}")
        _renderable(scene)
        out = _check_out(out_dir, force)

        all_times = viewer_times(scene.times, times, viewer_frames) if viewer_frames else times
        heat = "lbs" in methods and "dqs" in methods
        bar.total = (1 + 2 * len(methods) + _render_count(times, methods, render.views, heat,
                                                          True)
                     + bool(viewer_frames) + 2 * (sweeps_dir is not None) + 1)
        bar.update()  # loaded
        with atomic_folder(out, overwrite=force) as folder:  # the report appears whole
            assert folder.tmp is not None, "an open atomic_folder has its temporary folder"
            frames_dir = folder.tmp / "frames"
            frames_dir.mkdir()
            return _compare(_Report(scene, folder.tmp, frames_dir, times, all_times,
                                    tuple(methods), options, replace(render, up_axis=up),
                                    sweeps_dir, bool(viewer_frames), heat), bar, t0)


@dataclass(frozen=True)
class RenderSettings:
    """How :func:`run_compare` renders its panels.

    Attributes
    ----------
    views : sequence of {"front", "side", "three_quarter"}
    width : int
        Size of each rendered image: about ``width²`` pixels, shaped to the view's aspect ratio
        (within 1:2 and 2:1); the close-up is ``width × width``.
    supersample : int
        Anti-aliasing rays per pixel along each axis.
    adaptive : bool
        Cast the ``supersample²`` rays only for pixels on an edge, one ray through the centre
        elsewhere (:meth:`MeshRenderer.render`'s ``adaptive``); False super-samples every pixel.
    max_rays : int
        Refuse ``width × supersample`` above this, before rendering anything.
    up_axis : {"Y", "Z"} or None
        Up axis of the skeleton space for the cameras; None: :func:`skeleton_up_axis`.
    """

    views: tuple = VIEWS
    width: int = 512
    supersample: int = 2
    adaptive: bool = True
    max_rays: int = MAX_RAYS
    up_axis: str | None = None


class _Report(NamedTuple):
    """One :func:`run_compare` once its arguments are checked."""

    scene: Scene
    out: Path
    frames_dir: Path
    times: np.ndarray
    all_times: np.ndarray
    methods: tuple[Method, ...]
    options: SkinOptions
    render: RenderSettings
    sweeps_dir: str | Path | None
    viewer: bool
    heat: bool


def _compare(report: _Report, bar: Any, t0: float) -> dict[str, Any]:
    """The body of :func:`run_compare` once its arguments are checked; ``bar`` counts steps."""
    (scene, out, frames_dir, times, all_times, methods, options, render, sweeps_dir, viewer,
     heat) = report
    device = options.device
    bar.set_postfix_str("skinning")
    meshes, skipped, xforms = _skin(scene, all_times, methods, options)
    bar.update(len(methods))
    pick = np.searchsorted(all_times, times)  # the compared frames among the viewer's
    viewer_posed = _combined(meshes, methods) if viewer else None
    for m in meshes:
        m.posed = {meth: p[pick] for meth, p in m.posed.items()}
    xforms = {s: x[pick] for s, x in xforms.items()}
    t_skin = time.perf_counter()
    bar.set_postfix_str("metrics")
    skeletons = scene.skeletons
    measures = {}
    for m in meshes:
        measures[m.name] = _measure(m, skeletons[m.skeleton], methods, device)
    bar.update(len(methods))
    angles = {s: M.joint_bend_twist(x, skeletons[s].bind_transforms[:, :3, 3],
                                    skeletons[s].parents) for s, x in xforms.items()}
    height = M.character_height(np.concatenate([m.ghost for m in meshes]))
    percent = 100.0 / height if height > 0 else float("nan")
    distance, dist_json = None, None
    if heat:
        per_mesh = [M.vertex_distance(m.posed["lbs"], m.posed["dqs"], device=device) * percent
                    for m in meshes]
        distance = np.concatenate(per_mesh, axis=1)
        dist_json = {m.name: {"max": _json_floats(d.max(axis=1)),
                              "mean": _json_floats(d.mean(axis=1))}
                     for m, d in zip(meshes, per_mesh)}
    summary = _summary(measures, meshes, skeletons, angles, times, methods)
    closeup = _closeup_target(measures, meshes, skeletons, xforms, methods)
    t_metrics = time.perf_counter()

    bar.set_postfix_str("rendering")
    own_blend = _own_blend(scene, methods)
    panels, closeup_path, dmax = _render(meshes, times, methods, render, frames_dir, closeup,
                                         distance, bar, device, bool(own_blend))
    if closeup is None:
        bar.update(len(methods) + heat)
    t_render = time.perf_counter()

    viewer_data = None
    if viewer_posed is not None:
        bar.set_postfix_str("viewer data")
        faces, posed = viewer_posed
        ghost = np.concatenate([m.ghost for m in meshes])
        viewer_data = (all_times, encode(posed, ghost, faces))
        bar.update()
    t_viewer = time.perf_counter()

    sweep_data = None
    if sweeps_dir is not None:
        folder = _default_assets() if sweeps_dir == "default" else Path(sweeps_dir)
        bar.set_postfix_str("sweeps")
        sweep_data = (sweeps(folder, methods=methods, options=options) if folder.is_dir()
                      else {"skipped": f"{folder}: rig folder not found"})
        bar.update(2)

    def mesh_json(m, meth):
        r = measures[m.name][meth]
        names = skeletons[m.skeleton].joint_names
        bend, twist = angles[m.skeleton]
        out = {"volume_ratio": None if r["volume_ratio"] is None else _json_floats(
                   r["volume_ratio"]),
               "volume_ratio_reason": r["volume_ratio_reason"]}
        for metric, key in (("min_section_ratio", "min_section"), ("max_bulge_ratio", "max_bulge")):
            js = r[f"{key}_joint"]
            out[metric] = _json_floats(r[metric])
            out[f"{key}_joint"] = [names[j] if j >= 0 else None for j in js]
            out[f"{key}_bend_deg"] = [_json_float(bend[f, j]) if j >= 0 else None
                                      for f, j in enumerate(js)]
            out[f"{key}_twist_deg"] = [_json_float(twist[f, j]) if j >= 0 else None
                                       for f, j in enumerate(js)]
        return out

    def rel(path):
        return path.relative_to(out).as_posix()

    result = {
        "asset": str(scene.path),
        "methods": list(methods),
        "blend_weight": BLEND_WEIGHT if "blend" in methods else None,
        "blend_per_vertex": own_blend,
        "frames": _json_floats(times),
        "time_codes_per_second": float(scene.time_codes_per_second),
        "up_axis": render.up_axis,
        "views": list(render.views),
        "space": "skeleton",
        "ring_width": M.RING_WIDTH,
        "tie": TIE,
        "character_height": height,
        "distance_unit": DISTANCE_UNIT,
        "meshes": {m.name: {meth: mesh_json(m, meth) for meth in methods} for m in meshes},
        "skipped_meshes": skipped,
        "lbs_dqs_distance": dist_json,
        "summary": summary,
        "closeup": None if closeup is None else {
            k: closeup[k] for k in ("method", "mesh", "frame", "joint", "value", "view")},
        "images": {"frames": {v: [rel(p) for p in ps] for v, ps in panels.items()},
                   "closeup": None if closeup_path is None else rel(closeup_path),
                   "heat_range": [0.0, dmax] if heat else None},
        "sweeps": sweep_data,
        "render": {"width": int(render.width), "supersample": int(render.supersample),
                   "antialiasing": "adaptive" if render.adaptive else "full",
                   "vertices": int(sum(len(m.rest) for m in meshes)),
                   "faces": int(sum(len(m.faces) for m in meshes))},
    }
    if viewer_data is not None:
        meta, blob = viewer_data[1]
        result["viewer"] = {"frames": _json_floats(viewer_data[0]),
                            "vertices": meta["vertices"], "data_bytes": len(blob),
                            "heat_max": None if meta["heat_max"] is None
                            else _json_float(meta["heat_max"] * percent)}
    t_sweeps = time.perf_counter()
    result["timing_s"] = {"skin": t_skin - t0, "metrics": t_metrics - t_skin,
                          "render": t_render - t_metrics, "viewer": t_viewer - t_render,
                          "sweeps": t_sweeps - t_viewer}
    bar.set_postfix_str("report")
    page = build_html(result, out, viewer=viewer_data)
    bar.update()
    result["timing_s"]["report"] = time.perf_counter() - t_sweeps
    result["timing_s"]["total"] = time.perf_counter() - t0
    (out / "metrics.json").write_text(json.dumps(result, indent=1, ensure_ascii=False,
                                                 allow_nan=False), encoding="utf-8")
    (out / "report.html").write_text(page, encoding="utf-8")
    return result


def summary_lines(result: dict[str, Any]) -> list[str]:
    """The summary of a :func:`run_compare` result as text lines: each metric's worst value per
    method and the best method (or the methods that tie, or why it was not measured)."""
    lines = []
    per_vertex = bool(result.get("blend_per_vertex"))
    for metric, s in result["summary"].items():
        worst_values = ", ".join(f"{_label(m, per_vertex)} {r['value']:.3f} @ t={r['time']:g}"
                                 for m, r in s["by_method"].items() if r is not None)
        if not worst_values:
            lines.append(f"  {metric}: not measured ({s.get('unmeasured') or 'no value'})")
            continue
        best = s["winner"]
        if best == "tie":
            best = ("tie: " + ", ".join(_label(m, per_vertex) for m in s["leaders"])
                    + f" within {result.get('tie', TIE):g}")
        else:
            best = _label(best, per_vertex)
        lines.append(f"  {metric}: {worst_values}; best: {best}")
    return lines
