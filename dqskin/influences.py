"""Per-vertex joint influences: validated once and laid out once for every kernel that blends them
(skinning, velocities), as UsdSkel keeps every influence operation in one group
(``UsdSkelSortInfluences``, ``UsdSkelResizeInfluences``).

:class:`Influences` is the one home of the layout: validation (shapes, dtypes, finite
non-negative weights, the joint-index range: :func:`check_joint_range`), the weight sort
(:func:`weight_order`), the padding to groups of four, the concatenation of many meshes
(:meth:`Influences.concatenate`) and the upload to the kernels' one argument,
:class:`dqskin.kernels.layout.InfluenceLayout` (:meth:`Influences.layout`)."""

from collections.abc import Sequence

import numpy as np
import numpy.typing as npt
import warp as wp

from ._warp import Device
from .errors import InputError
from .kernels import buffers as KB
from .kernels import layout as KL
from .kernels.grid import beside
from .shapes import as_real
from .validation import nonnegative_max

__all__ = ["Influences", "check_influences", "check_joint_range", "weight_order"]


_BESIDE_MIN = 1 << 18
"""Influences from which indices and weights are checked on two threads at once."""


def _validated(joint_indices, joint_weights, vertex_count=None, joint_count=None, values=True):
    """:func:`check_influences` without its int64 copy: ``(indices (V, K) in their integer dtype,
    weights (V, K) float32, largest index or -1)``; one pass over each array
    (:func:`~dqskin.validation.nonnegative_max`), the two at once when large; ``values=False``:
    shapes and dtypes only (the largest index then reads -1)."""
    idx = as_real("joint_indices", joint_indices)
    wts = as_real("joint_weights", joint_weights, np.float32)
    if idx.ndim == 1:
        idx, wts = idx[:, None], wts[:, None]
    if idx.ndim != 2 or wts.shape != idx.shape or (vertex_count is not None
                                                   and idx.shape[0] != vertex_count):
        want = "(V, K)" if vertex_count is None else f"({vertex_count}, K)"
        raise InputError(f"joint_indices {idx.shape} and joint_weights {wts.shape} must both be "
                         f"{want}")
    if not np.issubdtype(idx.dtype, np.integer):
        raise InputError(f"joint_indices: expected integers, got {idx.dtype}")
    if not idx.size or not values:
        return idx, wts, -1
    if idx.size >= _BESIDE_MIN:  # the weights on another core
        weights_ok, largest = beside(lambda: nonnegative_max(wts) is not None,
                                     lambda: nonnegative_max(idx))
    else:
        weights_ok, largest = None, nonnegative_max(idx)
    if largest is None:
        raise InputError(f"joint_indices: negative index {int(idx.min())}")
    hi = int(largest)
    if joint_count is not None:
        check_joint_range(hi, joint_count)
    if weights_ok is None:
        weights_ok = nonnegative_max(wts) is not None
    if not weights_ok:  # then look closer (-0.0 is fine)
        wlo, whi = wts.min(), wts.max()  # NaN propagates; no temporaries
        if not (np.isfinite(wlo) and np.isfinite(whi)):
            raise InputError("joint_weights: NaN or infinite weight")
        if wlo < 0:
            raise InputError(f"joint_weights: negative weight {float(wlo)}")
    return idx, wts, hi


def check_joint_range(largest: int, joint_count: int, joints: str = "joints",
                      where: str = "joint_indices") -> None:
    """The one joint-index range check: InputError ``"<where>: index <largest> out of range for
    <joint_count> <joints>"`` unless ``largest < joint_count`` (indices already known
    non-negative)."""
    if largest >= joint_count:
        raise InputError(f"{where}: index {int(largest)} out of range for {joint_count} {joints}")


def weight_order(weights: npt.ArrayLike) -> np.ndarray:
    """``(V, K)`` int: each row's slots by descending weight, stable (the first slot first on
    ties): the order of the kernels' layout (slot 0 the DQS pivot, as UsdSkel)."""
    return np.argsort(-np.asarray(weights), axis=1, kind="stable")


def check_influences(joint_indices: npt.ArrayLike, joint_weights: npt.ArrayLike,
                     vertex_count: int | None = None,
                     joint_count: int | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Validate per-vertex influences; returns ``(indices (V, K) int64, weights (V, K) float32)``.

    1-D inputs are one influence per vertex. Raises InputError naming ``joint_indices`` or
    ``joint_weights`` for mismatched shapes, non-integer or out-of-range indices (``0 <= index <
    joint_count`` when given), and NaN, infinite or negative weights.
    """
    idx, wts, _ = _validated(joint_indices, joint_weights, vertex_count, joint_count)
    return idx.astype(np.int64), wts


class Influences:
    """A mesh's influences, validated, and their layout for the kernels.

    Each vertex's ``K`` influences are sorted by descending weight (:func:`weight_order`), so
    slot 0 is the antipodality pivot of DQS (the largest weight, as UsdSkel), and zero-padded
    (joint 0, weight 0) to ``C = max(1, ceil(K / 4))`` groups of four. ``K = 0`` (no
    influences) is allowed: LBS gives the origin, DQS leaves points where they are (a zero
    blend), as UsdSkel does; ``V = 0`` gives empty results.

    Parameters
    ----------
    joint_indices : (V, K) int
        Joint of each influence, ``0 <= index``. Any ``K`` (1, 4, 8, ...); pad with weight 0.
    joint_weights : (V, K) float
        Finite and non-negative; used as given (never renormalized, as UsdSkel).
    vertex_count : int, optional
        Required V.
    check_values : bool
        False: shapes and dtypes only; the values are checked by a kernel (a one-shot call's
        packet launch) or by :meth:`check_values`.

    Raises InputError (a ValueError) naming ``joint_indices`` or ``joint_weights`` for
    mismatched shapes, non-integer or negative indices, and NaN, infinite or negative weights.

    Attributes
    ----------
    indices : (V, C, 4) int32
        The sorted, padded host layout (computed when first read).
    weights : (V, C, 4) float32
    order : (V, K) int
        The sort: slot ``k`` of a vertex holds its input influence ``order[v, k]``.
    vertex_count, influence_count, group_count : int
        V, K and C.
    joint_count_min : int
        Joints the skinning transforms must at least have (largest index + 1; 0 until
        :meth:`check_values` with ``check_values=False``).
    """

    def __init__(self, joint_indices: npt.ArrayLike, joint_weights: npt.ArrayLike, *,
                 vertex_count: int | None = None, check_values: bool = True) -> None:
        idx, wts, hi = _validated(joint_indices, joint_weights, vertex_count,
                                  values=check_values)
        self.vertex_count, self.influence_count = idx.shape
        self.group_count = max(1, -(-self.influence_count // 4))  # K = 0: one group of zeros
        self._input = idx, wts  # indices in the caller's integer dtype (no copy)
        # (order, indices, weights) on the host, computed when first asked
        self._sorted: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None
        # (device, order) → (indices, weights) flat device arrays
        self._uploads: dict[tuple[str, str], tuple[wp.array, wp.array]] = {}
        self.joint_count_min = hi + 1

    @classmethod
    def concatenate(cls, parts: Sequence[tuple[npt.ArrayLike, npt.ArrayLike]],
                    joint_offsets: Sequence[int], joint_counts: Sequence[int],
                    names: Sequence[str] | None = None) -> "tuple[Influences, list[slice]]":
        """Many meshes' influences on one vertex axis and one joint axis.

        Parameters
        ----------
        parts : sequence of ((Vm, Km) int, (Vm, Km) float)
            Each mesh's joint indices and weights (1-D: one influence per vertex).
        joint_offsets : sequence of int
            Where each mesh's joints start on the concatenated joint axis (added to its indices).
        joint_counts : sequence of int
            Each mesh's joints: its indices must stay below (:func:`check_joint_range`).
        names : sequence of str, optional
            Each mesh's name, for the errors.

        Returns
        -------
        (Influences, list of slice)
            ``K`` the largest ``Km``, each mesh zero-padded to it (joint 0 of the concatenated
            axis, weight 0); each mesh's vertices on the concatenated axis. Raises InputError
            naming the mesh for an index outside its joints.
        """
        arrays = [(np.asarray(i), np.asarray(w)) for i, w in parts]
        counts = [int(i.shape[0]) if i.ndim else 0 for i, _ in arrays]
        starts = np.concatenate([[0], np.cumsum(counts, dtype=np.int64)]).astype(np.int64)
        slices = [slice(int(a), int(b)) for a, b in zip(starts[:-1], starts[1:])]
        K = max([w.shape[1] if w.ndim == 2 else 1 for _, w in arrays] + [0])
        V = int(starts[-1])
        idx = np.zeros((V, K), np.int32)
        wts = np.zeros((V, K), np.float32)
        names = names or [f"mesh {n}" for n in range(len(arrays))]
        for (i, w), sl, off, count, name in zip(arrays, slices, joint_offsets, joint_counts,
                                                names):
            i = i.reshape(sl.stop - sl.start, -1)
            if i.size:
                lo, hi = int(i.min()), int(i.max())
                if lo < 0:
                    raise InputError(f"{name}: joint_indices: negative index {lo}")
                check_joint_range(hi, count, "joints of its skeleton", f"{name}: joint_indices")
            idx[sl, :i.shape[1]] = i + off
            wts[sl, :i.shape[1]] = np.asarray(w, np.float32).reshape(i.shape)
        return cls(idx, wts, vertex_count=V), slices

    def check_values(self) -> None:
        """Check the values of indices and weights (``check_values=False`` left them to a
        kernel): InputError as the constructor raises."""
        self.joint_count_min = _validated(*self._input)[2] + 1

    def _host_layout(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        if self._sorted is None:
            idx, wts = self._input
            order = weight_order(wts)
            self._sorted = (order,) + self._groups(np.take_along_axis(idx, order, 1),
                                                   np.take_along_axis(wts, order, 1))
        return self._sorted

    @property
    def order(self) -> np.ndarray:
        return self._host_layout()[0]

    @property
    def indices(self) -> np.ndarray:
        return self._host_layout()[1]

    @property
    def weights(self) -> np.ndarray:
        return self._host_layout()[2]

    @property
    def given(self) -> tuple[np.ndarray, np.ndarray]:
        """``(indices (V, K) int64, weights (V, K) float32)`` as given (validated, unsorted)."""
        return self._input[0].astype(np.int64), self._input[1]

    def _groups(self, idx: np.ndarray, wts: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(V, K) → ``(indices (V, C, 4) int32, weights (V, C, 4) float32)``, zero-padded."""
        pad = 4 * self.group_count - idx.shape[1]
        V = self.vertex_count
        return (np.pad(idx, ((0, 0), (0, pad))).astype(np.int32).reshape(V, self.group_count, 4),
                np.pad(wts, ((0, 0), (0, pad))).reshape(V, self.group_count, 4))

    def check_joint_count(self, joint_count: int) -> None:
        """InputError when ``joint_count`` skinning transforms cannot cover the indices (the
        zero-weight padding points at joint 0, so points need at least one joint)."""
        if self.joint_count_min:
            check_joint_range(self.joint_count_min - 1, joint_count, "skinning transforms")
        if joint_count == 0 and self.vertex_count:
            raise InputError("skinning_transforms: no joints to skin the points with")

    def layout(self, device: Device, order: str = "weight", *, blend: wp.array, centers: wp.array,
               running_sum: bool = False, copy: bool = True) -> KL.InfluenceLayout:
        """The kernels' :class:`~dqskin.kernels.layout.InfluenceLayout` on ``device``.

        Parameters
        ----------
        order : {"weight", "input"}
            "weight": the sorted layout above; "input": the influences in the order they were
            given, zero-padded the same way (for the running-sum sign rule, which depends on the
            order, and for one-shot calls, whose kernels then search the pivot). Uploaded once
            per device and order.
        blend : (V,) or (0,) wp.array of float32
            DQS fraction of the blend method (empty when absent).
        centers : (V,) or (0,) wp.array of wp.vec4
            Centers of rotation of the COR method (empty when absent).
        running_sum : bool
            The running-sum sign rule (needs ``order="input"``).
        copy : bool
            False: on the CPU, ``"input"`` reads the caller's (V, 4k) int32 and float32 arrays in
            place when their layout allows (no pass over them at all).
        """
        if order not in ("weight", "input"):
            raise InputError(f'order must be "weight" or "input", got {order!r}')
        key = (str(device), order)
        arrays = self._uploads.get(key)
        if arrays is None:
            arrays = self._uploads[key] = self._upload(device, order, copy)
        s = KL.InfluenceLayout()
        s.indices, s.weights = arrays
        s.groups = self.group_count
        s.blend, s.centers = blend, centers
        s.running_sum, s.unsorted = int(bool(running_sum)), int(order == "input")
        return s

    def _upload(self, device, order, copy):
        """``(indices (V·C,) wp.vec4i, weights (V·C,) wp.vec4)`` in ``order`` on ``device``."""
        if order == "weight" and self._sorted is None:  # sorted on the device (kernels.layout)
            return self._device_layout(device)
        if order == "weight":
            idx, wts = self.indices, self.weights
        else:
            idx, wts = self._input
            V, K = idx.shape
            alias = (not copy and wp.get_device(device).is_cpu and K and K % 4 == 0
                     and idx.dtype == np.int32 and idx.flags.c_contiguous
                     and wts.flags.c_contiguous)
            if alias:
                return (wp.array(idx.reshape(V * K // 4, 4), dtype=wp.vec4i, device=device,
                                 copy=False),
                        wp.array(wts.reshape(V * K // 4, 4), dtype=wp.vec4, device=device,
                                 copy=False))
            idx, wts = self._groups(idx, wts)
        n = self.vertex_count * self.group_count
        return (wp.array(idx.reshape(n, 4), dtype=wp.vec4i, device=device),
                wp.array(wts.reshape(n, 4), dtype=wp.vec4, device=device))

    def _device_layout(self, device):
        """The weight-sorted layout built by :mod:`dqskin.kernels.layout` from the (V, K) input:
        no host sort, gather or pad (several times the cost of skinning the points once)."""
        idx, wts = self._input
        n = self.vertex_count * self.group_count
        out = KB.empty(n, wp.vec4i, device), KB.empty(n, wp.vec4, device)
        if self.influence_count == 0:
            out[0].zero_()
            out[1].zero_()
            return out
        cpu = wp.get_device(device).is_cpu  # inputs read during the launch only: no copies
        KL.layout(joint_indices=wp.array(idx.astype(np.int32, copy=False), dtype=wp.int32,
                                         device=device, copy=not cpu),
                  joint_weights=wp.array(np.ascontiguousarray(wts, np.float32), dtype=wp.float32,
                                         device=device, copy=not cpu),
                  indices=out[0], weights=out[1], device=device)
        return out
