"""Load UsdSkel skinned prims from ``.usd``/``.usda``/``.usdc``/``.usdz`` into a :class:`Scene`.

UsdSkel resolves the bindings (``UsdSkel.Cache`` over every ``SkelRoot``, instance proxies
included); dqskin does the rest: forward kinematics, skinning and the move to each prim's space
all run on the engine. Conventions at this boundary: USD's row-vector ``Gf`` matrices are
transposed to the column-vector convention, ``primvars:skel:skinningMethod`` maps
``"classicLinear"`` → ``"lbs"`` and ``"dualQuaternion"`` → ``"dqs"``.

What a loaded :class:`~dqskin.scene.Mesh` holds for a skinned ``UsdGeom.PointBased`` prim:

- ``points``: rest points (the default value, else the earliest time sample), prim space.
- ``faces``: polygons fan-triangulated (holes dropped, ``leftHanded`` winding flipped so every
  triangle is counter-clockwise); the original ``faceVertexCounts``/``faceVertexIndices`` are
  kept. Curves and points have no faces.
- ``joint_indices``/``joint_weights``: ``(V, K)`` with ``K = elementSize``, indices remapped from
  the prim's ``skel:joints`` order to its skeleton's order, constant (rigid) influences repeated
  on every point; weights as authored (UsdSkel never renormalizes).
- ``normals``: ``primvars:normals`` or ``normals``, vertex/varying (one per point) or
  faceVarying (``normal_vertex`` = ``faceVertexIndices``); constant/uniform normals are not
  skinned (None).
- ``output_transforms``: skeleton space → prim space, ``inverse(gprimLocalToWorld) @
  skelLocalToWorld`` (what ``UsdSkel.BakeSkinning`` applies) as a
  :class:`~dqskin.animation.TransformTrack` keyed at every time sample of the transforms above
  the two prims (exact there; between samples interpolated as joints are, which is USD's own
  interpolation for translate, orient and scale ops); None when identity.
- ``world_transforms``: skeleton space → world (stage units, no ``metersPerUnit`` scaling):
  ``skelLocalToWorld``, evaluated as ``output_transforms`` are, one track per skeleton; so
  ``gprimLocalToWorld`` applied to ``UsdSkel.BakeSkinning``'s points is what
  ``Scene.skin(space="world")`` returns. None when the prim's local-to-world is the identity at
  every time (world is then its own space).
- ``deformer``: blend shapes (offsets, normalOffsets, pointIndices, inbetweens) driven by the
  skeleton's ``SkelAnimation.blendShapeWeights``, and time-sampled rest points, with their
  analytic time derivative; None when there are neither.

Skinned prims that are not point-based (``Sphere``, ``Cube``, …, bound with constant
influences) have no points for a :class:`Scene`; :func:`load_rigid_prims` returns them (this module
reads, it never skins) and :func:`dqskin.pipeline.rigid_transforms` computes their per-time local
transform with the engine, as ``UsdSkel.BakeSkinning`` bakes them into ``xformOp:transform``.
"""

import contextlib
import io
import os
import re
import sys
import tempfile
import threading
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass
from typing import Any, NoReturn

import numpy as np
import numpy.typing as npt
from pxr import Sdf, Tf, Usd, UsdGeom, UsdSkel, Vt

from ..animation import Animation, Deformer, TransformTrack, segment_rates
from ..errors import InputError, LimitError, Param
from ..files.inputs import regular_file
from ..scene import Mesh, Scene
from ..skeleton import Skeleton
from ..topology import fan_corners
from . import LOADER_SUFFIXES
from .usd_anim import JointTracks
from .usd_layers import open_stage as _open_checked
from .usd_xform import LocalToWorld, XformChain

__all__ = ["BLEND_WEIGHTS", "SKINNING_METHODS", "SUFFIXES", "load", "RigidPrim",
           "UsdSkelAnimation", "load_rigid_prims", "load_usd", "open_stage"]

SUFFIXES = LOADER_SUFFIXES["usd"]
"""File extensions :func:`load_usd` (and :func:`load`) reads."""

SKINNING_METHODS = {"classicLinear": "lbs", "dualQuaternion": "dqs"}
"""``primvars:skel:skinningMethod`` tokens → dqskin method names."""

BLEND_WEIGHTS = "dqskin:blendWeights"
"""Primvar (``primvars:dqskin:blendWeights``, float per vertex in [0, 1], or one constant) of the
DQS fraction of each vertex: where authored, the prim's method is "blend" with these weights
(UsdSkel players ignore it and skin with ``primvars:skel:skinningMethod``)."""


def _tf_message(exc: BaseException) -> str:
    """The first diagnostic text of a ``Tf.ErrorException``, on one line."""
    for block in re.split(r"\n\s*Error in ", str(exc)):
        if " : '" in block:
            text = block.split(" : '", 1)[1].rstrip().rstrip("'")
            return " ".join(text.split())
    return " ".join(str(exc).split())


_TRAP = getattr(Tf, "DiagnosticTrap", None)
"""``Tf.DiagnosticTrap`` where this USD has it (else file descriptor 2 is set aside while USD
runs)."""

MAX_FRAMES = 10_000_000
"""Most time codes a stage's ``startTimeCode..endTimeCode`` may span."""

ANIMATION_ARRAYS = {"translations": "joints", "rotations": "joints", "scales": "joints",
                    "blendShapeWeights": "blendShapes"}
"""``SkelAnimation`` array attributes → the token attribute whose length they must have."""


class _SharedRedirect:
    """A process-wide redirection of stderr shared by every thread inside it: the first to enter
    sets it up, the last to leave undoes it (so overlapping uses from threads never leave stderr
    redirected).

    Parameters
    ----------
    setup : callable
        Sets the redirection up; returns ``(read, undo)``: ``read(start)`` gives the text written
        since offset ``start`` and ``read()`` the current offset; ``undo()`` restores.
    """

    def __init__(self, setup: Callable[[], tuple[Callable[..., Any], Callable[[], None]]]) -> None:
        self._setup = setup
        self._lock = threading.Lock()
        self._depth = 0
        self._state: tuple[Callable[..., Any], Callable[[], None]] | None = None

    @contextlib.contextmanager
    def __call__(self) -> Iterator[Callable[..., Any]]:
        with self._lock:
            if self._depth == 0:
                self._state = self._setup()
            assert self._state is not None  # set up by the first to enter
            self._depth += 1
            read = self._state[0]
        try:
            yield read
        finally:
            with self._lock:
                self._depth -= 1
                if self._depth == 0 and self._state is not None:
                    self._state[1]()
                    self._state = None


def _python_stderr_to_buffer():
    """``sys.stderr`` → a buffer (pxr's Python bindings print some conversion failures there)."""
    saved, buffer = sys.stderr, io.StringIO()
    sys.stderr = buffer

    def read(start=None):
        text = buffer.getvalue()
        return len(text) if start is None else text[start:]

    def undo():
        sys.stderr = saved

    return read, undo


def _fd_stderr_to_file():
    """File descriptor 2 → a temporary file (what USD's C++ prints there)."""
    nothing = (lambda start=None: 0 if start is None else ""), (lambda: None)
    try:
        sys.stderr.flush()
        saved = os.dup(2)
    except (AttributeError, OSError, ValueError):  # no usable stderr: nothing to keep quiet
        return nothing
    try:
        tmp = tempfile.TemporaryFile()
        os.dup2(tmp.fileno(), 2)
    except OSError:
        os.close(saved)
        return nothing

    def read(start=None):
        size = os.fstat(tmp.fileno()).st_size
        if start is None:
            return size
        return os.pread(tmp.fileno(), max(0, size - start), start).decode(errors="replace")

    def undo():
        os.dup2(saved, 2)
        os.close(saved)
        tmp.close()

    return read, undo


_PYTHON_STDERR = _SharedRedirect(_python_stderr_to_buffer)
_FD_STDERR = _SharedRedirect(_fd_stderr_to_file)


@contextlib.contextmanager
def _usd_diagnostics(process_stderr: bool = False) -> Iterator[Callable[[], list[str]]]:
    """Keep USD's diagnostics off the terminal.

    Inside, USD's C++ diagnostics (Tf warnings, status messages) on this thread are trapped
    (``Tf.DiagnosticTrap``) and dropped at the end. With ``process_stderr``, for the synchronous
    loading, the process's stderr is set aside too, file descriptor 2 and ``sys.stderr`` (the
    redirection is process-wide, shared by overlapping users): that catches what the trap cannot,
    Tf diagnostics of USD's worker threads, what USD's lowest layer prints with ``fprintf`` (e.g.
    ``failed call to posix_madvise`` on a corrupt crate file) and what pxr's Python bindings print
    to ``sys.stderr``. With an older USD without the trap, file descriptor 2 is always set aside.
    USD's errors still raise (``Tf.ErrorException``).

    Yields
    ------
    callable
        Returns the texts of the warnings caught so far inside this context, one line each, for
        the ValueErrors that the ones that matter become.
    """
    with contextlib.ExitStack() as stack:
        if process_stderr or _TRAP is None:
            read = stack.enter_context(_FD_STDERR())
        if process_stderr:
            stack.enter_context(_PYTHON_STDERR())
        if _TRAP is None:
            start = read()
            yield lambda: [ln.split(" -- ", 1)[-1] for ln in read(start).splitlines()
                           if ln.startswith("Warning")]
            return
        trap = stack.enter_context(_TRAP())
        try:
            yield lambda: [" ".join(w.commentary.split()) for w in trap.GetWarnings()]
        finally:
            trap.Clear()  # dropped, not reposted to the terminal


def _one_line(exc: BaseException) -> str:
    """An exception's message on one line."""
    return " ".join(str(exc).split())


_USD_NAMES = {"joint_names": "joints", "bind_transforms": "bindTransforms",
              "rest_transforms": "restTransforms", "world_transform": "local-to-world transform"}
"""Skeleton argument names → what they are called in a USD file (for messages)."""


def _usd_names(key: str, message: str) -> str:
    """A :class:`Skeleton` message about prim ``key`` with USD's names for its fields."""
    for ours, usd in _USD_NAMES.items():
        message = message.replace(f"{key}: {ours}", f"{key}: {usd}", 1)
    return message


def _first(texts: Sequence[str]) -> str:
    """`` (USD: first text)`` to append to a message, or "" when there is none."""
    return f" (USD: {texts[0]})" if texts else ""


def _at_time(time: float | None) -> str:
    """`` at time 2`` for a time sample, "" for the default value (None)."""
    return "" if time is None else f" at time {time:g}"


def _authored_values(attr):
    """``(time, value)`` of every time sample of ``attr``, else ``[(None, default)]``; empty
    when nothing is authored (time samples win over the default at every numeric time)."""
    if not attr or not attr.HasAuthoredValue():
        return []
    samples = attr.GetTimeSamples()
    if samples:
        query = Usd.AttributeQuery(attr)  # value resolution once, not per sample
        return [(float(t), query.Get(t)) for t in samples]
    return [(None, attr.Get(Usd.TimeCode.Default()))]


def _duplicates(names: Sequence[str]) -> list[str]:
    """The names that occur more than once, in first-seen order."""
    seen, dups = set(), []
    for n in names:
        if n in seen and n not in dups:
            dups.append(n)
        seen.add(n)
    return dups


def _missing_primvar(prim, name, pv):
    """Why the skinning query's ``primvars:skel:<name>`` of ``prim`` has no usable value."""
    full = f"primvars:skel:{name}"
    if pv:
        return (f"{full} has only time samples (joint influences are read at the default time, "
                "so they need a default value)")
    attr = prim.GetAttribute(full)
    if not attr or not attr.IsAuthored():
        return f"{full} is missing (a skinned prim needs jointIndices and jointWeights)"
    if not attr.HasAuthoredValue():
        return f"{full} is authored without a value"
    return f"{full} is not usable as a joint influence primvar (type {attr.GetTypeName()})"


def _matrices(gf_matrices: object) -> np.ndarray:
    """Row-vector ``Gf.Matrix4d`` array → ``(N, 4, 4)`` float64, column-vector convention."""
    return np.array(gf_matrices, dtype=np.float64).reshape(-1, 4, 4).transpose(0, 2, 1)


def _rest_value(attr):
    """The value USD resolves before any animation: the earliest time sample when there are
    samples (they win over the default at every time), else the default (None if unauthored)."""
    if not attr or not attr.HasAuthoredValue():
        return None
    if attr.GetNumTimeSamples() > 0:
        return attr.Get(Usd.TimeCode.EarliestTime())
    return attr.Get(Usd.TimeCode.Default())


class UsdSkelAnimation(Animation):
    """Joint transforms (and blend-shape weights) of one skeleton, sampled as UsdSkel does.

    ``UsdSkel.SkeletonQuery.ComputeJointLocalTransforms`` samples the ``SkelAnimation``
    (translations, rotations, scales; interpolated between time samples as USD does) and maps the
    animation's joint order onto the skeleton's, giving undriven joints their rest transform.
    The loader gives most animations a :class:`~.usd_anim.JointTracks` of their checked samples
    (``_tracks``), which does the same for all the times of a call at once in NumPy; the others
    (and NaN times) are sampled through UsdSkel, time by time.

    Parameters
    ----------
    skel_query : UsdSkel.SkeletonQuery
        A valid query whose skeleton has an animation source.
    stage : Usd.Stage
        Kept alive as long as the animation is.
    path : str, optional
        The file, for messages (default: the stage's root layer).

    Attributes
    ----------
    key_times : (K,) float64
        Time codes of the joint-transform and blend-shape-weight samples.
    name : str
        The ``SkelAnimation`` prim path.
    path : str
        The file (the stage's root layer).
    blend_shape_names : list of str
        The animation's ``blendShapes`` tokens (order of :meth:`blend_shape_weights`).
    """

    def __init__(self, skel_query: UsdSkel.SkeletonQuery, stage: Usd.Stage,
                 path: str | os.PathLike | None = None) -> None:
        self._stage = stage
        self._query = skel_query
        # the loader's JointTracks, when it can sample as UsdSkel does
        self._tracks: JointTracks | None = None
        self._anim = skel_query.GetAnimQuery()
        layer = stage.GetRootLayer()
        self.path = os.fspath(path) if path is not None else (layer.realPath or layer.identifier)
        self.name = str(self._anim.GetPrim().GetPath())
        self.joint_count = len(skel_query.GetJointOrder())
        self.blend_shape_names = [str(n) for n in self._anim.GetBlendShapeOrder()]
        keys = set(self._anim.GetJointTransformTimeSamples())
        keys.update(self._anim.GetBlendShapeWeightTimeSamples())
        self.key_times = np.array(sorted(keys), dtype=np.float64)

    def _fail(self, what: str) -> NoReturn:
        raise InputError(f"{self.path}: {self.name}: {what}")

    def local_transforms(self, times: npt.ArrayLike) -> np.ndarray:
        """Parent-relative joint transforms, skeleton joint order.

        Parameters
        ----------
        times : (F,) float
            USD time codes.

        Returns
        -------
        (F, J, 4, 4) float64, column-vector convention.

        Raises
        ------
        ValueError
            UsdSkel cannot compose the animation at a time (it would warn and fall back to the
            rest pose); the message names the file, the ``SkelAnimation`` and the time.
        """
        t = np.atleast_1d(np.asarray(times, dtype=np.float64))
        if self._tracks is not None and not np.isnan(t).any():  # USD: NaN is Default
            return self._tracks.local_transforms(t)
        return self._usdskel_local_transforms(t)

    def _usdskel_local_transforms(self, t: np.ndarray) -> np.ndarray:
        """:meth:`local_transforms` asking UsdSkel at each time."""
        J = self.joint_count
        rows = np.empty((t.shape[0], J, 4, 4))  # USD's row-vector matrices, one copy each
        compute = self._query.ComputeJointLocalTransforms
        with _usd_diagnostics() as warnings:
            for i, ti in enumerate(t.tolist()):
                xf = compute(Usd.TimeCode(ti))
                if xf is None or len(xf) != J:
                    trapped = warnings()  # from this time or an earlier one
                    self._fail(self._warned_at(t[:i + 1], trapped) if trapped else
                               f"cannot compute joint transforms at time {ti:g}")
                rows[i] = xf
            # warnings are checked once per call, not per frame (that doubled the sampling)
            trapped = warnings()
        if trapped:
            self._fail(self._warned_at(t, trapped))
        return np.ascontiguousarray(rows.transpose(0, 1, 3, 2))

    def _warned_at(self, t: np.ndarray, trapped: Sequence[str]) -> str:
        """Why sampling at ``t`` posted USD warnings (UsdSkel falls back to the rest pose): the
        first time that warns again, sampled one by one."""
        with _usd_diagnostics() as warnings:
            for ti in t.tolist():
                self._query.ComputeJointLocalTransforms(Usd.TimeCode(ti))
                if warnings():
                    return f"cannot compute joint transforms at time {ti:g}{_first(warnings())}"
        return (f"cannot compute joint transforms at a time from {t[0]:g} to {t[-1]:g}"
                f"{_first(trapped)}")

    def blend_shape_weight_rates(self, times: npt.ArrayLike) -> np.ndarray:
        """``(F, S)`` float64 time derivatives of :meth:`blend_shape_weights` (USD interpolates
        the weights linearly between time samples)."""
        attr = UsdSkel.Animation(self._anim.GetPrim()).GetBlendShapeWeightsAttr()
        keys = np.asarray(attr.GetTimeSamples() if attr else [], dtype=np.float64)
        S = len(self.blend_shape_names)
        if keys.size < 2 or S == 0:
            return np.zeros((np.atleast_1d(times).shape[0], S))
        return np.stack(segment_rates(keys, lambda k: self.blend_shape_weights([keys[k]])[0],
                                      times))

    def blend_shape_weights(self, times: npt.ArrayLike) -> np.ndarray:
        """``(F, S)`` float32 weights of :attr:`blend_shape_names` at ``times`` (0 when unset).

        Raises
        ------
        ValueError
            ``blendShapeWeights`` does not have one weight per ``blendShapes`` token.
        """
        t = np.atleast_1d(np.asarray(times, dtype=np.float64))
        out = np.zeros((t.shape[0], len(self.blend_shape_names)), dtype=np.float32)
        with _usd_diagnostics():
            for i, ti in enumerate(t):
                w = self._anim.ComputeBlendShapeWeights(Usd.TimeCode(float(ti)))
                if w is None or len(w) == 0:
                    continue
                if len(w) != out.shape[1]:
                    self._fail(f"blendShapeWeights has {len(w)} weights for {out.shape[1]} "
                               f"blendShapes at time {ti:g}")
                out[i] = np.asarray(w, dtype=np.float32)
        return out


@dataclass
class RigidPrim:
    """A skinned prim without points, which UsdSkel moves rigidly (constant influences).

    Attributes
    ----------
    name : str
        Prim path.
    skeleton : int
        Index into ``scene.skeletons``.
    joint_indices, joint_weights : (K,) int32, float32
        The prim's influences, skeleton joint order.
    geom_bind_transform : (4, 4) float64
        Prim (geometry) space → skeleton bind space, column-vector convention.
    skinning_method : {"lbs", "dqs"}
    parent_transforms : dqskin.animation.TransformTrack or None
        Skeleton space → the parent prim's space; identity when None.
    """

    name: str
    skeleton: int
    joint_indices: np.ndarray
    joint_weights: np.ndarray
    geom_bind_transform: np.ndarray
    skinning_method: str
    parent_transforms: TransformTrack | None = None


class _Loader:
    """One file's loading state; every error names the file and the prim.

    :meth:`load` runs with USD's diagnostics trapped (:func:`_usd_diagnostics`): nothing USD says
    reaches the terminal; what matters becomes a ValueError.
    """

    def __init__(self, path: str | os.PathLike) -> None:
        self.path = os.fspath(path)
        self._stage: Usd.Stage | None = None
        # texts of the USD warnings trapped so far (set by load)
        self.warnings: Callable[[], list[str]] = lambda: []
        self.skeleton_index: dict[str, int] = {}  # skeleton prim path -> index into skeletons
        self.skeletons: list[Skeleton] = []
        self.animations: list[UsdSkelAnimation | None] = []
        self.meshes: list[Mesh] = []
        self.rigid: list[RigidPrim] = []
        self.spaces = LocalToWorld()  # every prim's xform ops, read once
        # skeleton prim path -> its local-to-world XformChain
        self.world_tracks: dict[str, XformChain] = {}

    @property
    def stage(self) -> Usd.Stage:
        """The stage :meth:`load` opened."""
        assert self._stage is not None, "load() opens the stage"
        return self._stage

    def fail(self, where: str, what: str) -> NoReturn:
        raise InputError(f"{self.path}: {where}: {what}")

    @contextlib.contextmanager
    def at(self, where: str) -> Iterator[None]:
        """Make every exception inside a ValueError naming the file and ``where``: USD's
        (``Tf.ErrorException``, ``RuntimeError``) and NumPy's on malformed values; ours already
        name the file."""
        try:
            yield
        except ValueError as exc:
            if str(exc).startswith(self.path):
                raise
            raise InputError(f"{self.path}: {where}: {_one_line(exc)}") from None
        except RuntimeError as exc:  # Tf.ErrorException and pxr's Python-side errors
            raise InputError(f"{self.path}: {where}: USD error: {_tf_message(exc)}") from None

    def _open(self) -> Usd.Stage:
        regular_file(self.path)
        ext = os.path.splitext(self.path)[1].lower()
        if ext not in SUFFIXES:
            raise InputError(f"{self.path}: not a USD file (extension {ext!r}, expected one of "
                             f"{', '.join(SUFFIXES)})")
        try:
            stage = _open_checked(self.path, Usd.Stage.LoadAll)  # (no layer that is not a file)
        except Tf.ErrorException as exc:
            raise InputError(f"{self.path}: cannot open as USD: {_tf_message(exc)}") from None
        if stage is None:
            raise InputError(f"{self.path}: cannot open as USD{_first(self.warnings())}")
        return stage

    def value(self, where, attr, vt_type, type_name):
        """The default value of ``attr`` (None when it has none); ValueError naming ``where``
        and the attribute unless it is a ``vt_type`` (USD reports the schema's type for a schema
        attribute, whatever was authored, so the value is what is checked)."""
        if not attr or not attr.HasAuthoredValue():
            return None
        value = attr.Get(Usd.TimeCode.Default())
        if value is not None and not isinstance(value, vt_type):
            self.fail(where, f"{attr.GetName()} has a value of type {type(value).__name__}, "
                             f"expected {type_name}")
        return value

    def tokens(self, where, attr):
        """A ``token[]`` attribute's default value as a list of str ([] when unauthored)."""
        value = self.value(where, attr, Vt.TokenArray, "token[]")
        return [] if value is None else [str(t) for t in value]

    # -- skeletons -------------------------------------------------------------------------

    def skeleton(self, cache, skel):
        """Index of ``skel`` (a UsdSkel.Skeleton) in the scene, loading it the first time."""
        key = str(skel.GetPrim().GetPath())
        if key not in self.skeleton_index:
            with self.at(key):
                skeleton, animation = self.load_skeleton(cache, skel, key)
            self.skeleton_index[key] = len(self.skeletons)
            self.skeletons.append(skeleton)
            self.animations.append(animation)
        return self.skeleton_index[key]

    def load_skeleton(self, cache, skel, key):
        """``(Skeleton, UsdSkelAnimation or None)`` of one Skeleton prim."""
        joints = self.joints(key, skel)
        query = cache.GetSkelQuery(skel)
        if not query:
            self.fail(key, "UsdSkel cannot build a skeleton query (check joints, bindTransforms "
                           f"and restTransforms sizes){_first(self.warnings())}")
        bind, rest = self.bind_and_rest(key, skel, query, len(joints))
        world = _matrices(UsdGeom.Imageable(skel.GetPrim())
                          .ComputeLocalToWorldTransform(Usd.TimeCode.Default()))[0]
        try:
            skeleton = Skeleton(joints, np.asarray(query.GetTopology().GetParentIndices()), bind,
                                rest, name=key, world_transform=world)
        except ValueError as exc:
            raise InputError(f"{self.path}: {_usd_names(key, str(exc))}") from None
        animation = self.animation(query, rest)  # after the skeleton's own checks
        return skeleton.with_animation(animation), animation

    def joints(self, key, skel):
        """The Skeleton's ``joints``: at least one, unique, a valid topology."""
        joints = self.tokens(key, skel.GetJointsAttr())
        if not joints:
            self.fail(key, "joints is empty or missing (a Skeleton needs at least one joint)")
        dups = _duplicates(joints)
        if dups:
            self.fail(key, f"joints has duplicate joint name{'s' if len(dups) > 1 else ''} "
                           f"{', '.join(map(repr, dups))}")
        ok, reason = UsdSkel.Topology(joints).Validate()
        if not ok:
            self.fail(key, f"invalid joint topology: {reason}")
        return joints

    def bind_and_rest(self, key, skel, query, J):
        """``(J, 4, 4)`` bind transforms and rest transforms (None: derived from the bind)."""
        M4 = (Vt.Matrix4dArray, "matrix4d[]")
        bind = self.value(key, skel.GetBindTransformsAttr(), *M4)
        if bind is None or len(bind) != J:
            self.fail(key, f"bindTransforms has {0 if bind is None else len(bind)} matrices for "
                           f"{J} joints")
        authored_rest = self.value(key, skel.GetRestTransformsAttr(), *M4)
        if authored_rest is not None and len(authored_rest) != J:
            self.fail(key, f"restTransforms has {len(authored_rest)} matrices for {J} joints")
        rest = query.ComputeJointLocalTransforms(Usd.TimeCode.Default(), True)
        return _matrices(bind), (_matrices(rest) if rest is not None and len(rest) == J else None)

    # -- animations ------------------------------------------------------------------------

    def animation(self, query, rest=None):
        """The skeleton's :class:`UsdSkelAnimation`, or None without one. Its arrays are checked
        at every time sample, then UsdSkel composes the first key time, to see that it can (it
        warns and falls back to the rest pose when, say, a sparse animation meets a skeleton
        without restTransforms). ``rest``: the skeleton's (J, 4, 4) local rest transforms
        (:meth:`bind_and_rest`'s; None when it has none), for the joints it does not drive."""
        if not query.GetAnimQuery():
            return None
        prim = query.GetAnimQuery().GetPrim()
        where = str(prim.GetPath())
        with self.at(where):
            names = {key: self.tokens(where, prim.GetAttribute(key))
                     for key in ("joints", "blendShapes")}
            for key, tokens in names.items():
                dups = _duplicates(tokens)
                if dups:
                    self.fail(where, f"{key} has duplicate names {', '.join(map(repr, dups))}")
            arrays = {attr: self.check_animation_array(
                          where, attr, _authored_values(prim.GetAttribute(attr)), names[key], key)
                      for attr, key in ANIMATION_ARRAYS.items()}
            anim = UsdSkelAnimation(query, self.stage, self.path)
            first = anim.key_times[:1] if anim.key_times.size else np.zeros(1)
            composed = anim.local_transforms(first)
            anim._tracks = self.joint_tracks(query, prim, arrays, first, composed, rest)
        return anim

    def joint_tracks(self, query: UsdSkel.SkeletonQuery, prim: Usd.Prim,
                     arrays: dict[str, tuple[np.ndarray | None, np.ndarray] | None],
                     first: np.ndarray, composed: np.ndarray,
                     rest: np.ndarray | None = None) -> JointTracks | None:
        """The :class:`~.usd_anim.JointTracks` of the animation ``prim`` from its checked
        ``arrays`` (:meth:`check_animation_array`'s), or None where it might not sample as
        UsdSkel does: an array unauthored, blocked or of another layout, values from value
        clips, held interpolation, a sparse animation without rest transforms, or a result
        that differs from UsdSkel's ``composed`` at time ``first``; or an array not of its
        schema type (``float3[]``, ``quatf[]``, ``half3[]``: UsdSkel then gives the rest pose)."""
        kinds = {"translations": (Sdf.ValueTypeNames.Float3Array, "f", 3),
                 "rotations": (Sdf.ValueTypeNames.QuatfArray, "f", 4),
                 "scales": (Sdf.ValueTypeNames.Half3Array, "e", 3)}
        if self.stage.GetInterpolationType() != Usd.InterpolationTypeLinear:
            return None
        sources = (Usd.ResolveInfoSourceTimeSamples, Usd.ResolveInfoSourceDefault)
        checked = {}
        for a, (type_name, char, width) in kinds.items():
            attr = prim.GetAttribute(a)
            array = arrays.get(a)
            if (array is None or attr.GetTypeName() != type_name  # UsdSkel: rest pose
                    or array[1].dtype.char != char or array[1].shape[2:] != (width,)
                    or attr.GetResolveInfo().GetSource() not in sources):
                return None
            checked[a] = array
        skel_joints = {str(j): i for i, j in enumerate(query.GetJointOrder())}
        joints = [skel_joints.get(str(j), -1) for j in query.GetAnimQuery().GetJointOrder()]
        if rest is None:  # (J, 4, 4) from bind_and_rest, None when UsdSkel has none
            if sorted(joints) != list(range(len(skel_joints))):
                return None
            rest = np.zeros((len(skel_joints), 4, 4))  # every joint driven: rest unused
        try:
            tracks = JointTracks(checked["translations"], checked["rotations"], checked["scales"],
                                 joints, rest)
            same = np.array_equal(tracks.local_transforms(first), composed)
        except (TypeError, ValueError):
            return None
        return tracks if same else None

    def check_animation_array(self, where, attr, samples, names, key):
        """Every ``(time, value)`` of a ``SkelAnimation`` array (its default value, or each time
        sample): one finite entry per name of ``key`` (``joints`` or ``blendShapes``), no zero
        rotation. Checked all at once: an animation may have thousands of samples (their
        buffers joined in one call when they all hold one entry per name in one layout; one by
        one, to name the bad one, when not). Returns ``(times, values)`` (times None for a
        default value; values ``(K, names, components)`` in the attribute's own scalar type)
        when every sample is an array of that one layout, else None."""
        times = [time for time, value in samples if value is not None]
        values: np.ndarray | None = None
        native: np.ndarray | None = None
        if times and names:
            arrays = [v for _, v in samples if v is not None]
            kind = type(arrays[0])
            try:
                if all(type(v) is kind and len(v) == len(names) for v in arrays):
                    first = memoryview(arrays[0])
                    raw = b"".join(arrays)  # (a Vt array type has one layout)
                    if first.shape and first.shape[0] == len(names) and \
                            len(raw) == len(arrays) * first.nbytes:
                        native = np.frombuffer(raw, np.dtype(first.format)).reshape(
                            (len(arrays),) + first.shape)
                        values = native.astype(np.float64)
            except (TypeError, ValueError):
                values = native = None
        if values is None:
            values = self._animation_arrays(where, attr, samples, names, key)
            if values is None:
                return None
        values = values.reshape(len(times), len(names), -1)  # (samples, names, components)
        finite = np.isfinite(values).all(axis=2)
        ok = finite & np.any(values != 0, axis=2) if attr == "rotations" else finite
        if not ok.all():
            s, n = (int(i) for i in np.argwhere(~ok)[0])
            what = "NaN or infinite values" if not finite[s, n] else "a zero quaternion"
            self.fail(where, f"{attr} has {what} for {key[:-1]} {names[n]!r}{_at_time(times[s])}")
        if native is None or len(times) != len(samples):  # another layout, or blocked samples
            return None
        return (None if times[0] is None else np.asarray(times, np.float64)), native

    def _animation_arrays(self, where, attr, samples, names, key):
        """:meth:`check_animation_array`'s values one sample at a time, failing on the first
        that is not one array of numbers per name; None when there is nothing to check."""
        arrays = []
        for time, value in samples:
            if value is None:  # a blocked time sample
                continue
            try:
                a = np.asarray(value, dtype=np.float64)
            except (TypeError, ValueError):
                self.fail(where, f"{attr}{_at_time(time)} is not an array of numbers")
            if a.ndim == 0 or a.shape[0] != len(names):
                self.fail(where, f"{attr} has {a.shape[0] if a.ndim else 'no array of'} values "
                                 f"for {len(names)} {key}{_at_time(time)}")
            arrays.append(a.reshape(len(names), -1))
        if not arrays or not names:
            return None
        return np.stack(arrays)

    # -- skinned prims ---------------------------------------------------------------------

    def check_influences(self, where, q):
        """Check jointIndices/jointWeights have values and agree in interpolation, element size
        and count."""
        ipv, wpv = self.influence_primvars(where, q)
        interp = (ipv.GetInterpolation(), wpv.GetInterpolation())
        if interp[0] != interp[1]:
            self.fail(where, f"jointIndices interpolation {interp[0]!r} != jointWeights "
                             f"interpolation {interp[1]!r}")
        if interp[0] not in ("constant", "vertex"):
            self.fail(where, f"joint influence interpolation {interp[0]!r}: must be 'constant' "
                             "or 'vertex'")
        size = (ipv.GetElementSize(), wpv.GetElementSize())
        if size[0] != size[1]:
            self.fail(where, f"jointIndices elementSize {size[0]} != jointWeights elementSize "
                             f"{size[1]}")
        if size[0] < 1:
            self.fail(where, f"joint influence elementSize {size[0]}: must be positive")
        idx_raw, wts_raw = ipv.Get(Usd.TimeCode.Default()), wpv.Get(Usd.TimeCode.Default())
        n_idx = 0 if idx_raw is None else len(idx_raw)
        n_wts = 0 if wts_raw is None else len(wts_raw)
        if n_idx != n_wts:
            self.fail(where, f"{n_idx} jointIndices but {n_wts} jointWeights")
        if interp[0] == "constant" and n_idx != size[0]:
            self.fail(where, f"{n_idx} constant joint influences for elementSize {size[0]}")
        if n_idx % size[0]:
            self.fail(where, f"{n_idx} joint influences is not a multiple of elementSize "
                             f"{size[0]}")

    def influence_primvars(self, where, q):
        """The skinning query's ``jointIndices`` and ``jointWeights`` primvars, which must both
        have a default value (UsdSkel leaves a primvar without one invalid)."""
        out = []
        for name, pv in (("jointIndices", q.GetJointIndicesPrimvar()),
                         ("jointWeights", q.GetJointWeightsPrimvar())):
            if not pv or pv.Get(Usd.TimeCode.Default()) is None:
                self.fail(where, _missing_primvar(q.GetPrim(), name, pv))
            out.append(pv)
        return out

    def influences(self, where, q, point_count, skeleton):
        """``(V, K)`` int32 joint indices in skeleton order and float32 weights."""
        ipv = q.GetJointIndicesPrimvar()
        interp, K = ipv.GetInterpolation(), ipv.GetElementSize()
        n_idx = len(ipv.Get(Usd.TimeCode.Default()) or [])
        rigid = interp == "constant"
        expect = K if rigid else K * point_count
        if n_idx != expect:
            self.fail(where, f"{n_idx} joint influences, expected {expect} ({interp} "
                             f"interpolation, elementSize {K}, {point_count} points)")
        result = q.ComputeJointInfluences(Usd.TimeCode.Default())
        if not result:
            self.fail(where, "UsdSkel cannot compute the joint influences")
        idx = np.asarray(result[0], dtype=np.int64).reshape(-1, K)
        wts = np.asarray(result[1], dtype=np.float32).reshape(-1, K)
        if not np.all(np.isfinite(wts)):
            self.fail(where, "jointWeights has NaN or infinite weights")
        if wts.size and wts.min() < 0:
            self.fail(where, f"jointWeights has a negative weight {float(wts.min())}")
        skel = self.skeletons[skeleton]
        local_order = q.GetJointOrder()
        if local_order is not None:
            names = [str(n) for n in local_order]
            index = {n: i for i, n in enumerate(skel.joint_names)}
            missing = [n for n in names if n not in index]
            if missing:
                self.fail(where, f"skel:joints names {missing[0]!r}, not a joint of "
                                 f"{skel.name}")
            to_skel = np.array([index[n] for n in names], dtype=np.int64)
            limit, what = len(names), "skel:joints"
        else:
            to_skel, limit, what = None, skel.joint_count, f"skeleton {skel.name}"
        if idx.size and (idx.min() < 0 or idx.max() >= limit):
            bad = int(idx.min()) if idx.min() < 0 else int(idx.max())
            self.fail(where, f"joint index {bad} out of range for the {limit} joints of {what}")
        if to_skel is not None:
            idx = to_skel[idx]
        if rigid:
            idx = np.repeat(idx, point_count, axis=0)
            wts = np.repeat(wts, point_count, axis=0)
        return idx.astype(np.int32), wts

    def faces(self, where, mesh, point_count):
        """Fan triangles, and the original counts and indices (None for non-meshes)."""
        if not mesh:
            return np.zeros((0, 3), np.int32), None, None
        counts = _rest_value(mesh.GetFaceVertexCountsAttr())
        indices = _rest_value(mesh.GetFaceVertexIndicesAttr())
        counts = np.zeros(0, np.int64) if counts is None else np.asarray(counts, np.int64)
        indices = np.zeros(0, np.int64) if indices is None else np.asarray(indices, np.int64)
        if counts.size and counts.min() < 0:
            self.fail(where, "faceVertexCounts has a negative count")
        if counts.sum() != indices.size:
            self.fail(where, f"faceVertexCounts sum to {int(counts.sum())} but there are "
                             f"{indices.size} faceVertexIndices")
        if indices.size and (indices.min() < 0 or indices.max() >= point_count):
            bad = int(indices.min()) if indices.min() < 0 else int(indices.max())
            self.fail(where, f"faceVertexIndices has index {bad} out of range for "
                             f"{point_count} points")
        keep = counts >= 3
        holes = _rest_value(mesh.GetHoleIndicesAttr())
        if holes is not None and len(holes):
            h = np.asarray(holes, np.int64)
            keep[h[(h >= 0) & (h < counts.size)]] = False
        tris = indices[fan_corners(counts, keep)]
        if mesh.GetOrientationAttr().Get() == UsdGeom.Tokens.leftHanded:
            tris = tris[:, ::-1]
        return (np.ascontiguousarray(tris, dtype=np.int32), counts.astype(np.int32),
                indices.astype(np.int32))

    def normals(self, where, prim, point_count, face_vertex_indices):
        """Rest normals and their vertex map, or (None, None)."""
        pv = UsdGeom.PrimvarsAPI(prim).GetPrimvar("normals")
        if pv and pv.HasAuthoredValue():
            values, interp = pv.ComputeFlattened(Usd.TimeCode.Default()), pv.GetInterpolation()
            if values is None:
                values = pv.ComputeFlattened(Usd.TimeCode.EarliestTime())
        else:
            pb = UsdGeom.PointBased(prim)
            values, interp = _rest_value(pb.GetNormalsAttr()), pb.GetNormalsInterpolation()
        if values is None or len(values) == 0:
            return None, None
        n = np.asarray(values, dtype=np.float32).reshape(-1, 3)
        if interp in ("vertex", "varying") and n.shape[0] == point_count:
            return n, None
        if interp == "faceVarying" and face_vertex_indices is not None:
            if n.shape[0] != face_vertex_indices.size:
                self.fail(where, f"{n.shape[0]} faceVarying normals for "
                                 f"{face_vertex_indices.size} face vertices")
            return n, face_vertex_indices.copy()
        if interp in ("vertex", "varying", "faceVarying"):
            self.fail(where, f"{n.shape[0]} {interp} normals for {point_count} points")
        return None, None

    def method(self, where, q):
        """The dqskin name of the prim's ``primvars:skel:skinningMethod``."""
        method = str(q.GetSkinningMethod())
        if method not in SKINNING_METHODS:
            self.fail(where, f"unknown primvars:skel:skinningMethod {method!r} (expected "
                             f"{' or '.join(map(repr, SKINNING_METHODS))})")
        return SKINNING_METHODS[method]

    def blend_weights(self, where, prim, point_count):
        """(V,) float32 ``primvars:dqskin:blendWeights`` (:data:`BLEND_WEIGHTS`), or None."""
        pv = UsdGeom.PrimvarsAPI(prim).GetPrimvar(BLEND_WEIGHTS)
        if not pv or not pv.HasAuthoredValue():
            return None
        value = pv.ComputeFlattened(Usd.TimeCode.Default())
        b = np.asarray([] if value is None else value, dtype=np.float64).reshape(-1)
        if b.size == 1 and pv.GetInterpolation() == UsdGeom.Tokens.constant:
            b = np.full(point_count, b[0])
        if b.size != point_count:
            self.fail(where, f"primvars:{BLEND_WEIGHTS}: {b.size} values for {point_count} "
                             "points")
        if not np.all((b >= 0) & (b <= 1)):
            self.fail(where, f"primvars:{BLEND_WEIGHTS}: values outside [0, 1] (or NaN)")
        return b.astype(np.float32)

    def load_prim(self, q, skeleton, skel_prim):
        """A skinned point-based prim → :class:`Mesh`."""
        prim = q.GetPrim()
        where = str(prim.GetPath())
        method = self.method(where, q)
        points_attr = UsdGeom.PointBased(prim).GetPointsAttr()
        rest = _rest_value(points_attr)
        if rest is None or len(rest) == 0:
            self.fail(where, "no points")
        points = np.asarray(rest, dtype=np.float32).reshape(-1, 3)
        if not np.all(np.isfinite(points)):
            self.fail(where, "points has NaN or infinite coordinates")
        V = points.shape[0]
        idx, wts = self.influences(where, q, V, skeleton)
        mesh = UsdGeom.Mesh(prim)
        tris, counts, fvi = self.faces(where, mesh, V)
        normals, normal_vertex = self.normals(where, prim, V, fvi)
        st = UsdGeom.PrimvarsAPI(prim).GetPrimvar("st")
        uvs = None
        if st and st.HasAuthoredValue():
            flat = st.ComputeFlattened(Usd.TimeCode.Default())
            if flat is not None and len(flat):
                uvs = np.asarray(flat, dtype=np.float32).reshape(-1, 2)
        geom_bind = _matrices(q.GetGeomBindTransform(Usd.TimeCode.Default()))[0]
        if not np.all(np.isfinite(geom_bind)):
            self.fail(where, "primvars:skel:geomBindTransform has NaN or infinite entries")
        deform = _RestDeformer.build(self, where, q, skeleton, points_attr, points, normals,
                                     normal_vertex)
        blend = self.blend_weights(where, prim, V)
        if blend is not None:
            method = "blend"
        self.meshes.append(Mesh(
            name=where, points=points, faces=tris, joint_indices=idx, joint_weights=wts,
            skeleton=skeleton, geom_bind_transform=geom_bind,
            skinning_method=method, normals=normals,
            normal_vertex=normal_vertex,
            output_transforms=_output_transforms(self, where, skel_prim, prim),
            world_transforms=_world_transforms(self, prim, skel_prim),
            deformer=deform,
            face_vertex_counts=counts, face_vertex_indices=fvi, uvs=uvs, blend_weights=blend))

    def load_rigid(self, q, skeleton, skel_prim):
        """A skinned prim without points (Sphere, Cube, ...): moved as a whole by UsdSkel."""
        prim = q.GetPrim()
        where = str(prim.GetPath())
        if not q.IsRigidlyDeformed():
            self.fail(where, "vertex joint influences on a prim without points")
        method = self.method(where, q)
        idx, wts = self.influences(where, q, 1, skeleton)
        geom_bind = _matrices(q.GetGeomBindTransform(Usd.TimeCode.Default()))[0]
        parent = prim.GetParent()
        self.rigid.append(RigidPrim(
            name=where, skeleton=skeleton, joint_indices=idx[0], joint_weights=wts[0],
            geom_bind_transform=geom_bind, skinning_method=method,
            parent_transforms=_output_transforms(self, where, skel_prim, parent)))

    # -- the whole file --------------------------------------------------------------------

    def load(self) -> Scene:
        """The file as a :class:`Scene` (USD's diagnostics trapped throughout)."""
        with _usd_diagnostics(process_stderr=True) as self.warnings:
            self._stage = self._open()
            return self.load_stage()

    def load_stage(self) -> Scene:
        predicate = Usd.TraverseInstanceProxies()
        with self.at("/"):
            roots = [UsdSkel.Root(p) for p in self.stage.Traverse(predicate)
                     if p.IsA(UsdSkel.Root)]
        if not roots:
            raise InputError(f"{self.path}: no SkelRoot prim")
        cache = UsdSkel.Cache()
        seen: set[str] = set()
        for root in roots:
            with self.at(str(root.GetPrim().GetPath())):
                cache.Populate(root, predicate)
                bindings = cache.ComputeSkelBindings(root, predicate)
            for binding in bindings:
                self.load_binding(cache, binding, seen)
        if not self.meshes:
            raise InputError(f"{self.path}: no skinned point-based prim under "
                             f"{', '.join(str(r.GetPrim().GetPath()) for r in roots)}")
        tcps, up_axis, meters_per_unit = self.stage_metadata()
        return Scene(path=self.path, meshes=self.meshes, skeletons=self.skeletons,
                     times=self.times(),
                     time_codes_per_second=tcps, up_axis=up_axis,
                     meters_per_unit=meters_per_unit)

    def load_binding(self, cache, binding, seen):
        """The skinned prims of one UsdSkel binding not loaded yet (their skeleton too)."""
        skel = binding.GetSkeleton()
        targets = [q for q in binding.GetSkinningTargets()
                   if str(q.GetPrim().GetPath()) not in seen]
        if not skel or not targets:
            return
        for q in targets:
            where = str(q.GetPrim().GetPath())
            seen.add(where)
            with self.at(where):
                self.check_influences(where, q)
            skel_index = self.skeleton(cache, skel)
            with self.at(where):
                if UsdGeom.PointBased(q.GetPrim()):
                    self.load_prim(q, skel_index, skel.GetPrim())
                else:
                    self.load_rigid(q, skel_index, skel.GetPrim())

    def stage_metadata(self) -> tuple[float, str, float]:
        """``(timeCodesPerSecond, upAxis, metersPerUnit)``: positive, 'Y' or 'Z', positive."""
        tcps = float(self.stage.GetTimeCodesPerSecond())
        mpu = float(UsdGeom.GetStageMetersPerUnit(self.stage))
        up = str(UsdGeom.GetStageUpAxis(self.stage))
        for name, value in (("timeCodesPerSecond", tcps), ("metersPerUnit", mpu)):
            if not (np.isfinite(value) and value > 0):
                raise InputError(f"{self.path}: layer metadata {name} {value:g}: must be a "
                                 "positive number")
        if up not in ("Y", "Z"):
            raise InputError(f"{self.path}: layer metadata upAxis {up!r}: must be 'Y' or 'Z'")
        return tcps, up, mpu

    def times(self) -> np.ndarray:
        """The stage's start..end time codes, else every sample that drives the skinning."""
        st = self.stage
        if st.HasAuthoredTimeCodeRange():
            start, end = st.GetStartTimeCode(), st.GetEndTimeCode()
            if not (np.isfinite(start) and np.isfinite(end)):
                raise InputError(f"{self.path}: layer metadata startTimeCode {start:g} .. "
                                 f"endTimeCode {end:g}: must be finite")
            if end - start >= MAX_FRAMES:
                raise LimitError(f"{self.path}: layer metadata startTimeCode {start:g} .. "
                                 f"endTimeCode {end:g} spans more than {MAX_FRAMES} time codes")
            return np.arange(start, max(start, end) + 0.5, 1.0, dtype=np.float64)
        keys = set()
        for anim in self.animations:
            if anim is not None:
                keys.update(anim.key_times.tolist())
        for m in self.meshes:
            keys.update(st.GetPrimAtPath(m.name).GetAttribute("points").GetTimeSamples())
        return np.array(sorted(keys) or [0.0], dtype=np.float64)


def _shared_space(loader, skel_prim, gprim):
    """True when the skeleton and the gprim share their local-to-world at every time: no xform
    op (nor ``!resetXformStack!``) on either below their common ancestor (the prims owning
    their chains are at or above it), and that chain finite and invertible (evaluated once per
    chain: a crowd's instances hold many meshes each). Then skeleton space is gprim space and no
    transform chain is needed."""
    common = skel_prim.GetPath().GetCommonPrefix(gprim.GetPath())
    spaces = loader.spaces
    if not all(common.HasPrefix(spaces.owner(p)) for p in (skel_prim, gprim)):
        return False
    return spaces.is_regular(gprim)  # (the common ancestor's chain)


def _world_transforms(loader, gprim, skel_prim):
    """Skeleton space → world as an :class:`XformChain` (the skeleton's local-to-world, one per
    skeleton), or None when the gprim's local-to-world is the identity at every time (world is
    then the gprim's space, where ``output_transforms`` already lead). The chain's values are
    checked by :func:`_output_transforms`: it composes them with the gprim's."""
    if loader.spaces.is_identity(gprim):
        return None
    key = str(skel_prim.GetPath())
    if key not in loader.world_tracks:
        loader.world_tracks[key] = XformChain(loader.spaces.ops(skel_prim), (),
                                              name=f"{loader.path}: {key}")
    return loader.world_tracks[key]


def _output_transforms(loader, where, skel_prim, gprim):
    """Skeleton space → gprim space as an :class:`XformChain`, or None when it is the identity
    at every time."""
    if _shared_space(loader, skel_prim, gprim):
        return None
    track = XformChain(loader.spaces.ops(skel_prim), loader.spaces.ops(gprim),
                       name=f"{loader.path}: {where}")
    try:
        with np.errstate(all="ignore"):  # non-finite results are refused just below
            m = track.at(track.key_times)
    except ValueError as exc:
        loader.fail(where, str(exc).split(": ")[-1])
    bad = ~np.isfinite(m).all(axis=(1, 2))
    if bad.any():
        loader.fail(where, f"the transforms of {where} and its skeleton (xform ops of them and "
                           f"their ancestors) are NaN or infinite at time "
                           f"{track.key_times[int(np.argmax(bad))]:g}")
    if np.allclose(m, np.eye(4), rtol=0, atol=1e-12) and track.key_times.shape[0] == 1:
        return None
    return track


def _add_at(dst: np.ndarray, idx: np.ndarray | None, delta: np.ndarray) -> None:
    """``dst[:, idx] += delta`` over a frame axis, repeated indices adding up (as UsdSkel)."""
    if idx is None:
        dst += delta
    elif np.unique(idx).size == idx.size:
        dst[:, idx] += delta
    else:
        # (an index tuple with a slice: NumPy's stubs take integer arrays only)
        np.add.at(dst, (slice(None), idx), delta)  # type: ignore[arg-type]


class _RestDeformer(Deformer):
    """Per-time rest points/normals: time-sampled points, then blend shapes (UsdSkel order).

    Sub-shape weights (primary and inbetweens, extrapolation included) come from
    ``UsdSkel.BlendShapeQuery.ComputeSubShapeWeights``; offsets are added with NumPy, vectorized
    over frames. ``normalOffsets`` use the same ``pointIndices``; face-varying normals take the
    offset of their vertex.

    Velocities are exact: USD interpolates points and blend-shape weights linearly between time
    samples (:func:`~dqskin.animation.segment_rates`), and each blend shape's sub-shape weights are
    piecewise linear in its weight, between the sub-shapes' own weights (the zero shape at 0,
    inbetweens, the primary at 1).
    """

    def __init__(self, points_attr, points, normals, normal_vertex):
        self.points_attr = points_attr
        self.animated_points = points_attr.GetNumTimeSamples() > 0
        self.points = points
        self.normals = normals
        self.normal_vertex = normal_vertex
        # set by setup_blend_shapes: where the weights come from, the animation weight column of
        # each prim blend shape (-1: none), the query that splits weights into sub-shapes
        self.animation: UsdSkelAnimation | None = None
        self.shape_from_anim: np.ndarray | None = None
        self.query: UsdSkel.BlendShapeQuery | None = None
        # per sub-shape: (point indices or None, offsets (n, 3), normal offsets or None), or None
        # for the zero shape UsdSkel puts at weight 0
        self.sub_shapes: list[tuple[np.ndarray | None, np.ndarray, np.ndarray | None] | None] = []
        # per prim blend shape: (sub-shape indices, their weights), sorted by weight
        self.knots: list[tuple[list[int], list[float]]] = []

    @classmethod
    def build(cls, loader, where, q, skeleton, points_attr, points, normals, normal_vertex):
        """The deformer of one prim, or None when its rest points never change."""
        d = cls(points_attr, points, normals, normal_vertex)
        anim = loader.animations[skeleton]
        if q.HasBlendShapes() and anim is not None and anim.blend_shape_names:
            d.setup_blend_shapes(loader, where, q, anim)
        return d if d.animated_points or any(d.sub_shapes) else None

    def setup_blend_shapes(self, loader, where, q, anim):
        """Read the prim's blend shapes; weights will come from ``anim``."""
        prim = q.GetPrim()
        order = [str(n) for n in q.GetBlendShapeOrder()]
        column = {n: i for i, n in enumerate(anim.blend_shape_names)}
        self.shape_from_anim = np.array([column.get(n, -1) for n in order], dtype=np.int64)
        if np.all(self.shape_from_anim < 0):
            return
        bsq = UsdSkel.BlendShapeQuery(UsdSkel.BindingAPI(prim))
        if not bsq or bsq.GetNumBlendShapes() != len(order):
            loader.fail(where, f"skel:blendShapes names {len(order)} shapes but "
                               f"skel:blendShapeTargets resolves to "
                               f"{bsq.GetNumBlendShapes() if bsq else 0}")
        V = self.points.shape[0]
        point_indices = bsq.ComputeBlendShapePointIndices()
        offsets = bsq.ComputeSubShapePointOffsets()
        for s in range(bsq.GetNumSubShapes()):
            shape = bsq.GetBlendShapeIndex(s)
            target = bsq.GetBlendShape(shape)
            name = str(target.GetPrim().GetPath())
            idx = np.asarray(point_indices[shape], dtype=np.int64)
            off = np.asarray(offsets[s], dtype=np.float32).reshape(-1, 3)
            if off.shape[0] == 0:  # the implicit rest shape at weight 0
                self.sub_shapes.append(None)
                self._add_knot(shape, s, 0.0)
                continue
            count = idx.size if idx.size else V
            if off.shape[0] != count:
                loader.fail(name, f"{off.shape[0]} offsets for {count} points")
            if not np.all(np.isfinite(off)):
                loader.fail(name, "offsets has NaN or infinite values")
            if idx.size and (idx.min() < 0 or idx.max() >= V):
                loader.fail(name, f"pointIndices out of range for the {V} points of {where}")
            inbetween = bsq.GetInbetween(s)
            self._add_knot(shape, s, inbetween.GetWeight() if inbetween else 1.0)
            nrm = (inbetween.GetNormalOffsets() if inbetween
                   else _rest_value(target.GetNormalOffsetsAttr()))
            nrm = None if nrm is None or len(nrm) == 0 else np.asarray(nrm, np.float32)
            if nrm is not None and nrm.shape[0] != count:
                loader.fail(name, f"{nrm.shape[0]} normalOffsets for {count} points")
            self.sub_shapes.append((idx if idx.size else None, off, nrm))
        self.check_knots(loader, bsq)
        self.query = bsq
        self.animation = anim

    def check_knots(self, loader, bsq):
        """Every blend shape's sub-shape weights (0, inbetweens, 1) finite and distinct."""
        for shape, (_, weights) in enumerate(self.knots):
            w = np.asarray(weights, dtype=np.float64)
            if not (np.all(np.isfinite(w)) and np.all(np.diff(w) > 0)):
                name = str(bsq.GetBlendShape(shape).GetPrim().GetPath())
                loader.fail(name, f"inbetween weights {w.tolist()} (with 0 and 1 for the rest "
                                  "and the primary shape) must be finite and distinct")

    def _add_knot(self, shape, sub, weight):
        while len(self.knots) <= shape:
            self.knots.append(([], []))
        subs, weights = self.knots[shape]
        k = int(np.searchsorted(weights, weight))
        subs.insert(k, sub)
        weights.insert(k, float(weight))

    def sub_shape_rates(self, times: npt.ArrayLike) -> np.ndarray:
        """``(F, S_sub)`` float64 time derivatives of :meth:`sub_shape_weights`."""
        t = np.atleast_1d(np.asarray(times, dtype=np.float64))
        anim, cols = self.animation, self.shape_from_anim
        assert anim is not None and cols is not None, "only with blend shapes"
        anim_w = anim.blend_shape_weights(t)
        anim_rate = anim.blend_shape_weight_rates(t)
        out = np.zeros((t.shape[0], len(self.sub_shapes)))
        for shape, (subs, knots) in enumerate(self.knots):
            col = cols[shape]
            if col < 0:
                continue
            w, rate = anim_w[:, col], anim_rate[:, col]
            if len(subs) == 1:  # no inbetweens: the primary's weight is the shape's weight
                out[:, subs[0]] = rate
                continue
            k = np.clip(np.searchsorted(knots, w, side="right") - 1, 0, len(knots) - 2)
            span = np.diff(knots)[k]
            rows = np.arange(t.shape[0])
            out[rows, np.asarray(subs)[k + 1]] += rate / span
            out[rows, np.asarray(subs)[k]] -= rate / span
        return out

    def point_velocities_at(self, times: npt.ArrayLike) -> np.ndarray:
        """``(F, V, 3)`` float64 ``d points / dt`` per time code, prim space."""
        t = np.atleast_1d(np.asarray(times, dtype=np.float64))
        V = self.points.shape[0]
        vel = np.zeros((t.shape[0], V, 3))
        if self.animated_points:
            keys = np.asarray(self.points_attr.GetTimeSamples(), dtype=np.float64)
            vel += np.stack(segment_rates(keys, lambda k: np.asarray(
                self.points_attr.Get(Usd.TimeCode(float(keys[k]))), np.float64).reshape(V, 3), t))
        if self.sub_shapes:
            rate = self.sub_shape_rates(t)
            for s, sub in enumerate(self.sub_shapes):
                if sub is not None:
                    _add_at(vel, sub[0], rate[:, s, None, None] * sub[1][None])
        return vel

    def sub_shape_weights(self, times: np.ndarray) -> np.ndarray:
        """``(F, S_sub)`` float32 sub-shape weights at ``times``."""
        F = times.shape[0]
        out = np.zeros((F, len(self.sub_shapes)), dtype=np.float32)
        anim, cols, query = self.animation, self.shape_from_anim, self.query
        assert anim is not None and cols is not None and query is not None, "only with blend shapes"
        anim_w = anim.blend_shape_weights(times)
        for f in range(F):
            w = np.where(cols >= 0, anim_w[f][np.maximum(cols, 0)], 0.0).astype(np.float32)
            sub_w, _, sub_idx = query.ComputeSubShapeWeights(Vt.FloatArray.FromNumpy(w))
            sub = np.asarray(sub_idx, dtype=np.int64)
            np.add.at(out[f], sub, np.asarray(sub_w, dtype=np.float32))
        return out

    def points_at(self, times: npt.ArrayLike) -> np.ndarray:
        """``(F, V, 3)`` float32 rest points with blend shapes applied, prim space."""
        t = np.atleast_1d(np.asarray(times, dtype=np.float64))
        if self.animated_points:
            pts = np.stack([np.asarray(self.points_attr.Get(Usd.TimeCode(float(ti))),
                                       dtype=np.float32).reshape(-1, 3) for ti in t])
            if pts.shape[1] != self.points.shape[0]:
                raise InputError(f"{self.points_attr.GetPath()}: point count changes over time")
        else:
            pts = np.broadcast_to(self.points, (t.shape[0],) + self.points.shape).copy()
        if self.sub_shapes:
            w = self.sub_shape_weights(t)
            for s, sub in enumerate(self.sub_shapes):
                if sub is None:
                    continue
                idx, off, _ = sub
                _add_at(pts, idx, w[:, s, None, None] * off[None])
        return pts

    def normals_at(self, times: npt.ArrayLike) -> np.ndarray | None:
        """``(F, N, 3)`` float32 rest normals with blend-shape normal offsets (not normalized), or
        None without normals."""
        if self.normals is None:
            return None
        t = np.atleast_1d(np.asarray(times, dtype=np.float64))
        V = self.points.shape[0]
        nrm = np.broadcast_to(self.normals, (t.shape[0],) + self.normals.shape).copy()
        if any(s is not None and s[2] is not None for s in self.sub_shapes):
            w = self.sub_shape_weights(t)
            per_vertex = np.zeros((t.shape[0], V, 3), dtype=np.float32)
            for s, sub in enumerate(self.sub_shapes):
                if sub is None:
                    continue
                idx, _, noff = sub
                if noff is None:
                    continue
                _add_at(per_vertex, idx, w[:, s, None, None] * noff[None])
            nrm += per_vertex if self.normal_vertex is None else per_vertex[:, self.normal_vertex]
        return nrm


def load_usd(path: str | os.PathLike) -> Scene:
    """Load every skinned point-based prim of a USD file.

    Parameters
    ----------
    path : str or os.PathLike
        A ``.usd``, ``.usda``, ``.usdc`` or ``.usdz`` file with one or more ``SkelRoot`` prims.

    Returns
    -------
    Scene
        One :class:`~dqskin.scene.Mesh` per skinned ``UsdGeom.PointBased`` prim (named by prim
        path), one :class:`~dqskin.skeleton.Skeleton` per bound ``Skeleton`` prim (joint names
        are the ``joints`` tokens, bind transforms world-space, rest transforms local), one
        :class:`UsdSkelAnimation` or None per skeleton; ``times`` are the stage's start..end time
        codes (step 1), else every animation/points sample, else ``[0.]``; the stage's
        ``timeCodesPerSecond``, ``upAxis`` and ``metersPerUnit``.

    Raises
    ------
    ValueError
        The only exception it raises, on one line naming the file and the prim (and the
        attribute, joint or time where it applies): missing, unreadable or non-USD file; no
        ``SkelRoot`` or no skinned point-based prim; a Skeleton without joints, with duplicate
        joint names, an invalid joint topology, bind/rest transforms of the wrong count,
        non-finite or singular; a ``SkelAnimation`` whose translations, rotations, scales or
        blendShapeWeights (default value or any time sample) do not have one finite value per
        joint / blend shape, or that UsdSkel cannot compose; missing ``jointIndices`` or
        ``jointWeights``, or ones with mismatched interpolation, element size or count,
        out-of-range indices, NaN or negative weights; invalid face topology; normals whose count
        fits no interpolation; invalid stage metadata (time range, ``timeCodesPerSecond``,
        ``upAxis``, ``metersPerUnit``).

    Notes
    -----
    USD's own diagnostics (the C++ warnings it would print to stderr) are trapped while the file
    is read and dropped; those that mean the file cannot be used become the ValueError.
    """
    return _Loader(path).load()


def load(path: str | os.PathLike, *, clip: str | int | None = None,
         max_input_gib: float | None = None) -> Scene:
    """:func:`load_usd` with the signature every format's loader has (USD has one animation per
    skeleton, so ``clip`` must be None; ``max_input_gib`` is accepted for that signature: USD
    reads arrays of the sizes its layers hold)."""
    if clip is not None:
        raise InputError(f"{path}: ", Param("clip"), " applies to glTF files; USD has one "
                         "animation per skeleton")
    return load_usd(path)


def open_stage(path: str | os.PathLike) -> Usd.Stage:
    """The stage of ``path`` opened as :func:`load_usd` opens it (the same checks first, every
    payload loaded, USD's diagnostics trapped), for what reads a USD file that is not a
    character (``dqskin info`` on a point cache).

    Raises
    ------
    InputError
        Not a file, not a USD suffix, or USD cannot open it.
    """
    loader = _Loader(path)
    with _usd_diagnostics(process_stderr=True) as loader.warnings:
        return loader._open()


def load_rigid_prims(scene: Scene) -> list[RigidPrim]:
    """The rigidly skinned prims without points of a scene loaded by :func:`load_usd`.

    Parameters
    ----------
    scene : Scene
        Its ``path`` is read again; skeleton indices refer to ``scene.skeletons``.

    Returns
    -------
    list of RigidPrim
    """
    loader = _Loader(scene.path)
    loader.load()
    index = {s.name: i for i, s in enumerate(scene.skeletons)}
    out: list[RigidPrim] = []
    for r in loader.rigid:
        name = loader.skeletons[r.skeleton].name
        if name not in index:
            raise InputError(f"{scene.path}: {r.name}: skeleton {name} is not in the scene")
        r.skeleton = index[name]
        out.append(r)
    return out
