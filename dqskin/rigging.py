"""Rigging: a plain mesh bound to a BVH skeleton, and weights replaced on skinned characters.

:func:`rig_mesh` turns a mesh modelled in a BVH file's rest pose (every channel zero) into a
:class:`dqskin.Scene`: the BVH's :class:`dqskin.Skeleton` and animation, and one
:class:`dqskin.Mesh` whose influences are computed (:mod:`dqskin.autoweights`, bone heat) or read
from an ``.npz`` (:func:`read_weights`). The mesh is in the skeleton's space (no geom bind
transform); :func:`check_fit` refuses a mesh that is far from its skeleton or in other units, and
says how to fix it (``scale``: multiply the skeleton's lengths).

:func:`replace_weights` swaps the artist's influences of a loaded character for automatic ones
(or a file's), so the two can be compared under the character's own animation.
"""

import os
from collections.abc import Sequence
from dataclasses import replace
from pathlib import Path

import numpy as np
import numpy.typing as npt

from ._warp import Device
from .autoweights import automatic_weights
from .errors import InputError, Param
from .files.inputs import read_npz
from .influences import check_influences
from .limits import MAX_INPUT_GIB, MAX_RIG_VERTICES, check_vertices
from .options import Method
from .readers import bvh
from .readers.mesh import load_mesh
from .scene import Mesh, Scene
from .validation import check_points

__all__ = ["WEIGHT_FIELDS", "check_fit", "read_weights", "replace_weights", "rig_mesh",
           "skinned_difference"]

WEIGHT_FIELDS = ("joint_indices", "joint_weights", "joint_names")
"""Arrays of a weights ``.npz``: (V, K) int, (V, K) float, (J,) str."""

_SIZE_RATIO = 2.0  # mesh and skeleton heights may differ by up to this factor
_INSIDE = 0.75  # share of joints that must lie in the mesh's (padded) bounding box


def read_weights(path: str | os.PathLike, joint_names: Sequence[str], vertex_count: int, *,
                 max_input_gib: float = MAX_INPUT_GIB) -> tuple[np.ndarray, np.ndarray]:
    """Influences from an ``.npz`` with :data:`WEIGHT_FIELDS`, re-indexed by joint name into
    ``joint_names`` order: ``(indices (V, K) int32, weights (V, K) float32)``.

    Raises InputError (a ValueError) naming the file and field: an unreadable file (missing, not a
    regular file, empty, truncated, not an ``.npz``), missing arrays, wrong shapes, joints the
    skeleton does not have, bad indices or weights; LimitError for an array beyond
    ``max_input_gib`` (:func:`dqskin.files.inputs.read_npz`, checked before it is read).
    """
    p = Path(path)
    z = read_npz(p, WEIGHT_FIELDS, what="weights", max_input_gib=max_input_gib)
    idx, wts, stored = (z[f] for f in WEIGHT_FIELDS)
    names = [str(n) for n in np.ravel(stored)]
    try:
        idx, wts = check_influences(idx, wts, vertex_count, len(names))
    except ValueError as exc:
        raise InputError(f"{p}: {exc} (the mesh has {vertex_count} points)") from None
    index = {n: k for k, n in enumerate(joint_names)}
    unknown = [n for n in names if n not in index]
    if unknown:
        raise InputError(f"{p}: joint_names: {', '.join(map(repr, unknown[:5]))}"
                         f"{' and more' if len(unknown) > 5 else ''} not in the skeleton")
    remap = np.array([index[n] for n in names], np.int32)
    return (remap[idx] if idx.size else idx.astype(np.int32)), wts


def check_fit(points: np.ndarray, joint_positions: np.ndarray, where: str) -> None:
    """InputError (a ValueError) unless the mesh ``points`` and the skeleton's rest
    ``joint_positions`` are the same size (within a factor 2) and overlap (most joints inside the
    mesh's bounding box, padded by a tenth); the message gives the sizes and the ``scale`` that
    would match them."""
    lo, hi = points.min(0), points.max(0)
    size_mesh = float((hi - lo).max())
    jlo, jhi = joint_positions.min(0), joint_positions.max(0)
    size_skel = float((jhi - jlo).max())
    if size_mesh <= 0 or size_skel <= 0:
        return
    ratio = size_mesh / size_skel
    if not 1 / _SIZE_RATIO <= ratio <= _SIZE_RATIO:
        raise InputError(
            f"{where}: the mesh is {ratio:.3g}× the size of the skeleton (mesh {size_mesh:.4g}, "
            f"skeleton {size_skel:.4g} units across): different units? Scale the skeleton to "
            "the mesh with ", Param("scale", float(f"{ratio:.4g}")),
            " (or export the mesh in the BVH's units)")
    pad = 0.1 * (hi - lo).max()
    inside = np.all((joint_positions >= lo - pad) & (joint_positions <= hi + pad), axis=1)
    if inside.mean() < _INSIDE:
        mc, sc = 0.5 * (lo + hi), 0.5 * (jlo + jhi)
        raise InputError(
            f"{where}: the mesh is far from its skeleton (only {inside.sum()} of {inside.size} "
            f"rest joints inside the mesh's bounds; mesh centre {np.round(mc, 4).tolist()}, "
            f"skeleton centre {np.round(sc, 4).tolist()}): model the mesh in the BVH's rest pose "
            "(every channel zero) and space, moved by "
            f"{np.round(mc - sc, 4).tolist()} back onto the skeleton")


def rig_mesh(mesh: str | os.PathLike | tuple[npt.ArrayLike, npt.ArrayLike],
             skeleton: str | os.PathLike | bvh.BvhMotion, *,
             weights: str | os.PathLike | None = "auto", scale: float | None = None,
             max_influences: int = 8, cache: bool = True, max_vertices: int = MAX_RIG_VERTICES,
             max_input_gib: float = MAX_INPUT_GIB, device: Device = None) -> Scene:
    """Bind a plain mesh in a BVH's rest pose to the BVH's skeleton and motion.

    Parameters
    ----------
    mesh : path or (points (V, 3), faces (T, 3))
        ``.obj/.ply/.stl/.off/.glb`` geometry (:func:`dqskin.load_mesh`), in the skeleton's
        space and length unit (after ``scale``) and rest pose.
    skeleton : path or BvhMotion
        The ``.bvh`` file.
    weights : "auto", path or None
        "auto" (or None): bone heat (:func:`dqskin.autoweights.automatic_weights`, cached);
        a path: an ``.npz`` read by :func:`read_weights`.
    scale : float, optional
        Multiplies the skeleton's lengths (offsets, End Sites, root positions) into the mesh's
        unit, e.g. 0.0254 for a skeleton in inches and a mesh in metres.
    max_influences : int
        Influences kept per vertex by automatic weights.
    max_vertices : int
        Largest mesh given automatic weights (:func:`dqskin.limits.check_vertices`).
    max_input_gib : float
        Largest array the BVH or the weights file may ask for (:mod:`dqskin.limits`).

    Returns
    -------
    dqskin.Scene
        Path of the BVH file, its frames as times (``time_codes_per_second = 1 / Frame Time``),
        one mesh (named after the mesh file) on skeleton 0, method "lbs"; the skeleton's space
        is the world (``output_transforms`` and ``world_transforms`` None).

    Raises
    ------
    InputError
        (a ValueError) Unreadable inputs, a mesh far from the skeleton or in other units (naming the
        fix), a weights file that does not fit.
    LimitError
        Beyond ``max_vertices`` or ``max_input_gib``.
    """
    motion = skeleton if isinstance(skeleton, bvh.BvhMotion) else bvh.read_bvh(
        skeleton, max_input_gib=max_input_gib)
    if scale is not None and float(scale) != 1.0:
        motion = bvh.scaled(motion, scale)
    if isinstance(mesh, tuple):
        points, faces = (np.asarray(a) for a in mesh)
        name, where = "mesh", "mesh"
        check_points(where, np.asarray(points, np.float64))  # (load_mesh checks its own)
    else:
        points, faces = load_mesh(mesh)
        name, where = Path(mesh).stem or "mesh", str(mesh)
    points = np.asarray(points, np.float32)
    faces = np.asarray(faces, np.int32).reshape(-1, 3)
    skel = motion.skeleton()
    check_fit(points.astype(np.float64), skel.bind_transforms[:, :3, 3],
              f"{where} on {motion.path}")
    if weights is None or str(weights) == "auto":
        check_vertices(len(points), where, max_vertices)
        idx, w = automatic_weights(points, faces, skel, end_sites=motion.end_sites,
                                   max_influences=max_influences, cache=cache, device=device)
    else:
        idx, w = read_weights(weights, skel.joint_names, len(points),
                              max_input_gib=max_input_gib)
    m = Mesh(name=name, points=points, faces=faces, joint_indices=idx, joint_weights=w,
             skinning_method="lbs")
    return Scene(motion.path, [m], [skel], np.arange(motion.frame_count, dtype=np.float64),
                 time_codes_per_second=1.0 / motion.frame_time, up_axis="Y")


def replace_weights(scene: Scene, weights: str | os.PathLike = "auto", *,
                    max_influences: int = 8, cache: bool = True,
                    max_vertices: int = MAX_RIG_VERTICES, max_input_gib: float = MAX_INPUT_GIB,
                    device: Device = None) -> Scene:
    """``scene`` with every mesh's influences replaced: "auto" (bone heat from the mesh's bind
    pose and its skeleton's bind transforms) or an ``.npz`` (:func:`read_weights`; the scene
    must then have one mesh).

    Automatic weights use the joints the mesh's skin deforms with (those its influences refer
    to): a glTF skeleton also holds the skin's ancestors (an "Armature" node), which take no
    weight. The artist's weights themselves are not used. Returns a new Scene sharing the
    skeletons. ``max_vertices`` and ``max_input_gib`` as in :func:`rig_mesh`.
    """
    meshes = []
    if str(weights) != "auto" and len(scene.meshes) != 1:
        raise InputError(f"{weights}: a weights file applies to a scene with one mesh; "
                         f"{scene.path} has {len(scene.meshes)}")
    for m in scene.meshes:
        skel = scene.skeletons[m.skeleton]
        if str(weights) == "auto":
            check_vertices(len(m.points), f"{scene.path}: {m.name}", max_vertices)
            used = np.unique(np.asarray(m.joint_indices)[np.asarray(m.joint_weights) > 0])
            idx, w = automatic_weights(m.points, m.faces, skel,
                                       geom_bind_transform=m.geom_bind_transform,
                                       joints=used if used.size else None,
                                       max_influences=max_influences, cache=cache,
                                       device=device)
        else:
            idx, w = read_weights(weights, skel.joint_names, len(m.points),
                                  max_input_gib=max_input_gib)
        meshes.append(replace(m, joint_indices=idx, joint_weights=w))
    return replace(scene, meshes=meshes, _skinners={})


def skinned_difference(reference: Scene, other: Scene, times: npt.ArrayLike | None = None, *,
                       method: Method = "lbs", device: Device = None
                       ) -> dict[str, tuple[float, float]]:
    """How far ``other``'s skinned points are from ``reference``'s (the same scene with other
    weights, e.g. from :func:`replace_weights`), as a share of each mesh's height.

    Both are skinned with ``method`` at ``times`` (default the reference's) in skeleton space.
    Returns ``{mesh name: (mean, p95)}``: the mean and 95th percentile over the vertices of the
    distance, in % of the largest extent of the mesh's bind-pose points, at the worst frame.
    """
    times = reference.times if times is None else times
    ref = reference.skin(times, method=method, space="skeleton", device=device)
    got = other.skin(times, method=method, space="skeleton", device=device)
    out: dict[str, tuple[float, float]] = {}
    for m in reference.meshes:
        g = np.asarray(m.geom_bind_transform, np.float64)
        rest = np.asarray(m.points, np.float64) @ g[:3, :3].T + g[:3, 3]
        height = float(np.ptp(rest, axis=0).max()) if len(rest) else 0.0
        d = np.linalg.norm(ref.points[m.name].astype(np.float64)
                           - got.points[m.name].astype(np.float64), axis=-1)
        d = d / (height or 1.0) * 100
        out[m.name] = (float(d.mean(1).max()), float(np.percentile(d, 95, axis=1).max()))
    return out
