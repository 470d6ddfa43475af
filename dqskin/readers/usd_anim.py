"""UsdSkel's joint-transform sampling, for many times at once.

``UsdSkel.SkeletonQuery.ComputeJointLocalTransforms`` composes one time: it reads the
``SkelAnimation``'s ``translations`` (``float3[]``), ``rotations`` (``quatf[]``) and ``scales``
(``half3[]``) at that time as USD resolves them under linear interpolation (a sample's own time
gives that sample; between two samples, a componentwise lerp of translations and scales and
``GfSlerp`` of rotations, each in the attribute's own precision; held before the first sample
and after the last), builds each joint's scale · rotate · translate matrix
(``UsdSkelMakeTransforms``) and maps the animation's joints onto the skeleton's, the joints it
does not drive keeping their rest transform. Called once per frame from Python, that costs as
much as skinning a small mesh; :class:`JointTracks` does the same for all the times of a chunk
in NumPy, from the samples the loader has read and checked.

It follows USD's arithmetic: lerps and slerps rounded to float32 (half for scales) after each
operation as ``GfVec3f``, ``GfQuatf`` and ``GfVec3h`` do, each rotation-scale entry computed in
float32 from the quaternion as given (UsdSkel does; :mod:`dqskin.quat`'s float64 conversion of
unit ``(w, x, y, z)`` quaternions would differ in the last bits), stored as float64.
``tests/test_usd_anim.py`` compares it with UsdSkel at every sample and at sub-frames of the
animations of seven shared assets, sparse and random ones.
"""

from collections.abc import Callable

import numpy as np
import numpy.typing as npt

__all__ = ["JointTracks"]

_SLERP_LINEAR_BELOW = 1e-5
"""``GfSlerp`` interpolates linearly when ``1 - cos θ`` is not above this."""


class JointTracks:
    """The ``translations``, ``rotations`` and ``scales`` of one ``SkelAnimation``, sampled as
    UsdSkel does.

    Parameters
    ----------
    translations, rotations, scales : (times, values)
        Each attribute's samples: ``times`` (K,) strictly increasing time codes, or None for
        its default value alone (then ``values`` holds one entry); ``values`` (K, A, 3) float32
        translations, (K, A, 4) float32 rotations ``(x, y, z, w)`` (the memory order of
        ``GfQuatf``), (K, A, 3) half scales, in the animation's joint order.
    joints : (A,) int
        Each animation joint's index in the skeleton's joint order, -1 for one it lacks.
    rest : (J, 4, 4) float64
        The skeleton's local rest transforms (column-vector convention), for the joints the
        animation does not drive.
    """

    def __init__(self, translations: tuple[npt.ArrayLike | None, npt.ArrayLike],
                 rotations: tuple[npt.ArrayLike | None, npt.ArrayLike],
                 scales: tuple[npt.ArrayLike | None, npt.ArrayLike], joints: npt.ArrayLike,
                 rest: npt.ArrayLike) -> None:
        self._tracks = [_Track(*translations, np.float32, _lerp),
                        _Track(*rotations, np.float32, _slerp),
                        _Track(*scales, np.float16, _lerp)]
        joints = np.asarray(joints, np.int64)
        driven = joints >= 0
        self._from, self._to = np.flatnonzero(driven), joints[driven]
        self._rest = np.asarray(rest, np.float64)
        self._full = (len(self._to) == len(self._rest)
                      and np.array_equal(self._to, np.arange(len(self._rest))))

    def local_transforms(self, times: npt.ArrayLike) -> np.ndarray:
        """(F, J, 4, 4) float64 parent-relative joint transforms at ``times`` (F,),
        column-vector convention, skeleton joint order."""
        t = np.atleast_1d(np.asarray(times, np.float64))
        xf = _make_transforms(*(track.at(t) for track in self._tracks))
        if self._full:
            return xf
        out = np.broadcast_to(self._rest, (len(t),) + self._rest.shape).copy()
        out[:, self._to] = xf[:, self._from]
        return out


class _Track:
    """One attribute's samples and USD's linear interpolation between them."""

    def __init__(self, times: npt.ArrayLike | None, values: npt.ArrayLike, dtype: npt.DTypeLike,
                 blend: Callable[[np.ndarray, np.ndarray, np.ndarray], np.ndarray]) -> None:
        self.values = np.asarray(values, dtype)
        self.times = None if times is None else np.asarray(times, np.float64)
        self.blend = blend

    def at(self, t: np.ndarray) -> np.ndarray:
        """(F, A, C) values at times ``t`` (F,): a sample's own at its time, held outside the
        samples, blended between two."""
        k = self.times
        if k is None:
            return np.broadcast_to(self.values[0], (len(t),) + self.values.shape[1:])
        i = np.clip(np.searchsorted(k, t, side="right") - 1, 0, len(k) - 1)
        out = self.values[i]
        between = (t > k[0]) & (t < k[-1]) & (t != k[i])
        if between.any():
            lo = i[between]
            a = ((t[between] - k[lo]) / (k[lo + 1] - k[lo]))[:, None, None]
            out[between] = self.blend(a, self.values[lo], self.values[lo + 1])
        return out


def _lerp(a: np.ndarray, lower: np.ndarray, upper: np.ndarray) -> np.ndarray:
    """``(1 - a) * lower + a * upper`` as ``GfVec3f`` and ``GfVec3h`` compute it: each product
    rounded to the type (``GfVec3f``: in double; ``GfVec3h``: in float32, the weight made a
    float32 first, as ``GfHalf *= float`` does), then their sum in the type."""
    kind = lower.dtype
    if kind == np.float16:
        f4 = np.float32
        return (((1.0 - a).astype(f4) * lower.astype(f4)).astype(kind)
                + (a.astype(f4) * upper.astype(f4)).astype(kind))
    return ((1.0 - a) * lower).astype(kind) + (a * upper).astype(kind)


def _slerp(a: np.ndarray, q0: np.ndarray, q1: np.ndarray) -> np.ndarray:
    """``GfSlerp(a, q0, q1)`` of ``GfQuatf`` arrays ``(x, y, z, w)``, rounded where ``GfQuatf``
    arithmetic rounds: the dot product in float32, the angle (``acos`` in double) and its sine
    (in float32) and both weights (``sin`` in double) rounded to float32, the shorter way round
    (the second negated when the dot product is negative), linear weights when
    ``1 - cos θ ≤ 1e-5``; each weighted quaternion rounded, then their sum."""
    f4 = np.float32
    im = (q0[..., 0] * q1[..., 0] + q0[..., 1] * q1[..., 1]) + q0[..., 2] * q1[..., 2]
    cos = (im + q0[..., 3] * q1[..., 3])[..., None]
    flip = cos < 0
    cos = np.abs(cos)
    linear = 1.0 - cos.astype(np.float64) <= _SLERP_LINEAR_BELOW
    theta = np.arccos(np.where(linear, 0.5, cos).astype(np.float64)).astype(f4).astype(np.float64)
    sin = np.sin(theta).astype(f4).astype(np.float64)  # float32 sin, correctly rounded
    s0 = np.where(linear, 1.0 - a, np.sin((1.0 - a) * theta) / sin).astype(f4)
    s1 = np.where(linear, a, np.sin(a * theta) / sin).astype(f4)
    s1 = np.where(flip, -s1, s1)
    return s0 * q0 + s1 * q1


def _make_transforms(translations: np.ndarray, rotations: np.ndarray,
                     scales: np.ndarray) -> np.ndarray:
    """``UsdSkelMakeTransforms``: (F, A, 4, 4) float64 column-vector matrices of scale, then
    rotation (the quaternion ``(x, y, z, w)`` as given, not normalized, each entry computed in
    float32 as UsdSkel does: bit for bit with it), then translation."""
    q = rotations.astype(np.float32)
    x, y, z, w = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    s = scales.astype(np.float32)
    one, two = np.float32(1.0), np.float32(2.0)
    m = np.zeros(q.shape[:-1] + (4, 4))
    # the rotation matrix's rows (row-vector convention), row i scaled by scale i; stored
    # transposed for the column-vector convention: m[..., j, i] = row i, column j
    m[..., 0, 0] = (one - two * (y * y + z * z)) * s[..., 0]
    m[..., 1, 0] = (two * (x * y + z * w)) * s[..., 0]
    m[..., 2, 0] = (two * (z * x - y * w)) * s[..., 0]
    m[..., 0, 1] = (two * (x * y - z * w)) * s[..., 1]
    m[..., 1, 1] = (one - two * (z * z + x * x)) * s[..., 1]
    m[..., 2, 1] = (two * (y * z + x * w)) * s[..., 1]
    m[..., 0, 2] = (two * (z * x + y * w)) * s[..., 2]
    m[..., 1, 2] = (two * (y * z - x * w)) * s[..., 2]
    m[..., 2, 2] = (one - two * (y * y + x * x)) * s[..., 2]
    m[..., :3, 3] = translations
    m[..., 3, 3] = 1.0
    return m
