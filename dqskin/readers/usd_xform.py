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

from collections.abc import Sequence
from typing import Literal

import numpy as np
import numpy.typing as npt
from pxr import Gf, Sdf, Usd, UsdGeom

from .. import quat
from ..animation import TransformTrack
from ..errors import InputError
from ..linalg import hat

__all__ = ["LocalToWorld", "XformChain"]

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


class LocalToWorld:
    """The local-to-world xform ops of the prims of one stage, each prim's ops read once.

    A prim's chain is its ancestors' and its own ops from the root down (after the last
    ``!resetXformStack!``), the outermost first. Prims below one *owner* (the nearest prim at or
    above them with ops or a ``!resetXformStack!``; the root when none) share one chain, read
    and evaluated once: a stage of many referenced characters holds many meshes a character.
    """

    def __init__(self) -> None:
        # prim path → (its owner, the owner's ops)
        self._chains: dict[Sdf.Path, tuple[Sdf.Path, tuple[_Op, ...]]] = {}
        self._kinds: dict[Sdf.Path, tuple[bool, bool]] = {}  # owner → (identity, regular)

    def _chain(self, prim: Usd.Prim) -> tuple[Sdf.Path, tuple[_Op, ...]]:
        hit = self._chains.get(prim.GetPath())
        if hit is not None:
            return hit
        pending = []  # (path, own ops, reset) from ``prim`` up to a known chain or a reset
        chain: tuple[Sdf.Path, tuple[_Op, ...]] = (Sdf.Path.absoluteRootPath, ())
        while prim and not prim.IsPseudoRoot():
            hit = self._chains.get(prim.GetPath())
            if hit is not None:
                chain = hit
                break
            xf = UsdGeom.Xformable(prim)
            own = tuple(_Op(op) for op in xf.GetOrderedXformOps()) if xf else ()
            reset = bool(xf) and xf.GetResetXformStack()
            pending.append((prim.GetPath(), own, reset))
            if reset:
                break
            prim = prim.GetParent()
        for path, own, reset in reversed(pending):
            if reset:
                chain = (path, own)
            elif own:
                chain = (path, chain[1] + own)
            self._chains[path] = chain
        return chain

    def ops(self, prim: Usd.Prim) -> tuple[_Op, ...]:
        """The xform ops from the root down to ``prim``, in the order they compose."""
        return self._chain(prim)[1]

    def owner(self, prim: Usd.Prim) -> Sdf.Path:
        """The nearest prim at or above ``prim`` with xform ops or a ``!resetXformStack!`` (the
        absolute root when none): ``prim``'s local-to-world is that prim's."""
        return self._chain(prim)[0]

    def _kind(self, prim: Usd.Prim) -> tuple[bool, bool]:
        owner, ops = self._chain(prim)
        kind = self._kinds.get(owner)
        if kind is None:
            chain = XformChain(ops, ())
            try:
                with np.errstate(all="ignore"):
                    m = chain.at(chain.key_times)
            except (ValueError, np.linalg.LinAlgError):  # (its users name the problem)
                kind = (False, False)
            else:
                with np.errstate(all="ignore"):
                    kind = (bool(m.shape[0] == 1
                                 and np.allclose(m, np.eye(4), rtol=0, atol=1e-12)),
                            bool(np.isfinite(m).all()
                                 and (np.abs(np.linalg.det(m[:, :3, :3])) > 0).all()))
            self._kinds[owner] = kind
        return kind

    def is_identity(self, prim: Usd.Prim) -> bool:
        """Whether ``prim``'s local-to-world is one constant identity transform (within 1e-12)."""
        return self._kind(prim)[0]

    def is_regular(self, prim: Usd.Prim) -> bool:
        """Whether ``prim``'s local-to-world is finite and invertible at every key time."""
        return self._kind(prim)[1]


class XformChain(TransformTrack):
    """``inverse(localToWorld(target)) @ localToWorld(source)``: ``source`` space → ``target``
    space over time (skeleton → prim), from the ops of :meth:`LocalToWorld.ops`."""

    def __init__(self, source_ops: Sequence[_Op], target_ops: Sequence[_Op], *,
                 name: str = "transform") -> None:
        self.source, self.target, self.name = source_ops, target_ops, name
        keys = set()
        for op in [*source_ops, *target_ops]:
            if op.times.shape[0] > 1:
                keys.update(op.times.tolist())
        self.key_times = np.array(sorted(keys) or [0.0], dtype=np.float64)

    @staticmethod
    def _compose(ops: Sequence[_Op], t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
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
