"""One validation for every command and output format: what ``dqskin info`` lists as problems is
exactly what ``dqskin skin`` (every writer) and the Python API refuse.

* :func:`check_transforms`: 4×4 joint transforms must be finite and representable in float32
  (the device precision); the error names the argument, frame and joint.
* :func:`check_skinned`: skinned results (points, normals, velocities) must be finite; the error
  names the mesh, what and the time.
* :func:`scene_problems`: every problem of a loaded scene at its times, as lines (``info``).
  ``skin`` meets the same checks chunk by chunk: joint transforms as
  :meth:`dqskin.Scene.local_transforms` samples them, results with :func:`check_skinned`.
* :func:`points_stay_finite`: a float64 bound that proves skinned points finite without
  skinning (``info`` then needs no device).
"""

from collections.abc import Callable, Iterable, Sequence
from typing import TYPE_CHECKING, cast

import numpy as np
import numpy.typing as npt

from .errors import InputError
from .shapes import as_real

if TYPE_CHECKING:
    from ._warp import Device
    from .pipeline import SkinnedFrames
    from .scene import Scene

__all__ = ["FLOAT32_MAX", "check_finite", "check_points", "check_skinned", "check_transforms",
           "location", "nonnegative_max", "points_stay_finite", "scene_problems", "within_float32"]

FLOAT32_MAX = float(np.finfo(np.float32).max)
"""Largest magnitude a value may have to survive the device's float32."""


def within_float32(a: np.ndarray) -> str | None:
    """None when every value of the array is finite and within float32 range, else what is wrong
    ("NaN or infinite", "beyond float32 range"); one pass without temporaries in the common case:
    a contiguous float32 array's sum, or a float64 array's sum of squares, is finite (within
    ``FLOAT32_MAX²``) only then; otherwise, or when it overflows, min and max decide. No BLAS
    for large arrays: its threads would keep spinning beside the skinning launch."""
    if a.dtype.kind != "f" or a.size == 0:
        return None
    kind = a.dtype.char
    if a.flags.c_contiguous and (kind == "d" or kind == "f"):  # float64, float32
        flat = a.reshape(-1)
        if kind == "d" and flat.size <= _BLAS_ONE_THREAD:  # overflows only beyond float32
            ok = float(flat @ flat) <= _SQUARES_MAX
        else:
            with np.errstate(over="ignore", invalid="ignore"):  # an overflow: look closer below
                ok = (bool(np.isfinite(np.add.reduce(flat))) if kind == "f" else
                      float(np.einsum("i,i->", flat, flat)) <= _SQUARES_MAX)
        if ok:
            return None
    lo, hi = a.min(), a.max()
    if not (np.isfinite(lo) and np.isfinite(hi)):
        return "NaN or infinite"
    return None if max(hi, -lo) <= FLOAT32_MAX else "beyond float32 range"


_BLAS_ONE_THREAD = 8192
"""Lengths up to which a BLAS dot product runs on the calling thread."""

_SQUARES_MAX = FLOAT32_MAX ** 2  # exact in float64 (a 24-bit mantissa squared)

_BITS = {np.dtype(np.int32): (np.uint32, 1 << 31), np.dtype(np.int64): (np.uint64, 1 << 63),
         np.dtype(np.float32): (np.uint32, 0x7F800000),
         np.dtype(np.float64): (np.uint64, 0x7FF0000000000000)}
"""Unsigned view of a dtype, and the bits from which a value is negative, infinite or NaN."""


def nonnegative_max(a: np.ndarray) -> np.generic | None:
    """The largest value of a non-empty array of numbers when every value is non-negative (and
    finite, for floats), else None (-0.0 included: look closer then). One pass over the bits of a
    contiguous int32/int64/float32/float64 array: as unsigned integers, non-negative finite
    values keep their order and a sign bit, inf or NaN lands above them all."""
    bits = _BITS.get(a.dtype)
    if bits is None or not a.flags.c_contiguous:
        lo, hi = a.min(), a.max()
        ok = lo >= 0 and (a.dtype.kind != "f" or np.isfinite(hi))  # NaN fails lo >= 0
        return hi if ok else None
    m = a.view(bits[0]).max()
    if m >= bits[1]:
        return None
    # a 0-d array indexed by () is a scalar (NumPy's stubs type it as an array)
    return cast(np.generic, np.array(m).view(a.dtype)[()])


def location(index: Sequence[int] | np.ndarray, lead: int, joint_names: Sequence[str] | None = None,
             times: Sequence[float] | np.ndarray | None = None) -> str:
    """"frame 3, joint 'Hips'" for an index into a (*batch, J, ...) array with ``lead`` batch
    axes ("time 12" with ``times``); a multi-axis batch index is written as a tuple, none is
    left out."""
    frame = tuple(int(i) for i in index[:lead])
    j = int(index[lead])
    joint = f"joint {joint_names[j]!r}" if joint_names is not None else f"joint {j}"
    if not frame:
        return joint
    if times is not None and len(frame) == 1:
        return f"time {float(times[frame[0]]):g}, {joint}"
    return f"frame {frame[0] if len(frame) == 1 else frame}, {joint}"


def check_finite(name: str, a: np.ndarray, lead: int, joint_names: Sequence[str] | None = None,
                 times: Sequence[float] | np.ndarray | None = None) -> None:
    """Raise InputError (a ValueError) unless every value of ``a`` (``lead`` batch axes, then
    joints, then components) is finite and fits float32, the device precision.

    The message names ``name``, the first offending frame (its batch index, or its time when
    ``times`` is given) and joint (by name when ``joint_names`` is given) and what is wrong, e.g.
    ``rotations: NaN at frame 3, joint 'Hips'``.
    """
    if a.size == 0:
        return
    hi, lo = np.max(a), np.min(a)  # two passes, no temporaries; NaN propagates
    if np.isfinite(hi) and np.isfinite(lo) and max(hi, -lo) <= FLOAT32_MAX:
        return  # the common case
    finite = np.isfinite(a)
    if not finite.all():
        index = np.argwhere(~finite)[0]
        what = "NaN" if np.isnan(a[tuple(index)]) else "infinite value"
        raise InputError(f"{name}: {what} at {location(index, lead, joint_names, times)}")
    if a.dtype.itemsize > 4:
        index = np.argwhere(np.abs(a) > FLOAT32_MAX)[0]
        raise InputError(f"{name}: {float(a[tuple(index)]):.6g} at "
                         f"{location(index, lead, joint_names, times)} overflows float32 "
                         f"(|x| > {FLOAT32_MAX:.4g})")


def check_points(where: str, points: np.ndarray) -> None:
    """Raise InputError (a ValueError) unless a mesh's (V, 3) rest ``points`` are finite, within
    float32 range and not all at one point (a mesh without extent); the message names ``where``
    (the file), the field and the first offending vertex."""
    if len(points) == 0:
        return
    bad = within_float32(points)
    if bad is not None:
        v = int(np.argmax(~(np.abs(points) <= FLOAT32_MAX).all(axis=-1)))
        raise InputError(f"{where}: vertices: {bad} at vertex {v} ({points[v].tolist()})")
    if np.all(points.max(0) == points.min(0)):
        raise InputError(f"{where}: vertices: all {len(points)} are at one point "
                         f"{points[0].tolist()} (a mesh without extent)")


def check_transforms(name: str, transforms: npt.ArrayLike, joint_names: Sequence[str] | None = None,
                     times: Sequence[float] | np.ndarray | None = None) -> np.ndarray:
    """Raise InputError (a ValueError) unless every entry of ``transforms`` (..., J, 4, 4) is
    real, finite and within float32 range (:func:`check_finite`, the leading axes are frames);
    returns them as float64."""
    x = as_real(name, transforms, np.float64)
    check_finite(name, x, max(x.ndim - 3, 0), joint_names, times)
    return x


def _finite_bases(arrays: "Iterable[npt.ArrayLike]") -> bool:
    """Whether every array of ``arrays`` is a view of a NumPy array of its dtype that the views
    cover at least three quarters of (so checking it costs little more than checking them) and
    that is all finite; False means only "not shown" (check them one by one)."""
    bases: dict[int, tuple[np.ndarray, int]] = {}
    for a in arrays:
        base = getattr(a, "base", None)
        if not (isinstance(a, np.ndarray) and isinstance(base, np.ndarray)
                and base.dtype == a.dtype):
            return False
        covered = bases.get(id(base), (base, 0))[1]
        bases[id(base)] = (base, covered + a.size)
    return all(4 * covered >= 3 * base.size and bool(np.isfinite(base).all())
               for base, covered in bases.values())


def check_skinned(path: str, result: "SkinnedFrames") -> None:
    """Raise InputError (a ValueError) if any array of a :class:`dqskin.scene.SkinnedFrames` is
    not finite (joint transforms too large for float32, or degenerate), naming the mesh, the
    array and the time. Arrays that are views of one larger array (the meshes of a batch) are
    checked through it at once when they cover most of it; mesh by mesh only when it is not all
    finite (to name the first bad one)."""
    for what in ("points", "normals", "velocities"):
        arrays = getattr(result, what)
        if _finite_bases(arrays.values()):
            continue
        for mesh, a in arrays.items():
            bad = ~np.isfinite(np.asarray(a)).all(axis=tuple(range(1, np.ndim(a))))
            if bad.any():
                t = float(result.times[int(np.argmax(bad))])
                raise InputError(f"{path}: {mesh}: skinned {what} are NaN or infinite at time "
                                 f"{t:g} (joint transforms out of float32 range?)")


def scene_problems(scene: "Scene", times: npt.ArrayLike | None = None, *, skin: bool = True,
                   device: "Device" = None,
                   before_skinning: Callable[[], None] | None = None) -> list[str]:
    """Every problem of ``scene`` at ``times`` (default its own): unusable bind transforms,
    non-finite or out-of-range animated joint transforms, and with ``skin`` non-finite skinned
    points (:meth:`dqskin.Scene.skin`'s defaults), skinned on ``device`` unless
    :func:`points_stay_finite` proves them finite; ``before_skinning`` is called first when they
    are skinned. Returns a list of one-line messages (empty when the scene can be skinned and
    written)."""
    t = scene.times if times is None else np.atleast_1d(np.asarray(times, dtype=np.float64))
    problems: list[str] = []
    local: dict[int, np.ndarray] = {}
    for s, skel in enumerate(scene.skeletons):
        try:
            skel.inverse_bind_transforms  # noqa: B018  (raises for a singular bind pose)
            # raises for NaN, infinite or out-of-range transforms
            local[s] = scene.local_transforms(t, s)
        except ValueError as exc:
            problems.append(str(exc))
    if (skin and local and scene.meshes and all(m.skeleton in local for m in scene.meshes)
            and not points_stay_finite(scene, t, local)):
        if before_skinning is not None:
            before_skinning()
        try:
            check_skinned(scene.path, scene.skin(t, device=device))
        except ValueError as exc:
            problems.append(str(exc))
    return problems


_PROVEN = 1.0e30
"""Largest bound :func:`points_stay_finite` accepts: 3.4·10⁸ times inside float32's limit, a
margin for the float32 arithmetic's rounding and for the small constant factors (sums of three
or four products) the bounds leave out."""


def _fk_bound(parents: np.ndarray, local: np.ndarray) -> float:
    """A bound on the values forward kinematics computes for (F, J, 4, 4) ``local`` transforms
    (parents first): each world transform is its parent's times its local one, so its entries
    and the composition's intermediates (rotations, residuals, translations) are within a small
    factor of ``(1 + |parent|)·(1 + |local|)`` (the largest entries of the float64 products);
    inf when they leave float64."""
    with np.errstate(all="ignore"):
        world = np.empty_like(local)
        for j, p in enumerate(parents):
            world[:, j] = local[:, j] if p < 0 else world[:, p] @ local[:, j]
        big_world = float(np.max(np.abs(world), initial=0.0))
        big_local = float(np.max(np.abs(local), initial=0.0))
    bound = 4.0 * (1.0 + big_world) * (1.0 + big_local)
    return bound if np.isfinite(bound) else np.inf


def points_stay_finite(scene: "Scene", times: np.ndarray, local: dict[int, np.ndarray]) -> bool:
    """Whether a float64 bound proves every skinned point of ``scene`` at ``times`` finite in
    float32, without skinning: :meth:`dqskin.Scene.skin` with its default options, any method or
    sign rule. False when the bound cannot tell (the points must be skinned to know).

    For each mesh the bound takes the largest magnitudes: forward kinematics (:func:`_fk_bound`)
    and the inverse bind transforms give the skinning transforms' ``A``; the geom-bind transform
    and the rest points the bind-space points ``X``; the weight sums ``W``; the mesh's output
    transform ``O``. LBS gives at most ``4·W·(1 + A)·(1 + X)``; DQS (the residual blend, then the
    normalized blend, whose ``2/|r|²`` the kernels clamp at ``2·10³⁰``) at most
    ``10¹⁶·(1 + W)·(1 + A)·(1 + X)``, the blend and centers of rotation as much. A mesh with a
    deformer (blend shapes, animated points) is not bounded.

    Parameters
    ----------
    scene : dqskin.Scene
    times : (F,) float64
    local : dict of int to (F, J, 4, 4) float64
        Each skeleton's local transforms at ``times``, checked
        (:meth:`dqskin.Scene.local_transforms`).
    """
    from .spaces import space_track
    joints: dict[int, float] = {}
    with np.errstate(all="ignore"):
        for m in scene.meshes:
            if m.deformer is not None:
                return False
            s = m.skeleton
            if s not in joints:
                skel = scene.skeletons[s]
                ib = float(np.max(np.abs(skel.inverse_bind_transforms.astype(np.float32)),
                                  initial=0.0))
                fk = _fk_bound(np.asarray(skel.parents), local[s])
                joints[s] = 4.0 * (1.0 + fk) * (1.0 + ib)  # bind-relative: world · bind⁻¹
            track = space_track(m, "local")
            out = 0.0 if track is None else float(np.max(np.abs(track.at(times)), initial=0.0))
            a = 4.0 * (1.0 + out) * (1.0 + joints[s])  # an output transform folded in
            g = float(np.max(np.abs(m.geom_bind_transform), initial=0.0))
            x = 4.0 * (1.0 + g) * (1.0 + float(np.max(np.abs(m.points), initial=0.0)))
            w = float(np.max(np.sum(np.abs(m.joint_weights, dtype=np.float64), axis=1),
                             initial=0.0))
            bound = 4.0 * (1.0 + out) * (1.0 + 1.0e16 * (1.0 + w) * (1.0 + a) * (1.0 + x))
            if not (joints[s] <= _PROVEN and bound <= _PROVEN):  # (NaN: not proven)
                return False
    return True
