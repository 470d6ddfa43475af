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
from collections.abc import Mapping, Sequence
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
from .metrics import character_height
from .options import Method
from .readers import bvh
from .readers.mesh import load_mesh
from .scene import Mesh, Scene
from .skeleton import Skeleton
from .validation import check_points

__all__ = ["WEIGHT_FIELDS", "FitWarning", "check_fit", "fit_problems", "read_joints",
           "read_weights",
           "replace_weights", "rig_mesh", "skinned_difference"]

WEIGHT_FIELDS = ("joint_indices", "joint_weights", "joint_names")
"""Arrays of a weights ``.npz``: (V, K) int, (V, K) float, (J,) str."""

_SIZE_RATIO = 2.0  # mesh and skeleton heights may differ by up to this factor
_INSIDE = 0.75  # share of joints that must lie in the mesh's (padded) bounding box
_FAR = 0.10  # a vertex farther than this share of the height from every bone is "far"
_FAR_SHARE = 0.01  # ... and a fit with this share of far vertices is bad
_OUTSIDE_SHARE = 0.10  # a fit with this share of its bones' midpoints outside the mesh is bad
_FEET_BELOW = 0.02  # the skeleton's lowest point below the mesh's, as a share of its height
_FEET_ABOVE = 0.08  # ... or above it


class FitWarning(UserWarning):
    """A rig that binds but fits its mesh badly (:func:`fit_problems`); one line, with the
    figure."""


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


def check_fit(points: np.ndarray, joint_positions: np.ndarray, where: str, *,
              scale: float = 1.0) -> None:
    """InputError (a ValueError) unless the mesh ``points`` and the skeleton's rest
    ``joint_positions`` are the same size (within a factor 2) and overlap (most joints inside the
    mesh's bounding box, padded by a tenth); the message gives the sizes and the ``scale`` that
    would match them (``scale``: the one the skeleton already has; the suggestion replaces it)."""
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
            "the mesh with ", Param("scale", float(f"{ratio * scale:.4g}")),
            " (or export the mesh in the BVH's units)")
    pad = 0.1 * (hi - lo).max()
    inside = np.all((joint_positions >= lo - pad) & (joint_positions <= hi + pad), axis=1)
    if inside.mean() < _INSIDE:
        mc, sc = 0.5 * (lo + hi), 0.5 * (jlo + jhi)
        raise InputError(
            f"{where}: the mesh is far from its skeleton (only {inside.sum()} of {inside.size} "
            f"rest joints and End Sites inside the mesh's bounds; bounding-box centres: mesh "
            f"{np.round(mc, 4).tolist()}, skeleton {np.round(sc, 4).tolist()}): model the mesh "
            "in the BVH's rest pose (every channel zero) and space: add "
            f"{np.round(sc - mc, 4).tolist()} to its points to move it onto the skeleton")


def fit_problems(points: npt.ArrayLike, faces: npt.ArrayLike, skeleton: Skeleton, *,
                 end_sites: list | None = None, up: int = 1) -> list[str]:
    """How a skeleton's bind pose misfits a mesh, one line per problem (empty when it fits):

    * vertices far from every bone: more than 1% of them farther than 10% of the mesh's height
      from their nearest bone segment (:func:`dqskin.autoweights.bone_segments`);
    * bones outside the mesh: more than 10% of the bones' midpoints outside the surface
      (generalized winding number below ½);
    * feet off the floor: the skeleton's lowest point (joints and End Sites) more than 2% of the
      height below the mesh's lowest point, or more than 8% above it, along axis ``up``.

    Parameters
    ----------
    points : (V, 3) float
        Rest points, in the skeleton's space.
    faces : (T, 3) int
    skeleton : dqskin.Skeleton
        Its bind transforms place the bones.
    end_sites : list of (joint, (3,) float), optional
        BVH End Sites (joint-local leaf tips).
    up : int
        The up axis (0, 1, 2): Y by default, as BVH.

    Returns
    -------
    list of str
        Each line names the problem and its figure in % of the mesh's height.
    """
    from .autoweights import bone_segments
    from .geometry import outside_mesh, segment_distances
    P = np.asarray(points, np.float64)
    F = np.asarray(faces, np.int64).reshape(-1, 3)
    height = float(np.ptp(P[:, up])) if len(P) else 0.0
    if height <= 0:
        return []
    heads, tails, owner = bone_segments(skeleton, end_sites=end_sites)
    out = []
    near = segment_distances(P, heads, tails).min(1) / height
    far = near > _FAR
    if far.mean() > _FAR_SHARE:
        out.append(f"{100 * far.mean():.1f}% of the vertices are farther than "
                   f"{100 * _FAR:.0f}% of the height from every bone (farthest "
                   f"{100 * near.max():.1f}%)")
    long = np.linalg.norm(tails - heads, axis=1) > 1e-6 * height
    if F.size and long.any():
        mid = 0.5 * (heads[long] + tails[long])
        outside = outside_mesh(mid, P, F)
        if outside.mean() > _OUTSIDE_SHARE:
            names = sorted({skeleton.joint_names[j] for j in owner[long][outside]})
            out.append(f"{outside.sum()} of {outside.size} bones lie outside the mesh "
                       f"({', '.join(names[:4])}{' …' if len(names) > 4 else ''})")
    tips = np.concatenate([heads, tails])
    gap = (tips[:, up].min() - P[:, up].min()) / height
    if gap < -_FEET_BELOW or gap > _FEET_ABOVE:
        out.append(f"the skeleton's feet are {100 * abs(gap):.1f}% of the height "
                   f"{'below' if gap < 0 else 'above'} the mesh's lowest point")
    return out


def read_joints(path: str | os.PathLike) -> dict[str, list[float]]:
    """Joint positions from a ``.json`` file: ``{name: [x, y, z], ...}``, or that mapping under
    a ``"joints"`` key. Raises InputError naming the file for anything else."""
    import json
    p = Path(path)
    try:
        data = json.loads(p.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise InputError(f"{p}: cannot read joints: {exc}") from None
    if isinstance(data, dict) and isinstance(data.get("joints"), dict):
        data = data["joints"]
    if not isinstance(data, dict) or not all(
            isinstance(v, list) and len(v) == 3
            and all(isinstance(x, (int, float)) and not isinstance(x, bool) for x in v)
            for v in data.values()):
        raise InputError(f"{p}: expected {{joint name: [x, y, z], ...}} (optionally under "
                         "\"joints\")")
    return {str(k): [float(x) for x in v] for k, v in data.items()}


def rig_mesh(mesh: str | os.PathLike | tuple[npt.ArrayLike, npt.ArrayLike],
             skeleton: str | os.PathLike | bvh.BvhMotion, *,
             weights: str | os.PathLike | None = "auto", scale: float | None = None,
             as_is: bool = False,
             joints: str | os.PathLike | Mapping[str, npt.ArrayLike] | None = None,
             max_influences: int = 8, cache: bool = True, max_vertices: int = MAX_RIG_VERTICES,
             max_input_gib: float = MAX_INPUT_GIB, device: Device = None) -> Scene:
    """Bind a plain mesh to a BVH's skeleton and motion.

    Parameters
    ----------
    mesh : path or (points (V, 3), faces (T, 3))
        ``.obj/.ply/.stl/.off/.glb`` geometry (:func:`dqskin.load_mesh`), +Y up as BVH.
    skeleton : path or BvhMotion
        The ``.bvh`` file.
    weights : "auto", path or None
        "auto" (or None): bone heat (:func:`dqskin.autoweights.automatic_weights`, cached);
        a path: an ``.npz`` read by :func:`read_weights`.
    scale : float, optional
        Multiplies the skeleton's lengths (offsets, End Sites, root positions) into the mesh's
        unit, e.g. 0.0254 for a skeleton in inches and a mesh in metres (``as_is=True``).
    as_is : bool
        False (the default): the skeleton is placed in the mesh, whatever its rest pose, size and
        position (:func:`dqskin.embedding.embed_skeleton`), the motion retargeted to it
        (:func:`dqskin.retarget.retarget`) and the skinned feet put on the mesh's floor at every
        frame (:func:`dqskin.retarget.feet_on_the_floor`). True: the mesh is modelled in
        the BVH's rest pose (every channel zero), space and unit (after ``scale``);
        :func:`check_fit` refuses one that is far from the skeleton or in other units and says
        how to fix it.
    joints : path, or mapping of str to (3,) float, optional
        Without ``as_is``: joint positions (mesh space) that override the embedding, by name
        (a ``.json`` file read by :func:`read_joints`).
    max_influences : int
        Influences kept per vertex by automatic weights.
    max_vertices : int
        Largest mesh given automatic weights (:func:`dqskin.limits.check_vertices`).
    max_input_gib : float
        Largest array the BVH or the weights file may ask for (:mod:`dqskin.limits`).

    Returns
    -------
    dqskin.Scene
        Path of the BVH file, its frames as times (``time_codes_per_second``:
        :attr:`~dqskin.readers.bvh.BvhMotion.frame_rate`), one mesh (named after the mesh file)
        on skeleton 0, method "lbs"; the skeleton's space is the world (``output_transforms``
        and ``world_transforms`` None).

    Warns
    -----
    FitWarning
        One per problem :func:`fit_problems` finds (a rig that binds but fits badly).

    Raises
    ------
    InputError
        (a ValueError) Unreadable inputs, a mesh far from the skeleton or in other units (naming the
        fix), a weights or joints file that does not fit.
    LimitError
        Beyond ``max_vertices`` or ``max_input_gib``.
    """
    import warnings
    motion = skeleton if isinstance(skeleton, bvh.BvhMotion) else bvh.read_bvh(
        skeleton, max_input_gib=max_input_gib)
    if joints is not None and as_is:
        raise InputError(Param("joints"), " places joints of an embedded skeleton; ",
                         Param("as_is", True), " binds the BVH's own")
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
    end_sites = motion.end_sites
    if not as_is:
        from .embedding import embed_skeleton
        from .retarget import retarget
        given = read_joints(joints) if isinstance(joints, (str, os.PathLike)) else joints
        embedded = embed_skeleton((points, faces), skel, joints=given, end_sites=end_sites)
        end_sites = _embedded_end_sites(skel, embedded, end_sites)
        skel = retarget(motion, embedded)
    else:
        from .geometry import end_site_points
        bind = skel.bind_transforms
        check_fit(points.astype(np.float64),
                  np.concatenate([bind[:, :3, 3], end_site_points(bind, end_sites)]),
                  f"{where} on {motion.path}", scale=1.0 if scale is None else float(scale))
    for line in fit_problems(points, faces, skel, end_sites=end_sites):
        warnings.warn(FitWarning(f"{where} on {motion.path}: {line}"), stacklevel=2)
    if weights is None or str(weights) == "auto":
        check_vertices(len(points), where, max_vertices)
        idx, w = automatic_weights(points, faces, skel, end_sites=end_sites,
                                   max_influences=max_influences, cache=cache, device=device)
    else:
        idx, w = read_weights(weights, skel.joint_names, len(points),
                              max_input_gib=max_input_gib)
    if not as_is:  # the skinned feet on the floor whenever the capture's are
        from .retarget import feet_on_the_floor
        skel = feet_on_the_floor(skel, motion, points, idx, w)
    m = Mesh(name=name, points=points, faces=faces, joint_indices=idx, joint_weights=w,
             skinning_method="lbs")
    return Scene(motion.path, [m], [skel], np.arange(motion.frame_count, dtype=np.float64),
                 time_codes_per_second=motion.frame_rate, up_axis="Y")


def _embedded_end_sites(source: Skeleton, embedded: Skeleton, end_sites: list) -> list:
    """End Sites (joint-local) of an embedded skeleton: the source's, scaled by the ratio of the
    joint's embedded bone to its source bone (the rotations carry the rest-pose difference)."""
    a, b = source.bind_transforms[:, :3, 3], embedded.bind_transforms[:, :3, 3]
    out = []
    for j, off in end_sites:
        p = source.parents[j]
        la = float(np.linalg.norm(a[j] - a[p])) if p >= 0 else 0.0
        k = float(np.linalg.norm(b[j] - b[p])) / la if la > 0 else 1.0
        out.append((j, np.asarray(off, np.float64) * k))
    return out


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
        height = character_height(rest)
        d = np.linalg.norm(ref.points[m.name].astype(np.float64)
                           - got.points[m.name].astype(np.float64), axis=-1)
        d = d / (height or 1.0) * 100
        out[m.name] = (float(d.mean(1).max()), float(np.percentile(d, 95, axis=1).max()))
    return out
