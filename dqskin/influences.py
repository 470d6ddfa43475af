"""Per-vertex joint influences: validated once and laid out once for every kernel that blends them
(skinning, velocities), as UsdSkel sorts influences once in ``UsdSkelSortInfluences``."""

import numpy as np
import warp as wp

from .errors import InputError
from .kernels import buffers as KB
from .kernels import layout as KL
from .kernels.grid import beside
from .shapes import as_real
from .validation import nonnegative_max

__all__ = ["Influences", "check_influences"]


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
        weights_ok, hi = beside(lambda: nonnegative_max(wts) is not None,
                                lambda: nonnegative_max(idx))
    else:
        weights_ok, hi = None, nonnegative_max(idx)
    if hi is None:
        raise InputError(f"joint_indices: negative index {int(idx.min())}")
    hi = int(hi)
    if joint_count is not None and hi >= joint_count:
        raise InputError(f"joint_indices: index {hi} out of range for {joint_count} joints")
    if weights_ok is None:
        weights_ok = nonnegative_max(wts) is not None
    if not weights_ok:  # then look closer (-0.0 is fine)
        wlo, whi = wts.min(), wts.max()  # NaN propagates; no temporaries
        if not (np.isfinite(wlo) and np.isfinite(whi)):
            raise InputError("joint_weights: NaN or infinite weight")
        if wlo < 0:
            raise InputError(f"joint_weights: negative weight {float(wlo)}")
    return idx, wts, hi


def check_influences(joint_indices, joint_weights, vertex_count=None, joint_count=None):
    """Validate per-vertex influences; returns ``(indices (V, K) int64, weights (V, K) float32)``.

    1-D inputs are one influence per vertex. Raises ValueError naming ``joint_indices`` or
    ``joint_weights`` for mismatched shapes, non-integer or out-of-range indices (``0 <= index <
    joint_count`` when given), and NaN, infinite or negative weights.
    """
    idx, wts, _ = _validated(joint_indices, joint_weights, vertex_count, joint_count)
    return idx.astype(np.int64), wts


class Influences:
    """A mesh's influences in the kernels' layout.

    Each vertex's ``K`` influences are sorted by descending weight (stable: first on ties), so slot
    0 is the antipodality pivot of DQS (the largest weight, as UsdSkel), and zero-padded to
    ``C = max(1, ceil(K / 4))`` groups of four. ``K = 0`` (no influences) is allowed: LBS gives
    the origin, DQS leaves points where they are (a zero blend), as UsdSkel does; ``V = 0`` gives
    empty results.

    Parameters
    ----------
    joint_indices : (V, K) int
        Joint of each influence, ``0 <= index``. Any ``K`` (1, 4, 8, ...); pad with weight 0.
    joint_weights : (V, K) float
        Finite and non-negative; used as given (never renormalized, as UsdSkel).
    vertex_count : int, optional
        Required V.

    Attributes
    ----------
    indices : (V, C, 4) int32
    weights : (V, C, 4) float32
    order : (V, K) int
        The sort: slot ``k`` of a vertex holds its input influence ``order[v, k]``.
    vertex_count, influence_count : int
        V and K.
    joint_count_min : int
        Joints the skinning transforms must at least have (largest index + 1; 0 until
        :meth:`check_values` with ``check_values=False``).
    check_values : bool
        False: shapes and dtypes only; the values are checked by a kernel (a one-shot call's
        packet launch) or by :meth:`check_values`.
    """

    def __init__(self, joint_indices, joint_weights, *, vertex_count=None, check_values=True):
        idx, wts, hi = _validated(joint_indices, joint_weights, vertex_count,
                                  values=check_values)
        self.vertex_count, self.influence_count = idx.shape
        self._input = idx, wts  # indices in the caller's integer dtype (no copy)
        self._sorted = None  # (order, indices, weights) on the host, computed when first asked
        self.joint_count_min = hi + 1

    def check_values(self):
        """Check the values of indices and weights (``check_values=False`` left them to a
        kernel): ValueError as the constructor raises."""
        self.joint_count_min = _validated(*self._input)[2] + 1

    def _host_layout(self):
        if self._sorted is None:
            idx, wts = self._input
            order = np.argsort(-wts, axis=1, kind="stable")
            self._sorted = (order,) + self._groups(np.take_along_axis(idx, order, 1),
                                                   np.take_along_axis(wts, order, 1))
        return self._sorted

    order = property(lambda self: self._host_layout()[0])
    indices = property(lambda self: self._host_layout()[1])
    weights = property(lambda self: self._host_layout()[2])

    @property
    def given(self):
        """``(indices (V, K) int64, weights (V, K) float32)`` as given (validated, unsorted)."""
        return self._input[0].astype(np.int64), self._input[1]

    def _groups(self, idx, wts):
        groups = max(1, -(-idx.shape[1] // 4))  # K = 0: one group of zero weights
        pad = 4 * groups - idx.shape[1]
        V = self.vertex_count
        return (np.pad(idx, ((0, 0), (0, pad))).astype(np.int32).reshape(V, groups, 4),
                np.pad(wts, ((0, 0), (0, pad))).reshape(V, groups, 4))

    def check_joint_count(self, joint_count):
        """ValueError when ``joint_count`` skinning transforms cannot cover the indices (the
        zero-weight padding points at joint 0, so points need at least one joint)."""
        if joint_count < self.joint_count_min:
            raise InputError(f"joint_indices: index {self.joint_count_min - 1} out of range for "
                             f"{joint_count} skinning transforms")
        if joint_count == 0 and self.vertex_count:
            raise InputError("skinning_transforms: no joints to skin the points with")

    def upload(self, device, order="weight", copy=True):
        """``{"indices": (V, C) wp.vec4i, "weights": (V, C) wp.vec4}`` on ``device``.

        ``order="weight"``: the sorted layout above; ``"input"``: the influences in the order they
        were given, zero-padded the same way (for the running-sum sign rule, which depends on the
        order, and for one-shot calls, whose kernels then search the pivot). ``copy=False``: on
        the CPU, ``"input"`` reads the caller's (V, 4k) int32 and float32 arrays in place when
        their layout allows (no pass over them at all)."""
        if order == "weight" and self._sorted is None:  # sorted on the device (kernels.layout)
            return self._device_layout(device)
        if order == "weight":
            idx, wts = self.indices, self.weights
        elif order == "input":
            idx, wts = self._input
            V, K = idx.shape
            alias = (not copy and wp.get_device(device).is_cpu and K and K % 4 == 0
                     and idx.dtype == np.int32 and idx.flags.c_contiguous
                     and wts.flags.c_contiguous)
            if alias:
                return {"indices": wp.array(idx.reshape(V, K // 4, 4), dtype=wp.vec4i,
                                            device=device, copy=False),
                        "weights": wp.array(wts.reshape(V, K // 4, 4), dtype=wp.vec4,
                                            device=device, copy=False)}
            idx, wts = self._groups(idx, wts)
        else:
            raise InputError(f'order must be "weight" or "input", got {order!r}')
        return {"indices": wp.array(idx, dtype=wp.vec4i, device=device),
                "weights": wp.array(wts, dtype=wp.vec4, device=device)}

    def _device_layout(self, device):
        """The weight-sorted layout built by :mod:`dqskin.kernels.layout` from the (V, K) input:
        no host sort, gather or pad (several times the cost of skinning the points once)."""
        idx, wts = self._input
        V, groups = self.vertex_count, max(1, -(-self.influence_count // 4))
        out = {"indices": KB.empty((V, groups), wp.vec4i, device),
               "weights": KB.empty((V, groups), wp.vec4, device)}
        if self.influence_count == 0:
            out["indices"].zero_()
            out["weights"].zero_()
            return out
        cpu = wp.get_device(device).is_cpu  # inputs read during the launch only: no copies
        KL.layout(joint_indices=wp.array(idx.astype(np.int32, copy=False), dtype=wp.int32,
                                         device=device, copy=not cpu),
                  joint_weights=wp.array(np.ascontiguousarray(wts, np.float32), dtype=wp.float32,
                                         device=device, copy=not cpu),
                  device=device, **out)
        return out
