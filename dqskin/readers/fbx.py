"""FBX characters (binary and ASCII, FBX 5.0 to 7.7) read by ufbx into a
:class:`~dqskin.scene.Scene`.

ufbx runs in a process of its own (:mod:`.fbx_extract`, the only module that calls it): what it
evaluates comes back as plain arrays, and a file that makes ufbx fail, or crash, is one
:class:`~dqskin.errors.InputError` here. What is read:

* Every mesh (its first instance): rest points (the file's geometry space), polygons (kept as
  ``face_vertex_counts``/``face_vertex_indices``, fan-triangulated for ``faces``), face-varying
  normals and UVs. A mesh with a skin deformer is skinned by its clusters (any number of
  influences per vertex); a mesh without one moves rigidly with its node (one influence).
* The skinning method of the skin deformer is the mesh's ``skinning_method``: linear (and
  rigid) "lbs", dual quaternion "dqs", blended "blend" with the file's per-vertex DQ weights as
  ``blend_weights`` (Maya's "Weight Blended", 3ds Max's Skin modifier).
* Joints: the nodes the clusters bind (and each rigid mesh's node) with their ancestors, the
  scene root left out. Their world transforms are ufbx's (rotation orders, pre/post rotations,
  pivots, geometric transforms and scale inheritance as the file says) at every whole frame of
  the animation stack, read with the file, and at any other time a scene is skinned at (the
  file's curves: the reader's process runs again on those times, at most once per time); the
  local transforms are recovered from them, so forward kinematics gives ufbx's world
  transforms back. Times outside the stack hold its first and last frames. Velocities are
  those of the keyed motion through the whole frames and the times skinned between them
  (rotation slerp, translation and scale lerp, as
  :class:`~dqskin.animation.KeyedAnimation`); interpolations other than "trs" interpolate the
  whole frames.
* Bind transforms: cluster ``c`` of a mesh skins a point ``p`` as ufbx does,
  ``bone_to_world(t) · geometry_to_bone_c · p``; the skeleton's bind transform of its bone is
  ``G · geometry_to_bone_c⁻¹`` with ``G`` the mesh's geometry-to-world at the stored pose (its
  ``geom_bind_transform``). Meshes whose bind transforms of a shared bone differ get skeletons
  of their own.
* Blend shapes (with in-betweens and animated weights): ufbx's effective weight of every
  in-between at every time skinned, applied before skinning.
* Every animation stack is a clip (``clip``: name or index; the first by default). Times are
  seconds (``time_codes_per_second`` 1), the stack's whole frames at the file's frame rate
  (``frame_rate``) from its start to its end: frame ``f`` is ``f / frame_rate`` seconds. A
  file without a stack is its stored pose at time 0.
* World space is the file's own: ``up_axis`` and ``meters_per_unit`` as its settings say (no
  conversion). Points are skinned in world space, which is also each mesh's local space.
"""

from __future__ import annotations

import io
import json
import os
import signal
import subprocess
import sys
import threading
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import numpy.typing as npt

from ..animation import Deformer, check_times, segment_rates
from ..errors import InputError, LimitError, UnknownNameError
from ..files.inputs import regular_file
from ..limits import MAX_INPUT_GIB, check_bytes
from ..topology import fan_corners
from . import LOADER_SUFFIXES

if TYPE_CHECKING:
    from ..scene import Scene

__all__ = ["SUFFIXES", "load"]

SUFFIXES = LOADER_SUFFIXES["fbx"]

_EXTRACT = Path(__file__).with_name("fbx_extract.py")
_UP = {2: "Y", 3: "Y", 4: "Z", 5: "Z"}
"""ufbx's up axis (``CoordinateAxis``) → :attr:`dqskin.Scene.up_axis` (X up is read as Y)."""
_METHODS = {0: "lbs", 1: "lbs", 2: "dqs", 3: "blend"}
"""ufbx ``SkinningMethod`` (linear, rigid, dual quaternion, blended) → dqskin's method."""
_BIND_TOLERANCE = 1e-6
"""Relative difference below which two bind transforms of one bone are the same."""


def _extract(path: Path, clip: str | int | None, max_input_gib: float = MAX_INPUT_GIB,
             at: np.ndarray | None = None) -> tuple[dict, dict[str, np.ndarray]]:
    """Run :mod:`.fbx_extract` on ``path``: ``(meta, arrays)``, at the stack's frames or, with
    ``at``, at these seconds of stack number ``clip``; InputError naming the file when ufbx
    fails or its process dies, LimitError when its transforms would exceed ``max_input_gib``."""
    arg = "-" if clip is None else str(clip)
    command = [sys.executable, "-I", str(_EXTRACT), str(path), arg,
               str(int(max_input_gib * (1 << 30)))] + ([] if at is None else ["at"])
    try:
        done = subprocess.run(command, capture_output=True, check=False,
                              input=b"" if at is None else np.asarray(at, "<f8").tobytes())
    except OSError as exc:
        raise InputError(f"{path}: could not start the FBX reader ({exc})") from None
    why = done.stderr.decode("utf-8", "replace").strip().splitlines()
    if done.returncode < 0:
        try:
            name = signal.Signals(-done.returncode).name
        except ValueError:
            name = f"signal {-done.returncode}"
        raise InputError(f"{path}: ufbx crashed reading it ({name}); the file is damaged or "
                         "uses something ufbx cannot read")
    if done.returncode != 0:
        text = why[-1] if why else f"exit status {done.returncode}"
        if text.startswith("LookupError: "):
            raise UnknownNameError(f"{path}: {text.removeprefix('LookupError: ')}")
        if text.startswith("LimitBytes: "):
            need, what = text.removeprefix("LimitBytes: ").split(" ", 1)
            check_bytes(int(need), f"{path}: {what}", max_input_gib)
        if text.startswith("LimitExceeded: "):
            raise LimitError(f"{path}: {text.removeprefix('LimitExceeded: ')}")
        raise InputError(f"{path}: not a readable FBX file ({text})")
    try:
        with np.load(io.BytesIO(done.stdout), allow_pickle=False) as z:
            arrays = {k: z[k] for k in z.files}
        meta = json.loads(str(arrays.pop("meta")))
    except (ValueError, OSError, KeyError) as exc:
        raise InputError(f"{path}: the FBX reader returned nothing usable ({exc})") from None
    return meta, arrays


def _unique(names: list[str], fallback: str) -> list[str]:
    """``names`` made unique (``name``, ``name#2``, ...); empty names become ``fallback``+index."""
    seen: dict[str, int] = {}
    out = []
    for i, n in enumerate(names):
        n = n or f"{fallback}{i}"
        k = seen.get(n, 0) + 1
        seen[n] = k
        out.append(n if k == 1 else f"{n}#{k}")
    return out


def _inverse(m: np.ndarray, what: str) -> np.ndarray:
    """Inverse of (..., 4, 4) ``m``; InputError naming ``what`` when singular or not finite."""
    if not np.all(np.isfinite(m)):
        raise InputError(f"{what}: NaN or infinite transform")
    with np.errstate(all="ignore"):
        cond = np.linalg.cond(m)
    if not np.all(cond < 1e12):
        raise InputError(f"{what}: singular transform")
    return np.linalg.inv(m)


def _polygons(arrays: dict, key: str,
              name: str) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Polygons of a mesh: ``(faces (T, 3), counts, indices, corner mask)``: triangles fanned
    from the polygons of three or more corners (points and lines dropped), those polygons'
    corner counts and vertex indices, and which face corners they keep."""
    faces = arrays[key + "faces"].astype(np.int64)
    idx = arrays[key + "indices"].astype(np.int64)
    V = len(arrays[key + "points"])
    if idx.size and (idx.min() < 0 or idx.max() >= V):
        raise InputError(f"{name}: vertex index out of range for {V} points")
    begin, count = (faces[:, 0], faces[:, 1]) if faces.size else (np.zeros(0, np.int64),) * 2
    if np.any(begin + count > idx.size) or np.any(begin < 0):
        raise InputError(f"{name}: polygons out of range of the vertex indices")
    keep = count >= 3
    corner = np.zeros(idx.size, bool)
    starts = begin[keep]
    counts = count[keep]
    tris = idx[fan_corners(count, keep, begin)]
    if counts.size:
        marks = np.repeat(starts, counts) + (np.arange(int(counts.sum()))
                                             - np.repeat(np.cumsum(counts) - counts, counts))
        corner[marks] = True
    return tris.astype(np.int32).reshape(-1, 3), counts.astype(np.int32), idx[corner], corner


_ON_KEY = 1e-6
"""Frames within which a time is on a whole frame of the stack (no evaluation of its own)."""
_CACHE_TIMES = 4096
"""Times between frames whose evaluation is kept for later calls."""


class _Evaluator:
    """ufbx's evaluation of one animation stack: the joints' world transforms and the blend-shape
    weights at the stack's whole frames (``seconds``), and at any other time on demand (the
    reader's process run again on those times, kept for later calls)."""

    def __init__(self, path: Path, index: int, fps: float, max_input_gib: float,
                 seconds: np.ndarray, world: np.ndarray, weights: dict[int, np.ndarray]) -> None:
        self.path, self.index, self.fps, self.max_input_gib = path, index, fps, max_input_gib
        self.seconds, self.world, self.weights = seconds, world, weights
        self._more: dict[float, tuple[np.ndarray, dict[int, np.ndarray]]] = {}
        self._lock = threading.Lock()

    def split(self, times: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``(frame, off)``: each time (clamped to the stack) as the index of its whole frame,
        -1 for the times between frames, and those times (sorted, unique)."""
        t = np.clip(times, self.seconds[0], self.seconds[-1])
        f = np.clip(np.round((t - self.seconds[0]) * self.fps), 0,
                    len(self.seconds) - 1).astype(np.int64)
        on = np.abs((t - self.seconds[f]) * self.fps) <= _ON_KEY
        return np.where(on, f, -1), np.unique(t[~on])

    def between(self, off: np.ndarray) -> tuple[np.ndarray, dict[int, np.ndarray]]:
        """World transforms (T, N, 4, 4) and blend-shape weights of the times ``off`` (between
        frames), evaluated by ufbx."""
        with self._lock:
            missing = [x for x in off.tolist() if x not in self._more]
            if missing:
                meta, arrays = _extract(self.path, self.index, self.max_input_gib,
                                        np.asarray(missing, np.float64))
                for i, x in enumerate(missing):
                    self._more[x] = (arrays["world"][i],
                                     {k: arrays[f"m{k}/shape_weights"][i] for k in self.weights})
            rows = [self._more[x] for x in off.tolist()]
            for x in list(self._more)[:max(0, len(self._more) - max(_CACHE_TIMES, len(off)))]:
                del self._more[x]
        world = np.stack([r[0] for r in rows]) if rows else np.zeros((0,) + self.world.shape[1:])
        return world, {k: np.stack([r[1][k] for r in rows]) if rows
                       else np.zeros((0,) + w.shape[1:]) for k, w in self.weights.items()}

    def keys(self, times: np.ndarray, values: Callable[[np.ndarray], np.ndarray],
             between: Callable[[np.ndarray], np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
        """Key times and values to interpolate ``times`` between: the whole frames next to
        each time (and one more on either side) and every time between frames, exact.
        ``values(frames)``: the values at frame indices; ``between(off)``: at other times."""
        _, off = self.split(times)
        t = np.clip(times, self.seconds[0], self.seconds[-1])
        below = np.floor((t - self.seconds[0]) * self.fps + _ON_KEY).astype(np.int64)
        near = np.unique(np.clip(np.concatenate([below - 1, below, below + 1, below + 2]), 0,
                                 len(self.seconds) - 1))
        key_times = np.concatenate([self.seconds[near], off])
        order = np.argsort(key_times, kind="stable")
        return key_times[order], np.concatenate([values(near), between(off)])[order]


def _exact_poses(evaluator: _Evaluator, slots: list[int], parents: list[int], label: str
                 ) -> Callable[[np.ndarray], tuple[np.ndarray, np.ndarray] | None]:
    """``KeyedAnimation``'s ``refine`` for one skeleton of an FBX scene: its "trs" poses (the
    file's curves) are ufbx's at every time asked for, between keys at the stack's whole frames
    and at the times between frames asked for (velocities: the keyed interpolation's); None
    (the whole frames serve) when every time is on a frame."""
    def refine(t: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
        if not np.any(evaluator.split(t)[0] < 0):
            return None
        return evaluator.keys(
            t, lambda near: _locals(evaluator.world[near][:, slots], parents, label),
            lambda off: _locals(evaluator.between(off)[0][:, slots], parents, label))
    return refine


class _Shapes(Deformer):
    """Blend shapes of one mesh: ``points(t) = rest + Σ wₖ(t)·offsetₖ`` with ufbx's effective
    in-between weights ``wₖ`` at every time asked for (``evaluator``; velocities: linear
    between the stack's whole frames and the times between them asked for), or given at
    ``frames`` and linear between them."""

    def __init__(self, rest: np.ndarray, offsets: np.ndarray, frames: np.ndarray,
                 weights: np.ndarray, evaluator: _Evaluator | None = None, mesh: int = 0) -> None:
        self.rest, self.offsets, self.frames, self.weights = rest, offsets, frames, weights
        self.evaluator, self.mesh = evaluator, mesh

    def _keys(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        if self.evaluator is None:
            return self.frames, self.weights
        ev = self.evaluator
        return ev.keys(t, lambda near: self.weights[near],
                       lambda off: ev.between(off)[1][self.mesh].reshape(len(off), -1)
                       if len(off) else np.zeros((0, self.weights.shape[1])))

    def points_at(self, times: npt.ArrayLike) -> np.ndarray:
        t = check_times(times)
        frames, weights = self._keys(t)
        w = np.stack([np.interp(t, frames, weights[:, k]) for k in range(weights.shape[1])], 1)
        return (self.rest[None] + np.einsum("fk,kvc->fvc", w, self.offsets)).astype(np.float32)

    def point_velocities_at(self, times: npt.ArrayLike) -> np.ndarray:
        t = check_times(times)
        frames, weights = self._keys(t)
        rates = segment_rates(frames, lambda k: weights[k], t)
        return np.einsum("fk,kvc->fvc", np.asarray(rates, np.float64), self.offsets)


@dataclass
class _Skin:
    """What one mesh needs of its skeleton: the bind transforms of its nodes, its geometry-to-
    skeleton transform, its influences (as nodes), method and blend weights."""

    binds: dict[int, np.ndarray]
    geom: np.ndarray
    nodes: np.ndarray
    weights: np.ndarray
    method: str
    blend: np.ndarray | None


def _bind_groups(meshes: list[_Skin]) -> list[list[int]]:
    """Meshes grouped so that the bind transforms they need of each node agree (one skeleton per
    group)."""
    groups: list[tuple[list[int], dict[int, np.ndarray]]] = []
    for k, m in enumerate(meshes):
        for members, binds in groups:
            shared = set(binds) & set(m.binds)
            if all(np.allclose(binds[n], m.binds[n], rtol=_BIND_TOLERANCE,
                               atol=_BIND_TOLERANCE * max(1.0, float(np.abs(binds[n]).max())))
                   for n in shared):
                members.append(k)
                binds.update(m.binds)
                break
        else:
            groups.append(([k], dict(m.binds)))
    return [members for members, _ in groups]


def load(path: str | os.PathLike, *, clip: str | int | None = None,
         max_input_gib: float = MAX_INPUT_GIB) -> Scene:
    """Read an FBX character (see the module docstring).

    Parameters
    ----------
    path : str or Path
        A ``.fbx`` file, binary or ASCII.
    clip : str or int, optional
        Animation stack to load (name or index); the first by default.
    max_input_gib : float
        Most GiB the joints' transforms at the frames (or times) evaluated may take.

    Returns
    -------
    dqskin.scene.Scene
        Times are seconds (the stack's whole frames); ``frame_rate`` is the file's.

    Raises
    ------
    dqskin.errors.InputError
        Not a regular file, the file cannot be read (damaged, truncated, not FBX, or ufbx
        failed on it), or its data is invalid (singular transforms, NaN, bad weights): the
        message names the file.
    dqskin.errors.UnknownNameError
        No stack ``clip``.
    dqskin.errors.LimitError
        A stack of more than 1,000,000 frames, or whose joints' transforms at its frames would
        take more than ``max_input_gib``.
    """
    from ..animation import KeyedAnimation
    from ..scene import Mesh, Scene
    from ..skeleton import Skeleton

    p = regular_file(path)  # (ufbx, in its own process, would block on a FIFO)
    meta, arrays = _extract(p, clip, max_input_gib)
    names = _unique(meta["names"], "node")
    node_parent = meta["parents"]
    rest_world = arrays["rest_world"]
    frames = arrays.get("seconds")  # the stack's whole frames, in seconds
    world = arrays.get("world")
    fps = float(meta["fps"])
    evaluator = None
    if frames is not None and world is not None and len(frames):
        shapes = {k: arrays[f"m{k}/shape_weights"].reshape(len(frames), -1)
                  for k in range(len(meta["meshes"])) if f"m{k}/shape_weights" in arrays}
        evaluator = _Evaluator(Path(os.path.abspath(p)), int(meta["stack"]), fps, max_input_gib,
                               frames, world, shapes)
    joint_nodes = list(meta["joints"])
    slot = {n: j for j, n in enumerate(joint_nodes)}
    mesh_names = _unique([m["name"] for m in meta["meshes"]], "mesh")
    built: list[_Skin] = []
    for k, m in enumerate(meta["meshes"]):
        key, name = f"m{k}/", f"{p}: mesh {mesh_names[k]!r}"
        g2w = arrays[key + "geometry_to_world"]
        if m["method"] is None:  # rigid on its node
            geom = g2w
            _inverse(geom, name)
            binds = {m["node"]: rest_world[m["node"]]}
            V = len(arrays[key + "points"])
            infl = (np.full((V, 1), m["node"], np.int64), np.ones((V, 1), np.float32))
            method, blend = "lbs", None
        else:
            if m.get("skins", 1) > 1:
                raise InputError(f"{name}: {m['skins']} skin deformers; dqskin skins a mesh "
                                 "with one")
            geom = g2w if np.all(np.isfinite(g2w)) and abs(np.linalg.det(g2w)) > 1e-300 \
                else np.eye(4)
            bones = arrays[key + "bones"]
            to_bone = arrays[key + "geometry_to_bone"]
            binds = {}
            for c, b in enumerate(bones.tolist()):
                if b >= 0:
                    binds.setdefault(b, geom @ _inverse(to_bone[c], f"{name}: cluster {c}"))
            infl = _influences(arrays[key + "skin_vertices"], arrays[key + "skin_weights"],
                               bones, len(arrays[key + "points"]), name)
            method = _METHODS.get(m["method"], "lbs")
            sv = arrays[key + "skin_vertices"]
            blend = (np.clip(sv[:, 2], 0.0, 1.0).astype(np.float32) if method == "blend"
                     else None)
        built.append(_Skin(binds, geom, infl[0], infl[1], method, blend))
    skeletons: list[Skeleton] = []
    mesh_skeleton: dict[int, int] = {}
    mesh_slots: dict[int, dict[int, int]] = {}
    for members in _bind_groups(built):
        binds = {}
        for k in members:
            binds.update(built[k].binds)
        nodes = set(binds)
        for n in list(nodes):
            a = node_parent[n]
            while a >= 0 and a in slot and a not in nodes:
                nodes.add(a)
                a = node_parent[a]
        order = [n for n in joint_nodes if n in nodes]
        index = {n: j for j, n in enumerate(order)}
        parents = []
        for n in order:
            a = node_parent[n]
            while a >= 0 and a not in index:
                a = node_parent[a]
            parents.append(index.get(a, -1))
        label = f"{p}: skeleton {len(skeletons)}"
        bind = np.stack([binds.get(n, rest_world[n]) for n in order])
        rest = _locals(rest_world[order][None], parents, label)[0]
        anim = None
        if evaluator is not None:
            slots = [slot[n] for n in order]
            anim = KeyedAnimation(evaluator.seconds,
                                  _locals(evaluator.world[:, slots], parents, label),
                                  name=meta["clip"] or "",
                                  refine=_exact_poses(evaluator, slots, parents, label))
        skel = Skeleton([names[n] for n in order], np.asarray(parents, np.int32), bind, rest,
                        name=label.split(": ", 1)[1], animation=anim)
        for k in members:
            mesh_skeleton[k], mesh_slots[k] = len(skeletons), index
        skeletons.append(skel)
    meshes = []
    for k, m in enumerate(meta["meshes"]):
        b = built[k]
        meshes.append(_mesh(Mesh, arrays, k, mesh_names[k], b, mesh_skeleton[k], mesh_slots[k],
                            evaluator, f"{p}: mesh {mesh_names[k]!r}"))
    times = evaluator.seconds if evaluator is not None else np.zeros(1)
    return Scene(str(p), meshes, skeletons, times, time_codes_per_second=1.0, frame_rate=fps,
                 up_axis=_UP.get(int(meta["up"]), "Y"), meters_per_unit=float(meta["unit"]),
                 clips=list(meta["clips"]), clip=meta["clip"])


def _locals(world: np.ndarray, parents: list[int], label: str) -> np.ndarray:
    """(F, J, 4, 4) parent-relative transforms of (F, J, 4, 4) world transforms."""
    local = world.copy()
    for j, pj in enumerate(parents):
        if pj >= 0:
            local[:, j] = _inverse(world[:, pj], f"{label}: joint {j}'s parent") @ world[:, j]
    return local


def _influences(sv: np.ndarray, sw: np.ndarray, bones: np.ndarray, V: int,
                name: str) -> tuple[np.ndarray, np.ndarray]:
    """``(nodes (V, K) int64, weights (V, K) float32)`` of a skin: each vertex's clusters as the
    node they bind (-1 for none, weight 0), the weights divided by their sum (FBX players, ufbx
    and the authoring tools skin with normalized weights)."""
    begin = sv[:, 0].astype(np.int64)
    count = sv[:, 1].astype(np.int64)
    if len(sv) != V or np.any(count < 0) or np.any(begin < 0) or np.any(begin + count > len(sw)):
        raise InputError(f"{name}: skin weights out of range")
    K = max(1, int(count.max(initial=0)))
    slot = np.arange(K)
    take = begin[:, None] + slot[None]
    valid = slot[None] < count[:, None]
    take = np.where(valid, take, 0)
    cluster = sw[take, 0].astype(np.int64) if len(sw) else np.zeros(take.shape, np.int64)
    weight = np.where(valid, sw[take, 1] if len(sw) else 0.0, 0.0)
    if cluster.size and (cluster.min() < 0 or cluster.max() >= len(bones)):
        raise InputError(f"{name}: skin cluster index out of range")
    node = np.where(valid, bones[cluster], -1)
    weight = np.where(node >= 0, weight, 0.0)
    if not np.all(np.isfinite(weight)) or np.any(weight < 0):
        raise InputError(f"{name}: NaN, infinite or negative skin weights")
    total = weight.sum(1, keepdims=True)
    weight = np.divide(weight, total, out=weight, where=total > 0)  # as FBX players
    return node, weight.astype(np.float32)


def _corners(arrays: dict, key: str, what: str, corner: np.ndarray,
             where: str) -> np.ndarray | None:
    """The face-corner values ``what`` ("normals", "uvs") of the kept corners, float32, or None
    when the mesh has none; InputError for indices out of range."""
    if key + what not in arrays:
        return None
    index = arrays[f"{key}{what}_index"].astype(np.int64)
    values = arrays[key + what]
    if index.size != corner.size or (index.size and (index.min() < 0
                                                     or index.max() >= len(values))):
        raise InputError(f"{where}: {what} indices out of range")
    return values[index[corner]].astype(np.float32)


def _mesh(Mesh, arrays, k, name, b, skeleton, index, evaluator, where):
    """The :class:`~dqskin.scene.Mesh` of mesh ``k``; ``index``: node → joint of its
    skeleton."""
    key = f"m{k}/"
    rest = arrays[key + "points"]
    tris, counts, fvi, corner = _polygons(arrays, key, where)
    lut = np.zeros(max([*index, int(b.nodes.max(initial=0))]) + 1, np.int32)
    lut[list(index)] = list(index.values())
    joints = np.where(b.nodes >= 0, lut[np.maximum(b.nodes, 0)], 0)
    normals = _corners(arrays, key, "normals", corner, where)
    deformer = None
    if key + "shape_offsets" in arrays and evaluator is not None and k in evaluator.weights:
        deformer = _Shapes(rest.astype(np.float64), arrays[key + "shape_offsets"],
                           evaluator.seconds, evaluator.weights[k], evaluator, k)
    return Mesh(name=name, points=rest.astype(np.float32), faces=tris,
                joint_indices=joints.astype(np.int32), joint_weights=b.weights,
                skeleton=skeleton, geom_bind_transform=b.geom, skinning_method=b.method,
                normals=normals, normal_vertex=None if normals is None else fvi.astype(np.int32),
                deformer=deformer, face_vertex_counts=counts,
                face_vertex_indices=fvi.astype(np.int32),
                uvs=_corners(arrays, key, "uvs", corner, where), blend_weights=b.blend)
