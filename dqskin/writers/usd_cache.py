"""Write skinned results as a USD point cache: a new stage with time-sampled points, no skinning.

The source stage (never modified) is flattened into one new layer, so topology, UVs, materials,
other primvars and transforms are kept as composed. Every skinned prim then gets time-sampled
``points``, ``extent`` and, when given, ``normals`` and ``velocities``; skinned prims without
points get time-sampled ``xformOp:transform`` (engine-skinned); every skeleton binding is
removed (``SkelBindingAPI``, ``skel:*`` and ``primvars:skel:*`` properties, ``SkelRoot`` retyped
``Xform``) so nothing is skinned twice, and stale ``extentsHint`` on the skinned prims' ancestors
is dropped. ``Skeleton`` prims are kept but deactivated (unbound from their animation they would
be drawn in the rest pose); ``SkelAnimation`` prims stay as inert data.

Two classes serve both USD outputs, the single layer (:class:`UsdCacheWriter`) and the value
clips of :mod:`dqskin.writers.usd_clips`: :class:`CacheLayer` (the flattened, unbound copy of the
source and where each skinned value goes in it, as picklable :class:`Target` records) and
:class:`SampleWriter` (checked chunks of skinned frames → time samples: streamed into a crate
file by :class:`~.crate.CrateSamples`, after the cache's copy of the source exported once or as
a clip layer made on a worker that never opens the source stage; set in the cache's own Sdf
layer for ``.usda``).
"""

import contextlib
import ctypes
import itertools
import os
from collections.abc import Callable, Iterable, Mapping, Sequence
from concurrent.futures import ThreadPoolExecutor, wait
from dataclasses import dataclass
from pathlib import Path
from types import SimpleNamespace
from typing import TYPE_CHECKING, Any, TypeAlias

import numpy as np
import numpy.typing as npt
from pxr import Ar, Gf, Sdf, Tf, Usd, UsdGeom, Vt

from ..errors import InputError
from ..files.atomic import CommitOnSuccess, atomic_path, check_parent
from ..files.crate import CrateSamples, UnsupportedCrate
from ..files.direct import pays as direct_pays
from ..options import SkinOptions
from ..pipeline import rigid_transforms
from ..readers.usd import _tf_message, load_rigid_prims
from ..shapes import frames_of
from . import CACHE_EXTENSIONS  # (defined where it is known without importing USD)

if TYPE_CHECKING:
    from ..readers.usd import RigidPrim
    from ..scene import Scene, SkinnedFrames

__all__ = ["CACHE_EXTENSIONS", "CHUNK_BYTES", "CHUNK_FRAMES", "CHUNK_MIN_FRAMES",
           "CLIPS_FOLDER_SUFFIX",
           "CacheLayer", "SampleWriter", "Target", "UsdCacheWriter", "check_not_input",
           "clips_folder", "chunk_frames", "export_layer", "frame_bytes", "layer_file",
           "stage_files", "write_usd_cache"]


_SKEL_API = "SkelBindingAPI"

Frames = Mapping[str, npt.ArrayLike]
"""Per mesh name (prim path), (F, N, 3) values of ``F`` frames."""

TargetLookup = Callable[[str, str], "Target"]
"""``(prim, what) → Target``: :meth:`CacheLayer.target` or a lookup in its targets."""

Sink: TypeAlias = "Sdf.Layer | CrateSamples"
"""Where samples go: an ``Sdf.Layer`` or a :class:`~dqskin.files.crate.CrateSamples`."""

Prepared = tuple[np.ndarray, list[tuple[tuple[str, str], Any]]]
"""What :meth:`SampleWriter.prepare` returns: the times and ``[((prim, what), values)]``."""


def frame_bytes(scene: "Scene", normals: bool = True, velocities: bool = True) -> int:
    """Bytes of one frame's point, normal and velocity samples of ``scene``'s meshes (float32)."""
    return 12 * sum(len(m.points) * (2 if velocities else 1)
                    + (len(m.normals) if normals and m.normals is not None else 0)
                    for m in scene.meshes)


CHUNK_MIN_FRAMES = 32
"""Fewest frames skinned at a time (a chunk: see :data:`CHUNK_BYTES`)."""

CHUNK_FRAMES = 256
"""Most frames skinned at a time (a chunk: see :data:`CHUNK_BYTES`), and the chunk of ``.npz``
and per-frame bakes: a task keeps chunks of a small mesh this short, so that skinning one
overlaps writing the one before."""

CHUNK_BYTES = 64 << 20
"""Skinned points, normals and velocities a task holds per chunk it skins: chunks are
:data:`CHUNK_MIN_FRAMES` frames or as many more as fit, up to :data:`CHUNK_FRAMES`, since each
:meth:`dqskin.Scene.skin` call costs milliseconds whatever its size (32-frame chunks of a
3,273-point mesh cost 0.8 of 4.2 CPU-s of a 10,000-frame bake)."""


def chunk_frames(scene: "Scene", options: SkinOptions) -> int:
    """Frames per chunk skinned at a time with ``options`` (:data:`CHUNK_BYTES` of samples, at
    least :data:`CHUNK_MIN_FRAMES`, at most :data:`CHUNK_FRAMES`): the chunks of a clip layer,
    and of a single-layer USD bake (which streams them to its file, so this is what it holds)."""
    size = frame_bytes(scene, options.normals, options.velocities)
    return min(max(CHUNK_MIN_FRAMES, CHUNK_BYTES // max(size, 1)), CHUNK_FRAMES)


CLIPS_FOLDER_SUFFIX = ".clips"
"""``SHOT.usd`` → ``SHOT.clips/``: the folder of a value-clip cache's layers
(:mod:`.usd_clips`)."""


def clips_folder(out: str | os.PathLike) -> Path:
    """The folder of the clip layers of ``out`` (``SHOT.usd`` → ``SHOT.clips``)."""
    path = Path(out)
    return path.with_name(path.stem + CLIPS_FOLDER_SUFFIX)


def _frames(name, what, a, frames, count, finite=True):
    """``a`` as float32 ``(frames, count, 3)``, finite unless ``finite`` is False (checked by
    the caller); ValueError naming ``what[name]``."""
    return frames_of(f"{what}[{name!r}]", a, frames, count, dtype=np.float32, finite=finite,
                     broadcast=False)[0]


def _same_file(a, b):
    try:
        return os.path.samefile(a, b)
    except OSError:
        return os.path.realpath(a) == os.path.realpath(b)


def layer_file(layer: Sdf.Layer) -> str | None:
    """The file holding ``layer``: its real path, the package for a layer inside one (``.usdz``),
    None for an anonymous layer. (A ``[`` in a file's own name is kept: ``br[1].usda``.)"""
    real = layer.realPath
    if not real:
        return None
    if Ar.IsPackageRelativePath(real):
        return Ar.SplitPackageRelativePathOuter(real)[0]
    return real


def stage_files(stage: Usd.Stage) -> list[str]:
    """Every file ``stage`` reads, sorted: its layer stack, references and payloads (its used
    layers), and the layers and manifests its value clips name (opened only when values are
    read, so not yet among the used layers)."""
    files = {f for f in map(layer_file, stage.GetUsedLayers()) if f}
    for prim in stage.Traverse(Usd.TraverseInstanceProxies(Usd.PrimAllPrimsPredicate)):
        api = Usd.ClipsAPI(prim)
        sets = api.GetClips()
        if not sets:
            continue
        for name in sets:
            assets = [*(api.ComputeClipAssetPaths(name) or []),
                      api.GetClipManifestAssetPath(name)]
            for asset in assets:
                if asset is not None and asset.resolvedPath:
                    real = asset.resolvedPath
                    files.add(Ar.SplitPackageRelativePathOuter(real)[0]
                              if Ar.IsPackageRelativePath(real) else real)
    return sorted(files)


def _source_files(stage, source_path):
    """Every file the source stage reads (:func:`stage_files`) and ``source_path``."""
    return {os.fspath(source_path), *stage_files(stage)}


def check_not_input(out: str | os.PathLike, stage: Usd.Stage, src: str | os.PathLike) -> None:
    """InputError (a ValueError) when ``out`` is a file the source ``stage`` (read from ``src``)
    reads: its root layer, a sublayer, a reference, its usdz package."""
    if os.path.exists(out) and any(_same_file(out, f) for f in _source_files(stage, src)
                                   if os.path.exists(f)):
        raise InputError(f"{out}: refusing to overwrite an input of {src}")


def _remove_skel_binding(layer):
    """Strip SkelBindingAPI, skel properties and SkelRoot types; deactivate Skeletons."""
    specs = []
    layer.Traverse(Sdf.Path.absoluteRootPath,
                   lambda p: specs.append(p) if p.IsPrimPath() else None)
    for path in specs:
        spec = layer.GetPrimAtPath(path)
        if spec.typeName == "SkelRoot":
            spec.typeName = "Xform"
        elif spec.typeName == "Skeleton":
            spec.active = False  # unbound, it would be drawn in its rest pose
        if spec.HasInfo("apiSchemas"):
            keep = [s for s in spec.GetInfo("apiSchemas").ApplyOperations([]) if s != _SKEL_API]
            if keep:
                spec.SetInfo("apiSchemas", Sdf.TokenListOp.CreateExplicit(keep))
            else:
                spec.ClearInfo("apiSchemas")
        for prop in list(spec.properties):
            if prop.name.startswith(("skel:", "primvars:skel:")):
                spec.RemoveProperty(prop)


def _attribute(layer, prim_spec, name, type_name, variability=Sdf.VariabilityVarying, **info):
    """The attribute spec ``name`` on ``prim_spec`` with no time samples (created if needed)."""
    spec = layer.GetAttributeAtPath(prim_spec.path.AppendProperty(name))
    if spec is None:
        spec = Sdf.AttributeSpec(prim_spec, name, type_name, variability)
    if spec.HasInfo("timeSamples"):
        spec.ClearInfo("timeSamples")
    for key, value in info.items():
        spec.SetInfo(key, value)
    return spec


class _Buffer(ctypes.Structure):
    """CPython's ``Py_buffer`` (in the stable ABI since 3.11)."""

    _fields_ = [("buf", ctypes.c_void_p), ("obj", ctypes.py_object), ("len", ctypes.c_ssize_t),
                ("itemsize", ctypes.c_ssize_t), ("readonly", ctypes.c_int),
                ("ndim", ctypes.c_int), ("format", ctypes.c_char_p),
                ("shape", ctypes.c_void_p), ("strides", ctypes.c_void_p),
                ("suboffsets", ctypes.c_void_p), ("internal", ctypes.c_void_p)]


def _buffer_api():
    """``(PyObject_GetBuffer, PyBuffer_Release)`` through ctypes prototypes of our own (typing
    the shared ``ctypes.pythonapi`` functions would change them for every other module), or
    None (not CPython)."""
    try:
        get = ctypes.PYFUNCTYPE(ctypes.c_int, ctypes.py_object, ctypes.c_void_p, ctypes.c_int)(
            ("PyObject_GetBuffer", ctypes.pythonapi))
        release = ctypes.PYFUNCTYPE(None, ctypes.c_void_p)(("PyBuffer_Release", ctypes.pythonapi))
    except (AttributeError, TypeError):
        return None
    return get, release


_BUFFER_API = _buffer_api()


def _vt_addresses():
    """``address(array)`` of a Vt array's first element (its buffer is read-only to Python):
    through ``PyObject_GetBuffer``, else NumPy's (slower) view of it; one per call of
    :func:`vec3f_arrays` (its ``Py_buffer`` is not shared between threads)."""
    if _BUFFER_API is None:
        return lambda array: np.asarray(array).__array_interface__["data"][0]
    get, release = _BUFFER_API
    view = _Buffer()
    ref = ctypes.addressof(view)

    def address(array):
        if get(array, ref, 0) != 0:
            raise BufferError("Vt array without a buffer")
        try:
            return view.buf
        finally:
            release(ref)
    return address


def _memcpy_works():
    """True when a Vt.Vec3fArray's buffer is its own storage (a copy into it is seen)."""
    try:
        probe = Vt.Vec3fArray(2)
        src = np.arange(6, dtype=np.float32)
        ctypes.memmove(_vt_addresses()(probe), src.ctypes.data, src.nbytes)
        return np.array_equal(np.asarray(probe).ravel(), src)
    except Exception:  # noqa: BLE001  (any failure: use FromNumpy)
        return False


_MEMCPY = _memcpy_works()


SMALL_ARRAY = 16
"""Elements up to which :func:`vec3f_arrays` converts with ``Vt.Vec3fArray.FromNumpy``."""


def vec3f_arrays(frames):
    """One new ``Vt.Vec3fArray`` per frame of (F, N, 3) float32 ``frames``.

    Each is allocated by Vt and filled with one ``memmove`` (which releases the GIL):
    ``Vt.Vec3fArray.FromNumpy`` converts element by element, slower on large arrays, but takes
    one call: arrays of up to :data:`SMALL_ARRAY` elements (extents) use it. A new array is never
    shared, so writing into its storage is safe; :data:`_MEMCPY` checks once that the buffer Vt
    exposes is that storage, else ``FromNumpy`` is used.
    """
    frames = np.ascontiguousarray(frames, dtype=np.float32)
    F, N = frames.shape[:2]
    if not _MEMCPY or N <= SMALL_ARRAY:
        return [Vt.Vec3fArray.FromNumpy(f) for f in frames]
    out = [Vt.Vec3fArray(N) for _ in range(F)]
    base, stride, size = frames.ctypes.data, frames.strides[0], N * 12
    move, address = ctypes.memmove, _vt_addresses()
    for i, arr in enumerate(out):
        move(address(arr), base + i * stride, size)
    return out


def _extents(points, pad, block=32):
    """(F, 2, 3) float32 ``[min - pad, max + pad]`` of (F, V, 3) ``points``, reduced over
    contiguous (block, 3, V) copies (faster than per-component strided reductions or a min over
    axis 1 of (F, V, 3))."""
    out = np.empty((len(points), 2, 3), np.float32)
    for a in range(0, len(points), block):
        q = np.ascontiguousarray(points[a:a + block].transpose(0, 2, 1))
        out[a:a + block, 0] = q.min(axis=2) - pad
        out[a:a + block, 1] = q.max(axis=2) + pad
    return out


def _rigid_prims(stage, scene):
    """:func:`~.usd.load_rigid_prims` of ``scene``, which loads the file again; skipped (no
    rigid prims) when no prim without points has joint influences of its own or an ancestor's,
    a scan much cheaper than that second load."""
    influenced = set()
    for prim in stage.Traverse(Usd.TraverseInstanceProxies()):
        path = prim.GetPath()
        if (path.GetParentPath() in influenced
                or prim.GetAttribute("primvars:skel:jointIndices").HasAuthoredValue()):
            influenced.add(path)
            if prim.IsA(UsdGeom.Boundable) and not prim.IsA(UsdGeom.PointBased):
                return load_rigid_prims(scene)
    return []


def _rest_widths(prim):
    """Authored widths of curves or points (None for other prims)."""
    for schema in (UsdGeom.Curves, UsdGeom.Points):
        if prim.IsA(schema):
            attr = schema(prim).GetWidthsAttr()
            value = attr.Get(Usd.TimeCode.Default()) if attr.HasAuthoredValue() else None
            return value if value is not None else attr.Get(Usd.TimeCode.EarliestTime())
    return None


def _prim_spec(layer, path):
    """The prim spec at ``path``, created as an ``over`` (and de-instanced) if absent."""
    sdf_path = Sdf.Path(path)
    for anc in sdf_path.GetPrefixes()[:-1]:
        spec = layer.GetPrimAtPath(anc)
        if spec is not None and spec.HasInfo("instanceable") and spec.instanceable:
            spec.instanceable = False
    return layer.GetPrimAtPath(sdf_path) or Sdf.CreatePrimInLayer(layer, sdf_path)


@dataclass(frozen=True)
class Target:
    """Where one skinned value goes: plain strings and numbers, so it pickles to clip workers.

    Attributes
    ----------
    attr : str
        Attribute path (``/Root/Mesh.points``).
    type_name : str
        Its Sdf value type (``point3f[]``, ``normal3f[]``, ``matrix4d``, ...).
    info : tuple of (str, str)
        Metadata to author with it (a normals primvar's ``interpolation``).
    pad : float
        Half the widest rest width (curves, points): added around ``extent``.
    """

    attr: str
    type_name: str
    info: tuple[tuple[str, str], ...] = ()
    pad: float = 0.0

    def spec(self, layer: Sdf.Layer) -> Sdf.AttributeSpec:
        """The attribute spec in ``layer``, made (with ``over`` prims above it) if absent."""
        path = Sdf.Path(self.attr)
        spec = layer.GetAttributeAtPath(path)
        if spec is None:
            prim = _prim_spec(layer, path.GetPrimPath())
            spec = _attribute(layer, prim, path.name, Sdf.ValueTypeNames.Find(self.type_name),
                              **dict(self.info))
        return spec


_VALUE_TYPES = {"points": "point3f[]", "extent": "float3[]", "velocities": "vector3f[]",
                "normals": "normal3f[]", "xformOp:transform": "matrix4d"}


class CacheLayer:
    """The source stage flattened into one new layer with every skeleton binding removed, and the
    :class:`Target` of each skinned value in it (made on first use by :meth:`target`).

    Parameters
    ----------
    scene : Scene
        What :func:`dqskin.readers.usd.load_usd` returned.
    out_path : str or os.PathLike
        The cache to write: checked to be ``.usda/.usdc/.usd`` and not the source file nor any
        layer it reads (nothing is written here).
    source_path : str or os.PathLike, optional
        The stage to copy; ``scene.path`` by default.
    dropped : sequence of str
        Skinned prims of the source left out of the bake (:func:`dqskin.selection.
        select_meshes`): deactivated in the copy, which would show them in their rest pose.
    """

    def __init__(self, scene: "Scene", out_path: str | os.PathLike, *,
                 source_path: str | os.PathLike | None = None,
                 dropped: "Sequence[str]" = ()) -> None:
        out = os.fspath(out_path)
        check_parent(out)
        src = os.fspath(scene.path if source_path is None else source_path)
        ext = os.path.splitext(out)[1].lower()
        if ext not in CACHE_EXTENSIONS:
            raise InputError(f"{out}: cannot write extension {ext!r}; use one of "
                             f"{', '.join(CACHE_EXTENSIONS)}")
        try:
            stage = Usd.Stage.Open(src, Usd.Stage.LoadAll)
        except Tf.ErrorException:
            stage = None
        if stage is None:
            raise InputError(f"{src}: cannot open the source stage")
        check_not_input(out, stage, src)
        self.scene, self.out, self.src, self.ext = scene, out, src, ext
        self.stage = stage
        self.rigid = _rigid_prims(stage, scene)
        self.layer = stage.Flatten()
        _remove_skel_binding(self.layer)
        for name in dropped:
            spec = self.layer.GetPrimAtPath(name)
            if spec is not None:
                spec.active = False
        self.targets: dict[tuple[str, str], Target] = {}
        self._target_prims: set[str] = set()  # prims with a target (ancestors' extentsHint dropped)

    def target(self, name: str, what: str) -> Target:
        """The :class:`Target` of ``what`` (``points``, ``extent``, ``normals``, ``velocities``,
        ``xformOp:transform``) on prim ``name``; its spec is made in :attr:`layer` (time samples
        cleared, stale ancestor ``extentsHint`` dropped) on first use."""
        key = (name, what)
        if key in self.targets:
            return self.targets[key]
        layer = self.layer
        spec = _prim_spec(layer, name)
        info: tuple[tuple[str, str], ...] = ()
        pad = 0.0
        if what == "xformOp:transform":
            attr = what
            order = _attribute(layer, spec, "xformOpOrder", Sdf.ValueTypeNames.TokenArray,
                               Sdf.VariabilityUniform)
            order.default = Vt.TokenArray([what])
        else:
            prim = self.stage.GetPrimAtPath(name)
            if not prim or not UsdGeom.PointBased(prim):
                raise InputError(f"{self.src}: {name}: not a point-based prim")
            if name not in self._target_prims:  # a set: a crowd has thousands of prims
                for anc in Sdf.Path(name).GetPrefixes()[:-1]:
                    anc_spec = layer.GetPrimAtPath(anc)
                    if anc_spec is not None and "extentsHint" in anc_spec.properties:
                        anc_spec.RemoveProperty(anc_spec.properties["extentsHint"])
            attr = what
            if what == "normals":
                pv = UsdGeom.PrimvarsAPI(prim).GetPrimvar("normals")
                if pv and pv.HasAuthoredValue():
                    attr = "primvars:normals"
                    idx = layer.GetAttributeAtPath(spec.path.AppendProperty(attr + ":indices"))
                    if idx is not None:
                        spec.RemoveProperty(idx)
                    interp = pv.GetInterpolation()
                else:
                    interp = UsdGeom.PointBased(prim).GetNormalsInterpolation()
                info = (("interpolation", str(interp)),)
            elif what == "points":
                w = _rest_widths(prim)
                if w is not None and len(w):
                    pad = 0.5 * float(np.max(np.asarray(w)))
        target = Target(str(spec.path.AppendProperty(attr)), _VALUE_TYPES[what], info, pad)
        _attribute(layer, spec, attr, Sdf.ValueTypeNames.Find(target.type_name), **dict(info))
        self.targets[key] = target
        self._target_prims.add(name)
        return target

    def all_targets(self, *, normals: bool = True,
                    velocities: bool = True) -> dict[tuple[str, str], Target]:
        """Every :class:`Target` :meth:`dqskin.Scene.skin` fills with these options (points and
        extent of every mesh, normals of meshes that have them, velocities) and every rigid
        prim's ``xformOp:transform``, keyed ``(prim, what)``."""
        for m in self.scene.meshes:
            for what in ("points", "extent"):
                self.target(m.name, what)
            if normals and m.normals is not None:
                self.target(m.name, "normals")
            if velocities:
                self.target(m.name, "velocities")
        for r in self.rigid:
            self.target(r.name, "xformOp:transform")
        return dict(self.targets)

    def set_metadata(self, t_min: float, t_max: float, note: str = "point cache") -> None:
        """Time range, frame rate, up axis and units of the cache."""
        layer, scene = self.layer, self.scene
        with Sdf.ChangeBlock():
            layer.timeCodesPerSecond = float(scene.time_codes_per_second)
            layer.framesPerSecond = float(scene.time_codes_per_second)
            layer.startTimeCode, layer.endTimeCode = float(t_min), float(t_max)
            root = layer.pseudoRoot
            root.SetInfo(UsdGeom.Tokens.upAxis, str(scene.up_axis))
            root.SetInfo(UsdGeom.Tokens.metersPerUnit, float(scene.meters_per_unit))
            layer.documentation = f"dqskin {note} of {self.src}"


def export_layer(layer: Sdf.Layer, claim: atomic_path, out: str | os.PathLike | None = None,
                 tmp: Path | None = None) -> Path:
    """Write ``layer`` to the temporary file of ``claim`` (an :class:`~.atomic.atomic_path`, not
    committed here), or to ``tmp`` in its folder; ``.usd`` is crate. ValueError naming ``out``
    (default the claimed path)."""
    name = os.fspath(claim.path if out is None else out)
    tmp = claim.open() if tmp is None else tmp
    args = {"format": "usdc"} if Path(tmp).suffix.lower() == ".usd" else {}
    try:
        ok = layer.Export(str(tmp), args=args)
    except Tf.ErrorException as exc:  # (its first diagnostic: a full disk repeats one per block)
        raise InputError(f"{name}: USD could not write the layer "
                         f"({_tf_message(exc).replace(str(tmp), name)})") from None
    if not ok:
        raise InputError(f"{name}: USD could not write the layer")
    return tmp


class SampleWriter:
    """Checked chunks of skinned frames → time samples in a layer: an ``Sdf.Layer`` (a
    ``.usda`` cache: one ``Vt`` array per frame and attribute, set under the GIL) or a
    :class:`~.crate.CrateSamples` (every crate file: a clip layer, or a ``.usdc``/``.usd``
    cache after its copy of the source; the frames go to the file as they come).

    Parameters
    ----------
    scene : Scene
        Its meshes' rest data check the shapes; rigid prims are skinned from it.
    target : callable (prim, what) → Target
        :meth:`CacheLayer.target`, or a lookup in the :meth:`CacheLayer.all_targets` a clip
        worker received.
    rigid : list of dqskin.readers.usd.RigidPrim
        Skinned prims without points, baked as ``xformOp:transform`` samples.
    options : dqskin.SkinOptions
        As for :class:`UsdCacheWriter`.
    """

    def __init__(self, scene: "Scene", target: TargetLookup, rigid: "list[RigidPrim]",
                 options: SkinOptions) -> None:
        self.scene, self.target, self.rigid, self.options = scene, target, rigid, options
        self.meshes = {m.name: m for m in scene.meshes}
        self._pads: dict[str, float] = {}  # prim → extent padding, resolved on the thread that
        # owns the layer

    def _pad(self, name: str) -> float:
        pad = self._pads.get(name)
        if pad is None:
            pad = self._pads[name] = self.target(name, "points").pad
        return pad

    def prepare(self, times: npt.ArrayLike, points: Frames, normals: Frames | None = None,
                velocities: Frames | None = None, checked: bool = False,
                raw: bool = False) -> Prepared:
        """Check a chunk (see :meth:`UsdCacheWriter.write`) and turn it into USD values, touching
        no layer (so it can run on another thread than :meth:`apply`): returns the checked
        float64 times and ``[((prim, what), values)]``, one Vt array or Gf matrix per time, or
        with ``raw`` the frames as arrays ((F, N, 3) float32; (F, 4, 4) float64 column-vector
        matrices) for a :class:`~.crate.CrateSamples`. ``checked``: the caller has checked that
        every value is finite (:func:`dqskin.validation.check_skinned`): float32 arrays are not
        checked again (others are, as float32); shapes are always checked."""
        t = np.atleast_1d(np.asarray(times, dtype=np.float64))
        if t.ndim != 1 or t.size == 0 or not np.all(np.isfinite(t)):
            raise InputError(f"times: expected a non-empty 1-D array of finite time codes, "
                             f"got shape {t.shape}")
        F = t.shape[0]
        meshes = self.meshes
        normals, velocities = normals or {}, velocities or {}
        for what, d in (("points", points), ("normals", normals), ("velocities", velocities)):
            unknown = sorted(set(d) - set(meshes))
            if unknown:
                raise InputError(f"{what}: no mesh {unknown[0]!r} in {self.scene.path}; meshes: "
                                 f"{sorted(meshes)}")
        # checked float32 values need no second pass (others may overflow)
        def finite(a: npt.ArrayLike) -> bool:
            return not (checked and getattr(a, "dtype", None) == np.float32)

        pts = {n: _frames(n, "points", p, F, meshes[n].points.shape[0], finite(p))
               for n, p in points.items()}
        nrm = {}
        for n, v in normals.items():
            if meshes[n].normals is None:
                raise InputError(f"normals[{n!r}]: the mesh has no rest normals to replace")
            nrm[n] = _frames(n, "normals", v, F, meshes[n].normals.shape[0], finite(v))
        vel = {n: _frames(n, "velocities", v, F, meshes[n].points.shape[0], finite(v))
               for n, v in velocities.items()}
        convert = (lambda a: a) if raw else vec3f_arrays
        values = []
        for name in sorted(set(pts) | set(nrm) | set(vel)):
            if name in pts:
                p = pts[name]
                values.append(((name, "points"), convert(p)))
                values.append(((name, "extent"), convert(_extents(p, self._pad(name)))))
            if name in nrm:
                values.append(((name, "normals"), convert(nrm[name])))
            if name in vel:
                values.append(((name, "velocities"), convert(vel[name])))
        for r in self.rigid:
            xf = rigid_transforms(self.scene, r, t, self.options)
            values.append(((r.name, "xformOp:transform"),
                           xf if raw else [Gf.Matrix4d(m.T.tolist()) for m in xf]))
        return t, values

    def apply(self, layer: Sink, prepared: Prepared) -> np.ndarray:
        """Set the samples :meth:`prepare` made in ``layer`` (raw for a
        :class:`~.crate.CrateSamples`); returns their times."""
        t, values = prepared
        if isinstance(layer, CrateSamples):  # the chunk as one write
            targets = [(self.target(name, what), vals) for (name, what), vals in values]
            layer.add_many([(tg.attr, tg.type_name, t, vals, tg.info) for tg, vals in targets])
            return t
        times = t.tolist()
        with Sdf.ChangeBlock():
            for (name, what), vals in values:
                attr = self.target(name, what).spec(layer).path
                for ti, v in zip(times, vals):
                    layer.SetTimeSample(attr, ti, v)
        return t

    def write(self, layer: Sink, times: npt.ArrayLike, points: Frames,
              normals: Frames | None = None, velocities: Frames | None = None) -> np.ndarray:
        """Add samples at ``times`` to ``layer`` (see :meth:`UsdCacheWriter.write`); returns the
        checked times as float64."""
        return self.apply(layer, self.prepare(times, points, normals, velocities,
                                              raw=isinstance(layer, CrateSamples)))

    def write_chunks(self, layer: Sink, chunks: "Iterable[SkinnedFrames]",
                     check: "Callable[[SkinnedFrames], None] | None" = None,
                     checked: bool = False,
                     executor: ThreadPoolExecutor | None = None) -> tuple[float, float]:
        """Write every :class:`dqskin.scene.SkinnedFrames` of the iterable ``chunks`` to
        ``layer``, pipelined: chunk ``k + 1`` is checked (``check(frames)``, then
        :meth:`prepare`) on a helper thread while chunk ``k``'s samples are set here (NumPy and
        the copies into Vt arrays release the GIL; setting samples in an Sdf layer does not,
        writing them to a crate file does). ``checked``: ``check`` raises for every NaN or
        infinite value (:func:`dqskin.validation.check_skinned`), so :meth:`prepare` does not
        look again.
        ``executor``: a one-thread executor for the helper (a caller writing many layers passes
        its own: starting a thread per layer costs a GIL hand-over); by default one is made.
        Returns the ``(min, max)`` time written (``(inf, -inf)`` for no chunk)."""
        raw = isinstance(layer, CrateSamples)

        def prep(res: "SkinnedFrames") -> Prepared:
            if check is not None:
                check(res)
            return self.prepare(res.times, res.points, res.normals, res.velocities,
                                checked=checked and check is not None, raw=raw)

        lo, hi = np.inf, -np.inf
        with contextlib.ExitStack() as stack:
            ex = executor or stack.enter_context(
                ThreadPoolExecutor(max_workers=1, thread_name_prefix="dqskin-usd-values"))
            queued = []  # the preparations submitted and not applied: at most two
            try:
                for res in chunks:
                    for name in set(res.points) & set(self.meshes):  # targets made here only
                        self._pad(name)
                    queued.append(ex.submit(prep, res))
                    if len(queued) == 2:
                        t = self.apply(layer, queued[0].result())
                        queued.pop(0)
                        lo, hi = min(lo, t.min()), max(hi, t.max())
                while queued:
                    t = self.apply(layer, queued[0].result())
                    queued.pop(0)
                    lo, hi = min(lo, t.min()), max(hi, t.max())
            finally:
                for f in queued:  # on an error: none left running for a shared executor
                    if not f.cancel():
                        wait([f])
        return lo, hi


class UsdCacheWriter(CommitOnSuccess):
    """Incremental USD point-cache writer: open once, :meth:`write` chunks of frames, :meth:`close`.

    Use as a context manager; on an exception nothing is written. A ``.usdc``/``.usd`` cache is
    written as it goes: on the first :meth:`write` the flattened, unbound copy of the source
    (:class:`CacheLayer`, with the spec of every value that chunk holds) is exported once, and
    every chunk's samples are streamed after it into the temporary file
    (:class:`~.crate.CrateSamples` with that ``base``): memory holds the copy of the source but
    no sample. Every later chunk must hold the same meshes and values as the first. A ``.usda``
    layer keeps every sample in memory until it is written. (For clips too long for one file,
    see :mod:`dqskin.writers.usd_clips`.)

    Parameters
    ----------
    scene : Scene
        What :func:`dqskin.readers.usd.load_usd` returned; its metadata (``time_codes_per_second``,
        ``up_axis``, ``meters_per_unit``) is written and its meshes' rest data checks the shapes.
    out_path : str or os.PathLike
        ``.usda``, ``.usdc`` or ``.usd``. Written atomically: into a temporary file in a private
        folder beside it (from the first :meth:`write` for crate outputs; by :meth:`close` for
        ``.usda``), moved into place by :meth:`close` (``os.replace``, or ``os.link`` without
        ``overwrite``). Must not be the source file or any layer it reads.
    source_path : str or os.PathLike, optional
        The stage to copy; ``scene.path`` by default.
    dropped : sequence of str
        Skinned prims left out of the bake, deactivated (:class:`CacheLayer`).
    options : dqskin.SkinOptions, optional
        The options that produced the points: the skinned prims without points (``Sphere``,
        ``Cube``, ...) are skinned with them (``method``: None uses each prim's own; ``interp``,
        ``sign_reference``, ``device``) and baked as ``xformOp:transform`` samples as
        ``UsdSkel.BakeSkinning`` does. Default: :class:`~dqskin.options.SkinOptions` defaults.
    overwrite : bool
        Replace an existing ``out_path`` (the last writer wins). False claims it exclusively:
        :meth:`close` raises FileExistsError if it exists by then (another run finished first).
    final : bool
        The run's last output (:class:`~.atomic.atomic_path`): an interrupt once it is in place
        is ignored.
    expected_bytes : int, optional
        About how many bytes of samples the cache will hold: a ``.usdc``/``.usd`` cache that
        fits what the system buffers without slowing its writer is written through the page
        cache, a larger one (or of unknown size) past it (:func:`dqskin.files.direct.pays`).

    As a context manager the writer claims its temporary folder on entry
    (``.STEM.XXXXXXXX/`` beside ``out_path``, :mod:`.atomic`) and removes it on an exception or
    interrupt.
    """

    def __init__(self, scene: "Scene", out_path: str | os.PathLike,
                 options: SkinOptions | None = None, *,
                 source_path: str | os.PathLike | None = None, overwrite: bool = True,
                 final: bool = False, dropped: "Sequence[str]" = (),
                 expected_bytes: int | None = None) -> None:
        self.expected_bytes = expected_bytes
        self.cache = CacheLayer(scene, out_path, source_path=source_path, dropped=dropped)
        self.scene, self.out, self.src = scene, self.cache.out, self.cache.src
        self.layer = self.cache.layer
        self.samples = SampleWriter(scene, self.cache.target, self.cache.rigid,
                                    SkinOptions() if options is None else options)
        self._t_min, self._t_max = np.inf, -np.inf
        self._claim = atomic_path(self.out, overwrite=overwrite, final=final)
        self.target = Path(self.out)
        # the layer or CrateSamples samples go to, chosen by the first chunk
        self._sink: Sink | None = None

    def __enter__(self) -> "UsdCacheWriter":
        self._claim.open()
        return self

    def commit(self) -> str:
        """:meth:`close` (the context manager's end without an exception)."""
        return self.close()

    def discard(self) -> None:
        """Nothing written: the temporary file removed (the context manager's end on an
        exception)."""
        if isinstance(self._sink, CrateSamples):
            self._sink.abort()
        self._claim.discard()

    def _sink_for(self, first: "SkinnedFrames | SimpleNamespace") -> Sink:
        """Where samples go (chosen once, from the first chunk ``first``): the layer for
        ``.usda``; else a :class:`~.crate.CrateSamples` in the claimed temporary file over the
        layer exported once with the spec of every value ``first`` holds (and of every rigid
        prim's transform). A crate file this writer cannot extend (usd-core wrote a version
        older than 0.7.0: ``USD_WRITE_NEW_USDC_FILES_AS_VERSION``) keeps the layer."""
        if self._sink is not None:
            return self._sink
        self._sink = self.layer
        if Path(self.out).suffix.lower() not in (".usdc", ".usd"):
            return self._sink
        meshes, target = self.samples.meshes, self.cache.target
        for what, names in (("points", first.points), ("normals", first.normals or {}),
                            ("velocities", first.velocities or {})):
            for name in names:
                mesh = meshes.get(name)
                if mesh is None or (what == "normals" and mesh.normals is None):
                    continue  # refused by SampleWriter.prepare, naming it
                target(name, what)
                if what == "points":
                    target(name, "extent")
        for r in self.cache.rigid:
            target(r.name, "xformOp:transform")
        t = np.atleast_1d(np.asarray(first.times, np.float64))
        if t.size and np.all(np.isfinite(t)):
            self.cache.set_metadata(t.min(), t.max())  # the range is replaced by close()
        tmp = self._claim.open()
        base = tmp.with_name(tmp.name + ".base.usdc")  # never the output's own name
        export_layer(self.layer, self._claim, tmp=base)
        try:
            self._sink = CrateSamples(tmp, self.scene.time_codes_per_second, base=base,
                                      direct=direct_pays(self.expected_bytes))
        except UnsupportedCrate:  # a usd-core writing another crate version: through Sdf
            pass
        finally:
            base.unlink(missing_ok=True)
        if isinstance(self._sink, CrateSamples):
            self.samples.target = self._frozen_target(dict(self.cache.targets))
        return self._sink

    def _frozen_target(self, targets: dict[tuple[str, str], Target]) -> TargetLookup:
        """The target lookup once the copy is exported: only what it declares."""
        def target(name: str, what: str) -> Target:
            try:
                return targets[name, what]
            except KeyError:
                raise InputError(f"{self.out}: {name}: {what} was not in the first chunk; a "
                                 ".usdc/.usd cache takes the meshes and values of its first "
                                 "chunk in every later one (.usda takes any)") from None
        return target

    def write(self, times: npt.ArrayLike, points: Frames, normals: Frames | None = None,
              velocities: Frames | None = None) -> None:
        """Add samples for ``times``.

        Parameters
        ----------
        times : (F,) float
            USD time codes of these frames.
        points : dict str → (F, V, 3) float
            Per mesh (prim path, ``Mesh.name``): points in the prim's own space, as
            :meth:`Scene.skin` returns them. Meshes left out keep their rest points (unbound).
        normals : dict str → (F, N, 3) float, optional
            Skinned normals, ``N`` = the mesh's rest normal count; written to the attribute the
            normals were read from (``primvars:normals`` loses its ``:indices``, the values being
            flattened), keeping its interpolation.
        velocities : dict str → (F, V, 3) float, optional
            Point velocities in prim-space units per second, written to ``velocities``.
        """
        sink = self._sink_for(SimpleNamespace(times=times, points=points, normals=normals,
                                              velocities=velocities))
        t = self.samples.write(sink, times, points, normals, velocities)
        self._t_min, self._t_max = min(self._t_min, t.min()), max(self._t_max, t.max())

    def write_chunks(self, chunks: "Iterable[SkinnedFrames]",
                     check: "Callable[[SkinnedFrames], None] | None" = None,
                     checked: bool = False) -> None:
        """:meth:`write` every :class:`dqskin.scene.SkinnedFrames` of ``chunks``, checking and
        converting the next on a helper thread (:meth:`SampleWriter.write_chunks`)."""
        rest = iter(chunks)
        first = next(rest, None)
        if first is None:
            return
        sink = self._sink_for(first)
        lo, hi = self.samples.write_chunks(sink, itertools.chain([first], rest), check,
                                           checked)
        self._t_min, self._t_max = min(self._t_min, lo), max(self._t_max, hi)

    def close(self) -> str:
        """Set the stage metadata and write the file atomically. Returns ``out_path``."""
        claim = self._claim
        try:
            if not np.isfinite(self._t_min):
                raise InputError(f"{self.out}: no frames were written")
            if isinstance(self._sink, CrateSamples):
                self._sink.close(self._t_min, self._t_max)
            else:
                self.cache.set_metadata(self._t_min, self._t_max)
                export_layer(self.layer, claim)
        except BaseException:
            self.discard()
            raise
        claim.commit()
        return self.out


def write_usd_cache(scene: "Scene", out_path: str | os.PathLike, times: npt.ArrayLike,
                    points: Frames, normals: Frames | None = None, *,
                    velocities: Frames | None = None, options: SkinOptions | None = None,
                    source_path: str | os.PathLike | None = None, overwrite: bool = True) -> str:
    """Write skinned points (and normals, velocities) for all ``times`` as a new USD stage.

    One :class:`UsdCacheWriter` chunk; see it for the parameters.

    Returns
    -------
    str
        ``out_path``.

    Raises
    ------
    ValueError
        Unsupported extension, output equal to an input file, unknown mesh names, or arrays
        whose shape disagrees with ``times`` and the mesh.
    """
    with UsdCacheWriter(scene, out_path, options, source_path=source_path,
                        overwrite=overwrite) as writer:
        writer.write(times, points, normals, velocities)
    return writer.out
