"""What a USD point cache holds, read back for ``dqskin info``: dqskin's own caches (one layer or
value clips) and UsdSkel's ``BakeSkinning`` output alike.

A USD stage is a point cache here when it has no ``SkelRoot`` (nothing left to skin) and at least
one point-based prim (``UsdGeom.PointBased``: meshes, points, curves). For each such prim: its
point count, faces, the time samples of its points, and which of normals (``normals`` or
``primvars:normals``), velocities, accelerations, UVs (``primvars:st``) and extents it holds, with
their sample counts; for the stage: time range in time codes and seconds, rates, up axis, unit,
value clips; and world-space bounds (each prim's points through
``ComputeLocalToWorldTransform`` at the sample's time, in stage units) over up to
:data:`BOUND_RANGES` consecutive ranges of the sample times. Every sample is read once, one
prim and time at a time (memory stays one sample's points).
"""

import os
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import numpy as np

from .errors import InputError
from .terminal import printable

if TYPE_CHECKING:
    from pxr import Usd

__all__ = ["BOUND_RANGES", "CacheInfo", "PrimInfo", "cache_info", "info_lines",
           "is_point_cache", "open_stage"]

BOUND_RANGES = 4
"""Consecutive ranges of the sample times that :func:`cache_info` gives bounds for."""

_ATTRIBUTES = (("normals", ("normals", "primvars:normals")), ("velocities", ("velocities",)),
               ("accelerations", ("accelerations",)), ("uvs", ("primvars:st",)),
               ("extent", ("extent",)))


@dataclass
class PrimInfo:
    """One point-based prim of a cache.

    Attributes
    ----------
    path : str
        Prim path.
    type_name : str
        USD schema (``Mesh``, ``Points``, ``BasisCurves``, ...).
    points : int
        Point count (of the first sample; the default value when not animated).
    faces : int or None
        Faces of a mesh (``faceVertexCounts``), None for other prims.
    samples : (S,) float64
        Time codes of the points' samples (empty: not animated).
    attributes : dict
        What else it holds: ``"normals"``, ``"velocities"``, ``"accelerations"``, ``"uvs"``,
        ``"extent"`` → ``(attribute name, number of time samples)`` (0: a static value).
    problems : list of str
        Samples whose point count differs from ``points``, non-finite points.
    """

    path: str
    type_name: str
    points: int
    faces: int | None
    samples: np.ndarray
    attributes: dict = field(default_factory=dict)
    problems: list = field(default_factory=list)


@dataclass
class CacheInfo:
    """A point cache's contents (:func:`cache_info`).

    Attributes
    ----------
    path : str
    prims : list of PrimInfo
    times : (T,) float64
        Every prim's sample times together, sorted (empty when nothing is animated).
    time_codes_per_second, frames_per_second : float
    up_axis : str
    meters_per_unit : float
    clip_layers : int
        Value-clip layers the stage's prims refer to (0: none).
    bounds : list of (start, end, lo, hi)
        Time-code range (of :attr:`times`) and world-space (3,) float64 bounds over it, in stage
        units; one entry over the static points when nothing is animated.
    """

    path: str
    prims: list
    times: np.ndarray
    time_codes_per_second: float
    frames_per_second: float
    up_axis: str
    meters_per_unit: float
    clip_layers: int
    bounds: list


def _has_skel_root(stage: "Usd.Stage") -> bool:
    from pxr import Usd, UsdSkel
    return any(p.IsA(UsdSkel.Root) for p in stage.Traverse(Usd.TraverseInstanceProxies()))


def _point_prims(stage: "Usd.Stage") -> list:
    from pxr import Usd, UsdGeom
    return [p for p in stage.Traverse(Usd.TraverseInstanceProxies())
            if p.IsA(UsdGeom.PointBased)]


def open_stage(path: "str | os.PathLike | Usd.Stage") -> "Usd.Stage":
    """The USD stage of ``path`` (a stage is returned as it is); InputError if unreadable."""
    if hasattr(path, "Traverse"):
        return path
    from .readers import usd
    return usd.open_stage(path)


def is_point_cache(stage: "str | os.PathLike | Usd.Stage") -> bool:
    """Whether a USD stage (or file) is a point cache: no ``SkelRoot``, some point-based prim."""
    stage = open_stage(stage)
    return not _has_skel_root(stage) and bool(_point_prims(stage))


def _prim_info(prim: Any) -> PrimInfo:
    from pxr import UsdGeom
    geom = UsdGeom.PointBased(prim)
    points_attr = geom.GetPointsAttr()
    samples = np.asarray(points_attr.GetTimeSamples(), dtype=np.float64)
    first = points_attr.Get(float(samples[0])) if len(samples) else points_attr.Get()
    faces = None
    if prim.IsA(UsdGeom.Mesh):
        counts = UsdGeom.Mesh(prim).GetFaceVertexCountsAttr().Get()
        faces = 0 if counts is None else len(counts)
    info = PrimInfo(str(prim.GetPath()), str(prim.GetTypeName()),
                    0 if first is None else len(first), faces, samples)
    for key, names in _ATTRIBUTES:
        for name in names:
            attr = prim.GetAttribute(name)
            if attr and attr.HasAuthoredValue():
                info.attributes[key] = (name, attr.GetNumTimeSamples())
                break
    return info


def _world_points(prim: Any, time: float | None) -> np.ndarray:
    """(P, 3) float64 world-space points of ``prim`` at ``time`` (None: the default value)."""
    from pxr import Usd, UsdGeom
    code = Usd.TimeCode.Default() if time is None else Usd.TimeCode(time)
    value = UsdGeom.PointBased(prim).GetPointsAttr().Get(code)
    p = np.asarray(value if value is not None else [], dtype=np.float64).reshape(-1, 3)
    m = np.asarray(UsdGeom.Imageable(prim).ComputeLocalToWorldTransform(code), np.float64)
    return p @ m[:3, :3] + m[3, :3]  # USD's row vectors: [p, 1] · M


def cache_info(path: "str | os.PathLike | Usd.Stage", ranges: int = BOUND_RANGES) -> CacheInfo:
    """Read a USD point cache back (see the module docstring).

    Parameters
    ----------
    path : str, os.PathLike or pxr.Usd.Stage
        ``.usd``/``.usda``/``.usdc``/``.usdz`` file, or its open stage.
    ranges : int
        Number of consecutive time ranges to give bounds for (≥ 1).

    Returns
    -------
    CacheInfo

    Raises
    ------
    InputError
        Not a readable USD stage, or not a point cache (a ``SkelRoot``, or no point-based prim).
    """
    from pxr import UsdGeom
    stage = open_stage(path)
    path = stage.GetRootLayer().realPath or stage.GetRootLayer().identifier
    if _has_skel_root(stage):
        raise InputError(f"{path}: a skinned character (it has a SkelRoot), not a point cache")
    prims = _point_prims(stage)
    if not prims:
        raise InputError(f"{path}: no point-based prim (mesh, points, curves): not a point cache")
    infos = [_prim_info(p) for p in prims]
    times = np.unique(np.concatenate([i.samples for i in infos]))
    spans = ([(float(t[0]), float(t[-1]), t) for t in np.array_split(times, min(ranges,
                                                                               len(times)))]
             if len(times) else [(np.nan, np.nan, np.zeros(0))])
    bounds = []
    for start, end, span in spans:
        lo, hi = np.full(3, np.inf), np.full(3, -np.inf)
        for prim, info in zip(prims, infos):
            own: list[float | None] = [
                float(t) for t in info.samples[(info.samples >= start) & (info.samples <= end)]]
            if not len(info.samples):  # static points, placed at the range's start
                own = [None] if np.isnan(start) else [start]
            for t in own:
                p = _world_points(prim, t)
                _check_sample(info, p, t)
                ok = p[np.isfinite(p).all(axis=1)]
                if len(ok):
                    lo, hi = np.minimum(lo, ok.min(axis=0)), np.maximum(hi, ok.max(axis=0))
        bounds.append((start, end, lo, hi))
    clip_layers: set[str] = set()
    for prim in stage.Traverse():
        for clip_set in (prim.GetMetadata("clips") or {}).values():
            clip_layers.update(a.path for a in clip_set.get("assetPaths", []))
    return CacheInfo(path, infos, times, float(stage.GetTimeCodesPerSecond()),
                     float(stage.GetFramesPerSecond()), str(UsdGeom.GetStageUpAxis(stage)),
                     float(UsdGeom.GetStageMetersPerUnit(stage)), len(clip_layers), bounds)


def _check_sample(info: PrimInfo, points: np.ndarray, time: float | None) -> None:
    where = "the default value" if time is None else f"time {time:g}"
    if len(points) != info.points and len(info.problems) < 5:
        info.problems.append(f"{len(points)} points at {where} ({info.points} at the first)")
    if not np.isfinite(points).all() and len(info.problems) < 5:
        info.problems.append(f"non-finite points at {where}")


def _vec(v: np.ndarray) -> str:
    return "(" + ", ".join(f"{x:.4g}" for x in v) + ")"


def info_lines(info: CacheInfo) -> list[str]:
    """``dqskin info``'s lines for a point cache (names shown with ``repr``, so a name cannot
    write control characters to a terminal)."""
    t, tcps = info.times, info.time_codes_per_second
    lines = [printable(info.path)]
    points = sum(i.points for i in info.prims)
    prims = f"{len(info.prims)} prim" + ("s" if len(info.prims) != 1 else "")
    lines.append(f"  point cache: {prims}, {points} points; up axis "
                 f"{info.up_axis}, {info.meters_per_unit:g} m/unit")
    if len(t):
        seconds = f"{t[0] / tcps:g} .. {t[-1] / tcps:g} s" if tcps > 0 else "no time unit"
        lines.append(f"  frames: {t[0]:g} .. {t[-1]:g} ({len(t)} samples; time codes at "
                     f"{tcps:g}/s: {seconds}; {info.frames_per_second:g} fps)")
    else:
        lines.append("  frames: none (no prim's points are animated)")
    if info.clip_layers:
        lines.append(f"  value clips: {info.clip_layers} clip layers")
    for i in info.prims:
        shape = f"{i.points} points" + ("" if i.faces is None else f", {i.faces} faces")
        anim = (f"points animated: {len(i.samples)} samples ({i.samples[0]:g} .. "
                f"{i.samples[-1]:g})" if len(i.samples) else "points static")
        lines.append(f"  {i.type_name.lower()} {i.path!r}: {shape}; {anim}")
        held = [f"{key} ({name}, {'static' if n == 0 else f'{n} samples'})"
                for key, (name, n) in i.attributes.items()]
        missing = [key for key, _ in _ATTRIBUTES if key not in i.attributes]
        lines.append("    " + ("; ".join(held) if held else "no normals, velocities or UVs")
                     + (f"; none of: {', '.join(missing)}" if held and missing else ""))
    lines.append("  bounds (world space, stage units):")
    for start, end, lo, hi in info.bounds:
        span = "static" if np.isnan(start) else f"frames {start:g} .. {end:g}"
        box = f"min {_vec(lo)}, max {_vec(hi)}" if np.all(lo <= hi) else "no finite points"
        lines.append(f"    {span}: {box}")
    problems = [f"{i.path!r}: {p}" for i in info.prims for p in i.problems]
    lines.append("  problems: " + ("none" if not problems else ""))
    lines += [f"    - {p}" for p in problems]
    return lines
