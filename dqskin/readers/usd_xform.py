"""USD transforms over time as plain data: the xform ops above a prim, read once, evaluated and
differentiated in NumPy exactly as USD interpolates them.

USD interpolates each op attribute on its own between its time samples (held outside them): vectors,
scalars and matrices linearly, quaternions by slerp along the shorter arc. An op's matrix follows
from its value (rotations in degrees, ``rotateXYZ`` rotating about X first), a prim's local
transform is the product of its ops in ``xformOpOrder`` (the first op outermost; ``!invert!`` ops
inverted), and local-to-world the product over the ancestors up to a ``!resetXformStack!``. Within
an interval every value is linear (or a slerp) in time, so each op's derivative is exact and the
chain is differentiated by the product rule. At an interior sample time, where the interpolant has
a kink, the derivative is the mean of both sides, as for joints.
"""

from typing import Literal

import numpy as np
import numpy.typing as npt
from pxr import Gf, Usd, UsdGeom

from .. import quat
from ..animation import TransformTrack
from ..errors import InputError
from ..linalg import hat

__all__ = ["XformChain", "read_local_to_world"]

_T = UsdGeom.XformOp
_AXES = {"X": 0, "Y": 1, "Z": 2}


def _value(v: object) -> np.ndarray:
    """An op attribute value as a flat float64 array ((w, x, y, z) for quaternions)."""
    if isinstance(v, (Gf.Quatf, Gf.Quatd, Gf.Quath)):
        return np.array([v.GetReal(), *v.GetImaginary()], dtype=np.float64)
    if isinstance(v, (Gf.Matrix4d, Gf.Matrix4f)):
        return np.array(v, dtype=np.float64).T.reshape(16)  # row-vector Gf → column-vector
    return np.atleast_1d(np.asarray(v, dtype=np.float64)).reshape(-1)


class _Op:
    """One xform op: its kind, axis order, inversion and keyed values."""

    def __init__(self, op: UsdGeom.XformOp) -> None:
        self.type = op.GetOpType()
        self.inverse = op.IsInverseOp()
        times = op.GetTimeSamples()
        if times:
            self.times = np.asarray(times, dtype=np.float64)
            self.values = np.stack([_value(op.Get(t)) for t in times])
        else:
            self.times = np.zeros(1)
            self.values = _value(op.Get())[None]
        self.name = op.GetOpName()

    def sample(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Value (F, n) and its time derivative (F, n) at times ``t`` (at an interior sample, the
        mean of the two one-sided derivatives)."""
        kt, v = self.times, self.values
        if kt.shape[0] == 1:
            return (np.broadcast_to(v[0], (t.shape[0],) + v.shape[1:]),
                    np.zeros((t.shape[0],) + v.shape[1:]))
        value, rate = self._segment(t, "right")
        at_key = np.isin(t, kt[1:-1])
        if at_key.any():
            rate[at_key] = 0.5 * (rate[at_key] + self._segment(t[at_key], "left")[1])
        return value, rate

    def _segment(self, t: np.ndarray,
                 side: Literal["left", "right"]) -> tuple[np.ndarray, np.ndarray]:
        kt, v = self.times, self.values
        k = np.clip(np.searchsorted(kt, t, side=side) - 1, 0, kt.shape[0] - 2)
        dt = kt[k + 1] - kt[k]
        u = np.clip((t - kt[k]) / dt, 0.0, 1.0)[:, None]
        inside = ((t >= kt[0]) & (t <= kt[-1]))[:, None]
        if self.type == _T.TypeOrient:
            q0, q1 = v[k], v[k + 1]
            q = quat.slerp(q0, q1, u[:, 0])
            q1 = np.where(quat.dot(q0, q1)[:, None] < 0, -q1, q1)
            log = quat.log(quat.mul(quat.conjugate(quat.normalize(q0)), quat.normalize(q1)))
            return q, quat.mul(q, log) * (inside / dt[:, None])
        return (1 - u) * v[k] + u * v[k + 1], (v[k + 1] - v[k]) * (inside / dt[:, None])

    def matrices(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(F, 4, 4) op matrices and their time derivatives."""
        val, rate = self.sample(t)
        F = t.shape[0]
        m = np.tile(np.eye(4), (F, 1, 1))
        dm = np.zeros((F, 4, 4))
        name = str(self.type).rsplit(".", 1)[-1].replace("Type", "")
        if name.startswith("Translate"):
            axes = [_AXES[name[-1]]] if name[-1] in _AXES else [0, 1, 2]
            m[:, axes, 3], dm[:, axes, 3] = val, rate
        elif name.startswith("Scale"):
            axes = [_AXES[name[-1]]] if name[-1] in _AXES else [0, 1, 2]
            m[:, axes, axes], dm[:, axes, axes] = val, rate
        elif name == "Transform":
            m, dm = val.reshape(F, 4, 4).copy(), rate.reshape(F, 4, 4)
        elif name == "Orient":
            r = quat.to_matrix(quat.normalize(val))
            omega = 2 * quat.mul(quat.conjugate(quat.normalize(val)), rate)[:, 1:]  # body
            m[:, :3, :3] = r
            dm[:, :3, :3] = r @ hat(omega)
        elif name.startswith("Rotate"):
            order = name[len("Rotate"):]
            angles, rates = np.radians(val), np.radians(rate)
            for i, axis in enumerate(order):  # first letter applied first: outermost last
                r, dr = _axis_rotation(_AXES[axis], angles[:, i], rates[:, i])
                m, dm = r @ m, dr @ m + r @ dm
        else:
            raise InputError(f"xform op {self.name}: unsupported type {name}")
        if self.inverse:
            inv = np.linalg.inv(m)
            return inv, -inv @ dm @ inv
        return m, dm


def _axis_rotation(axis: int, angle: np.ndarray, rate: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(F, 4, 4) rotations about one axis and their derivatives (angles in radians)."""
    F = angle.shape[0]
    c, s = np.cos(angle), np.sin(angle)
    i, j = [(1, 2), (2, 0), (0, 1)][axis]
    r = np.tile(np.eye(4), (F, 1, 1))
    dr = np.zeros((F, 4, 4))
    r[:, i, i], r[:, i, j], r[:, j, i], r[:, j, j] = c, -s, s, c
    dr[:, i, i], dr[:, i, j], dr[:, j, i], dr[:, j, j] = -s * rate, -c * rate, c * rate, -s * rate
    return r, dr


def read_local_to_world(prim: Usd.Prim) -> list[_Op]:
    """The xform ops from the root down to ``prim`` (after the last ``!resetXformStack!``), in
    the order they compose: a list of :class:`_Op`, the outermost first."""
    chain: list[_Op] = []
    while prim and not prim.IsPseudoRoot():
        xf = UsdGeom.Xformable(prim)
        if xf:
            chain[:0] = [_Op(op) for op in xf.GetOrderedXformOps()]
            if xf.GetResetXformStack():
                break
        prim = prim.GetParent()
    return chain


class XformChain(TransformTrack):
    """``inverse(localToWorld(target)) @ localToWorld(source)``: ``source`` space → ``target``
    space over time (skeleton → prim), from the ops read by :func:`read_local_to_world`."""

    def __init__(self, source_ops: list[_Op], target_ops: list[_Op], *,
                 name: str = "transform") -> None:
        self.source, self.target, self.name = source_ops, target_ops, name
        keys = set()
        for op in source_ops + target_ops:
            if op.times.shape[0] > 1:
                keys.update(op.times.tolist())
        self.key_times = np.array(sorted(keys) or [0.0], dtype=np.float64)

    @staticmethod
    def _compose(ops: list[_Op], t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        m = np.tile(np.eye(4), (t.shape[0], 1, 1))
        dm = np.zeros_like(m)
        for op in ops:
            a, da = op.matrices(t)
            m, dm = m @ a, dm @ a + m @ da
        return m, dm

    def with_derivative(self, times: npt.ArrayLike) -> tuple[np.ndarray, np.ndarray]:
        t = np.atleast_1d(np.asarray(times, dtype=np.float64))
        s, ds = self._compose(self.source, t)
        g, dg = self._compose(self.target, t)
        if np.any(np.abs(np.linalg.det(g[:, :3, :3])) < 1e-300):
            raise InputError(f"{self.name}: singular local-to-world transform")
        gi = np.linalg.inv(g)
        return gi @ s, gi @ ds - gi @ dg @ gi @ s
