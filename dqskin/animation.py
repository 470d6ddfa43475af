"""Animations and how they are sampled between keys: the asset's own TRS player or dual-quaternion
interpolants, with analytic time derivatives.

Sampling
--------
:func:`sample` evaluates an :class:`Animation` at any times with one of
:data:`dqskin.options.INTERPOLATIONS`:

``"trs"``
    ``animation.local_transforms(times)`` unchanged: what the asset's own player does (glTF
    LINEAR, USD: rotation slerp, translation and scale lerp).
``"sclerp"``, ``"dlb"``, ``"spline"``, ``"catmull-rom"``
    The key poses ``animation.local_transforms(animation.key_times)`` are split, per joint, into a
    unit dual quaternion ``η`` (polar rotation ``R`` and translation ``t``, ``M = [R·S | t]``) and a
    residual 3×3 ``S`` (scale/shear, interpolated linearly between keys). The key DQs are
    sign-aligned along the clip (each key onto the hemisphere of the previous one), then:

    * ``"sclerp"``: screw linear interpolation ``ηₖ·exp(u·log(ηₖ⁻¹·ηₖ₊₁))`` (Kenwright eq. 41,
      Montgomery-Smith eq. 41): shortest path, constant twist between keys.
    * ``"dlb"``: normalized linear blend ``normalize((1 − u)·ηₖ + u·ηₖ₊₁)`` (Kenwright eq. 44).
    * ``"spline"``: Montgomery-Smith & Shy §6: a free (natural) cubic spline ``γ`` through the key
      DQs as 8-vectors, normalized (eq. 31, 34: ``η(t) = normalize(γ(s(t)))``), with the ramp-up /
      ramp-down reparametrization ``s`` of eq. 32–33 (:func:`ramp`): ``γ`` is knotted at
      ``½(t₀ + t₁), t₁, …, tₙ₋₁, ½(tₙ₋₁ + tₙ)``, and ``s`` maps ``[t₀, t₁]`` onto
      ``[½(t₀ + t₁), t₁]`` (and the last interval likewise) with ``s' = s'' = 0`` at ``t₀`` and
      ``tₙ``: the motion passes through every key, starts and stops with zero velocity and
      acceleration, and has a bounded third derivative everywhere. With only two keys eq. 32 is
      degenerate (ramp-up and ramp-down would share the single interval); a middle key
      ``sclerp(η₀, η₁, ½)`` at ``½(t₀ + t₁)`` is inserted first.
    * ``"catmull-rom"``: Kenwright's Catmull-Rom spline on dual quaternions: a cubic Hermite curve
      per component through the key DQs with the (non-uniform) Catmull-Rom tangents
      ``(ηₖ₊₁ − ηₖ₋₁)/(tₖ₊₁ − tₖ₋₁)`` (one-sided at the ends), normalized. C¹, no ramp.

    The local transform is ``[R(η)·S | t(η)]``.

Times outside the key range clamp to the first / last pose (zero velocity there). Everything is
vectorized NumPy float64 over (times, joints).

Derivatives
-----------
Every interpolant is differentiated analytically (no finite differences): ``η̇`` from the
interpolant's derivative (the derivative of the dual-number normalization for the normalized
ones), the twist ``φ = η⁻¹·η̇ = ω/2 + ε·v/2`` (Montgomery-Smith eq. 25–26, :func:`dqskin.dq.twist`),
``Ṁ = [R·[ω]×·S + R·Ṡ | R·v]``. For ``"trs"`` the keyed TRS interpolant is differentiated (slerp:
``q̇ = q·log(qₖ*·qₖ₊₁)/Δt``; lerp: ``(xₖ₊₁ − xₖ)/Δt``), which reproduces any linear TRS player
whose key times are all in ``animation.key_times`` (glTF LINEAR, USD); STEP or CUBICSPLINE clips
are detected and rejected.

References
----------
[K] B. Kenwright, "Dual-Quaternions: From Classical Mechanics to Computer Graphics and Beyond",
    2012 (shared/references/000_e688072581e8ee3b.txt).
[MS] S. Montgomery-Smith and C. Shy, "An Introduction to Using Dual Quaternions to Study
    Kinematics", 2023 (shared/references/003_d8d7d9932a992693.txt).
"""

import abc
import weakref
from collections.abc import Callable

import numpy as np
import numpy.typing as npt

from . import dq, quat
from .errors import InputError
from .linalg import hat, polar
from .options import DEFAULT_INTERP, INTERPOLATIONS, Interpolation

__all__ = ["Animation", "Deformer", "KeyedAnimation", "TransformTrack", "check_times", "ramp",
           "sample", "sample_with_derivative", "segment_rates"]


_TRS_TOLERANCE = 1e-5  # relative: "trs" velocities need the player to be linear TRS between keys


def _pure(v):
    """3-vectors as pure quaternions ``(0, v)``."""
    return np.concatenate([np.zeros_like(v[..., :1]), v], -1)


class Animation(abc.ABC):
    """Keyed local joint transforms of one skeleton (format loaders subclass it).

    Subclasses set ``key_times`` in their constructor and implement :meth:`local_transforms`.

    Attributes
    ----------
    key_times : (K,) float64
        Times of the keys, in the scene's time unit (USD time codes, glTF seconds).
    """

    key_times: np.ndarray
    linear_trs: bool = True
    """Whether :meth:`local_transforms` interpolates linearly in TRS between ``key_times``
    (slerp, lerp: glTF LINEAR, USD); "trs" velocities need it (a glTF STEP or CUBICSPLINE clip
    sets it False)."""

    @abc.abstractmethod
    def local_transforms(self, times: npt.ArrayLike) -> np.ndarray:
        """Parent-relative joint transforms at ``times``.

        Parameters
        ----------
        times : (F,) float

        Returns
        -------
        (F, J, 4, 4) float64, column-vector convention.
        """


def check_times(times: npt.ArrayLike, name: str = "times") -> np.ndarray:
    t = np.atleast_1d(np.asarray(times, dtype=np.float64))
    if t.ndim != 1 or not np.all(np.isfinite(t)):
        raise InputError(f"{name}: expected a 1-D array of finite times, got shape {t.shape}")
    return t


def _check_interp(interp: str) -> None:
    if interp not in INTERPOLATIONS:
        raise InputError(f"interp must be one of {INTERPOLATIONS}, got {interp!r}")


def _normalize_with_derivative(g, g_dot):
    """``normalize(g)`` ([MS] eq. 14) and its derivative along ``g_dot``, both (..., 8).

    With ``n = |r|``, ``c = r·d``: ``η = r/n + ε·(d/n − c·r/n³)``.
    """
    r, d = g[..., :4], g[..., 4:]
    rd, dd = g_dot[..., :4], g_dot[..., 4:]
    n2 = np.sum(r * r, -1, keepdims=True)
    if np.any(n2 == 0):
        raise InputError("interpolated dual quaternion has a zero real part (keys too far apart)")
    n = np.sqrt(n2)
    n_dot = np.sum(r * rd, -1, keepdims=True) / n
    c = np.sum(r * d, -1, keepdims=True)
    c_dot = np.sum(rd * d + r * dd, -1, keepdims=True)
    n3 = n2 * n
    eta = np.concatenate([r / n, d / n - c * r / n3], -1)
    eta_dot = np.concatenate([
        (rd - r * n_dot / n) / n,
        dd / n - d * n_dot / n2 - (c_dot * r + c * rd) / n3 + 3 * c * r * n_dot / (n3 * n)], -1)
    return eta, eta_dot


def ramp(times: npt.ArrayLike, key_times: npt.ArrayLike) -> tuple[np.ndarray, np.ndarray]:
    """Ramp-up / ramp-down reparametrization ``s(t)`` of [MS] §6 eq. 32–33 and its derivative.

    ``f(x) = ½ + ½·(2 − x)·x³`` (eq. 33). With keys ``t₀ < … < tₙ`` (``n ≥ 2``)::

        s(t) = ½(t₀ + t₁)                               t < t₀
               t₀ + (t₁ − t₀)·f((t − t₀)/(t₁ − t₀))     t₀ ≤ t < t₁
               t                                        t₁ ≤ t < tₙ₋₁
               tₙ − (tₙ − tₙ₋₁)·f((tₙ − t)/(tₙ − tₙ₋₁)) tₙ₋₁ ≤ t < tₙ
               ½(tₙ₋₁ + tₙ)                             t ≥ tₙ

    so ``s(tₖ) = tₖ`` for ``1 ≤ k ≤ n − 1``, ``s' = s'' = 0`` at ``t₀`` and ``tₙ``, ``s' = 1`` and
    ``s'' = 0`` at ``t₁`` and ``tₙ₋₁``, and ``s'''`` is bounded.

    Parameters
    ----------
    times : (F,) float
    key_times : (K,) float, strictly increasing, K ≥ 3

    Returns
    -------
    s, s_dot : (F,) float64
    """
    t = check_times(times)
    k = np.asarray(key_times, dtype=np.float64)
    if k.ndim != 1 or k.shape[0] < 3:
        raise InputError(f"key_times: ramp needs at least 3 keys, got shape {k.shape}")
    t0, t1, tm, tn = k[0], k[1], k[-2], k[-1]
    up = np.clip((t - t0) / (t1 - t0), 0.0, 1.0)
    down = np.clip((tn - t) / (tn - tm), 0.0, 1.0)
    s = np.where(t < t1, t0 + (t1 - t0) * (0.5 + 0.5 * (2 - up) * up ** 3),
                 np.where(t < tm, t, tn - (tn - tm) * (0.5 + 0.5 * (2 - down) * down ** 3)))
    s_dot = np.where(t < t1, 3 * up ** 2 - 2 * up ** 3,
                     np.where(t < tm, 1.0, 3 * down ** 2 - 2 * down ** 3))
    return s, s_dot


def _natural_spline(x, y):
    """Second derivatives ``M`` (K, ...) of the natural cubic spline through ``(x, y)``.

    ``h₋·M₋ + 2(h₋ + h₊)·M + h₊·M₊ = 6·(Δy₊/h₊ − Δy₋/h₋)``, ``M₀ = Mₙ = 0``; Thomas algorithm.
    """
    n = x.shape[0] - 1
    m = np.zeros_like(y)
    if n < 2:
        return m
    h = np.diff(x)
    slope = np.diff(y, axis=0) / h.reshape((-1,) + (1,) * (y.ndim - 1))
    rhs = 6 * (slope[1:] - slope[:-1])
    diag = 2 * (h[:-1] + h[1:])
    c_prime = np.zeros(n - 1)
    d_prime = np.zeros_like(rhs)
    for i in range(n - 1):
        denom = diag[i] - (h[i] * c_prime[i - 1] if i else 0.0)
        c_prime[i] = h[i + 1] / denom
        d_prime[i] = (rhs[i] - (h[i] * d_prime[i - 1] if i else 0.0)) / denom
    for i in range(n - 2, -1, -1):
        m[i + 1] = d_prime[i] - (c_prime[i] * m[i + 2] if i < n - 2 else 0.0)
    return m


# ---------------------------------------------------------------------------------------------
# keyed poses and their interpolants


_KEY_BLOCK = 512
"""Keys decomposed at a time by :class:`_Keys`."""


class _Keys:
    """Key poses split into sign-aligned unit DQs, rotations, translations and residuals."""

    def __init__(self, key_times, local, where):
        kt = np.asarray(key_times, dtype=np.float64)
        if kt.ndim != 1 or kt.shape[0] == 0 or not np.all(np.isfinite(kt)):
            raise InputError(f"{where}: key_times must be a non-empty 1-D array of finite times, "
                             f"got shape {kt.shape}")
        if np.any(np.diff(kt) <= 0):
            raise InputError(f"{where}: key_times must be strictly increasing")
        m = np.asarray(local, dtype=np.float64)
        if m.ndim != 4 or m.shape[0] != kt.shape[0] or m.shape[2:] != (4, 4):
            raise InputError(f"{where}: key transforms must be ({kt.shape[0]}, J, 4, 4), "
                             f"got {m.shape}")
        if not np.all(np.isfinite(m)):
            raise InputError(f"{where}: key transforms have NaN or infinite entries")
        self.times = kt
        self.joint_count = m.shape[1]
        # in blocks of keys: the SVD's temporaries for every key at once would be a multiple of
        # the result, so a clip worker's memory would grow with the key count
        q = np.empty(m.shape[:2] + (4,))
        self.residual = np.empty(m.shape[:2] + (3, 3))
        for a in range(0, m.shape[0], _KEY_BLOCK):
            rot, self.residual[a:a + _KEY_BLOCK] = polar(m[a:a + _KEY_BLOCK, :, :3, :3])
            q[a:a + _KEY_BLOCK] = quat.from_matrix(rot)
        if kt.shape[0] > 1:
            flips = np.where(quat.dot(q[:-1], q[1:]) < 0, -1.0, 1.0)
            q[1:] *= np.cumprod(flips, axis=0)[..., None]
        self.q = q
        self.t = m[..., :3, 3].copy()
        self.eta = dq.from_rt(q, self.t)
        self._cache = {}

    def segments(self, t, side="right"):
        """Interval index ``i``, parameter ``u`` in [0, 1] and ``du/dt`` (0 outside the keys).
        At a key, ``side`` picks the interval: "right" the one starting there, "left" the one
        ending there."""
        kt = self.times
        if kt.shape[0] == 1:
            z = np.zeros(t.shape)
            return np.zeros(t.shape, dtype=np.int64), z, z
        i = np.clip(np.searchsorted(kt, t, side=side) - 1, 0, kt.shape[0] - 2)
        dt = kt[i + 1] - kt[i]
        u = np.clip((t - kt[i]) / dt, 0.0, 1.0)
        du = np.where((t >= kt[0]) & (t <= kt[-1]), 1.0 / dt, 0.0)
        return i, u, du

    def _cached(self, name, build):
        if name not in self._cache:
            self._cache[name] = build()
        return self._cache[name]

    def residual_at(self, t, side="right"):
        """(F, J, 3, 3) residuals and derivatives, linear between keys."""
        if self.times.shape[0] == 1:
            s = np.broadcast_to(self.residual, (t.shape[0],) + self.residual.shape[1:])
            return s, np.zeros_like(s)
        i, u, du = self.segments(t, side)
        s0, s1 = self.residual[i], self.residual[i + 1]
        uu = u[:, None, None, None]
        return (1 - uu) * s0 + uu * s1, (s1 - s0) * du[:, None, None, None]

    def dual_quaternions(self, t, interp, side="right"):
        """(F, J, 8) interpolated unit DQs ``η`` and their derivatives ``η̇``."""
        if self.times.shape[0] == 1:
            eta = np.broadcast_to(self.eta, (t.shape[0],) + self.eta.shape[1:])
            return eta, np.zeros_like(eta)
        return getattr(self, "_" + interp.replace("-", "_"))(t, side)

    def _trs(self, t, side="right"):
        """Rotation slerp, translation lerp: ``q = qₖ·exp(u·Lₖ)``, ``Lₖ = log(qₖ*·qₖ₊₁)``."""
        log = self._cached("rot_log", lambda: quat.log(
            quat.mul(quat.conjugate(self.q[:-1]), self.q[1:])) * np.array([0.0, 1, 1, 1]))
        i, u, du = self.segments(t, side)
        lk = log[i]
        q = quat.mul(self.q[i], quat.exp(u[:, None, None] * lk))
        q_dot = quat.mul(q, lk) * du[:, None, None]
        uu = u[:, None, None]
        tr = (1 - uu) * self.t[i] + uu * self.t[i + 1]
        tr_dot = (self.t[i + 1] - self.t[i]) * du[:, None, None]
        eta = dq.from_rt(q, tr)
        dual_dot = 0.5 * (quat.mul(_pure(tr_dot), q) + quat.mul(_pure(tr), q_dot))
        return eta, np.concatenate([q_dot, dual_dot], -1)

    def _sclerp(self, t, side="right"):
        """``ηₖ·exp(u·ξₖ)``, ``ξₖ = log(ηₖ*·ηₖ₊₁)``; ``η̇ = η·ξₖ/Δt`` ([MS] eq. 25, 41)."""
        xi = self._cached("screw_log", lambda: dq.log(dq.mul(
            dq.conjugate_quat(self.eta[:-1]), self.eta[1:])) * np.array([0.0, 1, 1, 1, 0, 1, 1, 1]))
        i, u, du = self.segments(t, side)
        eta = dq.mul(self.eta[i], dq.exp(u[:, None, None] * xi[i]))
        return eta, dq.mul(eta, xi[i]) * du[:, None, None]

    def _dlb(self, t, side="right"):
        i, u, du = self.segments(t, side)
        a, b = self.eta[i], self.eta[i + 1]
        uu = u[:, None, None]
        return _normalize_with_derivative((1 - uu) * a + uu * b, (b - a) * du[:, None, None])

    def _catmull_rom(self, t, side="right"):
        """Cubic Hermite per component with Catmull-Rom tangents, normalized."""
        kt, p = self.times, self.eta

        def tangents():
            m = np.empty_like(p)
            m[0] = (p[1] - p[0]) / (kt[1] - kt[0])
            m[-1] = (p[-1] - p[-2]) / (kt[-1] - kt[-2])
            m[1:-1] = (p[2:] - p[:-2]) / (kt[2:] - kt[:-2])[:, None, None]
            return m

        m = self._cached("catmull_rom", tangents)
        i, u, du = self.segments(t, side)
        h = (kt[i + 1] - kt[i])[:, None, None]
        uu = u[:, None, None]
        u2, u3 = uu * uu, uu * uu * uu
        g = ((2 * u3 - 3 * u2 + 1) * p[i] + (u3 - 2 * u2 + uu) * h * m[i]
             + (-2 * u3 + 3 * u2) * p[i + 1] + (u3 - u2) * h * m[i + 1])
        g_u = ((6 * u2 - 6 * uu) * p[i] + (3 * u2 - 4 * uu + 1) * h * m[i]
               + (-6 * u2 + 6 * uu) * p[i + 1] + (3 * u2 - 2 * uu) * h * m[i + 1])
        return _normalize_with_derivative(g, g_u * du[:, None, None])

    def _spline_data(self):
        kt, p = self.times, self.eta
        if kt.shape[0] == 2:  # eq. 32 needs 3 keys: insert the screw midpoint
            kt = np.array([kt[0], 0.5 * (kt[0] + kt[1]), kt[1]])
            p = np.stack([p[0], dq.sclerp(p[0], p[1], 0.5), p[1]])
            p[2] = np.where(dq.dot(p[1], p[2])[..., None] < 0, -p[2], p[2])
        knots = kt.copy()
        knots[0] = 0.5 * (kt[0] + kt[1])
        knots[-1] = 0.5 * (kt[-2] + kt[-1])
        return kt, knots, p, _natural_spline(knots, p)

    def _spline(self, t, side="right"):
        """[MS] eq. 31–34: ``η(t) = normalize(γ(s(t)))``, ``γ`` the natural cubic spline."""
        kt, knots, p, m = self._cached("spline", self._spline_data)
        s, s_dot = ramp(t, kt)
        i = np.clip(np.searchsorted(knots, s, side="right") - 1, 0, knots.shape[0] - 2)
        h = (knots[i + 1] - knots[i])[:, None, None]
        x = (s - knots[i])[:, None, None]
        m0, m1 = m[i], m[i + 1]
        b = (p[i + 1] - p[i]) / h - h * (2 * m0 + m1) / 6
        g = p[i] + x * (b + x * (m0 / 2 + x * (m1 - m0) / (6 * h)))
        g_s = b + x * (m0 + x * (m1 - m0) / (2 * h))
        return _normalize_with_derivative(g, g_s * s_dot[:, None, None])

    def local(self, t, interp, derivative=True):
        """(F, J, 4, 4) local transforms, their derivatives, and the DQs ``η``, ``η̇``.

        Without ``derivative`` only the transforms are computed (the rest is None). At an interior
        key, where piecewise interpolants have a kink, the derivatives are the mean of both sides
        (what a renderer's shutter interval around the key sees): the mean of ``η̇`` and of the
        residual's ``Ṡ``, from which ``Ṁ`` follows linearly at the key's pose (a bake samples
        at the keys, so each side's matrices are not computed).
        """
        eta, eta_dot = self.dual_quaternions(t, interp, "right")
        s, s_dot = self.residual_at(t, "right")
        at_key = np.isin(t, self.times[1:-1]) if derivative else np.zeros(0, bool)
        if at_key.any():  # (interior keys: at least 3 keys, so both are new arrays, not views)
            eta_dot[at_key] = 0.5 * (eta_dot[at_key] +
                                     self.dual_quaternions(t[at_key], interp, "left")[1])
            s_dot[at_key] = 0.5 * (s_dot[at_key] + self.residual_at(t[at_key], "left")[1])
        q, tr = dq.to_rt(eta)
        rot = quat.to_matrix(q)
        m = np.zeros(eta.shape[:-1] + (4, 4))
        m[..., :3, :3] = rot @ s
        m[..., :3, 3] = tr
        m[..., 3, 3] = 1
        if not derivative:
            return m, None, None, None
        omega, v = dq.twist(eta, eta_dot, "body")  # linear in η̇ at a pose
        m_dot = np.zeros_like(m)
        m_dot[..., :3, :3] = rot @ hat(omega) @ s + rot @ s_dot
        m_dot[..., :3, 3] = (rot @ v[..., None])[..., 0]
        return m, m_dot, eta, eta_dot


class KeyedAnimation(Animation):
    """Animation given by key poses: for tests and procedural motion.

    Its ``"trs"`` interpolation (:meth:`local_transforms`) decomposes each key into rotation
    (polar factor), translation and residual scale/shear ``S`` (``M = [R·S | t]``), then slerps the
    rotation along the shorter arc and lerps translation and ``S`` per joint (for diagonal ``S``:
    the scale lerp of glTF and USD). Times outside the keys clamp.

    Parameters
    ----------
    key_times : (K,) float
        Strictly increasing key times (any time unit).
    local : (K, J, 4, 4) float
        Parent-relative joint transforms at the keys, column-vector convention.
    name : str
        Used in messages.
    refine : callable, optional
        For curves that are not linear TRS between ``key_times`` (an FBX stack's, evaluated
        exactly): ``refine(times)`` takes (F,) float64 times and returns the key times and
        (K', J, 4, 4) poses that "trs" interpolation at ``times`` reads instead of
        ``key_times`` / ``local`` (poses exact at ``times`` and at keys bracketing them), or None
        where ``key_times`` / ``local`` serve. The other interpolations always interpolate
        ``key_times`` / ``local``.
    """

    def __init__(self, key_times: npt.ArrayLike, local: npt.ArrayLike, *,
                 name: str = "KeyedAnimation",
                 refine: Callable[[np.ndarray], tuple[np.ndarray, np.ndarray] | None] | None
                 = None) -> None:
        self.name = name
        self._keys = _Keys(key_times, local, name)
        self._refine = refine
        self.key_times = self._keys.times

    def _keys_at(self, t: np.ndarray, interp: str) -> _Keys:
        """The keys that ``interp`` interpolates at times ``t``."""
        if interp == "trs" and self._refine is not None:
            refined = self._refine(t)
            if refined is not None:
                return _Keys(refined[0], refined[1], self.name)
        return self._keys

    def local_transforms(self, times: npt.ArrayLike) -> np.ndarray:
        """(F, J, 4, 4) float64 parent-relative transforms at ``times`` ("trs" interpolation)."""
        t = check_times(times)
        return self._keys_at(t, "trs").local(t, "trs", derivative=False)[0]


def _name(animation: Animation) -> str:
    return getattr(animation, "name", type(animation).__name__)


_KEYS_CACHE: "weakref.WeakKeyDictionary[Animation, _Keys]" = weakref.WeakKeyDictionary()


def _keys_of(animation: Animation, t: np.ndarray, interp: str) -> _Keys:
    """The decomposed key poses that ``interp`` interpolates ``animation`` between at times
    ``t``, computed once per animation object (a :class:`KeyedAnimation`'s own)."""
    if isinstance(animation, KeyedAnimation):
        return animation._keys_at(t, interp)
    keys = _KEYS_CACHE.get(animation)
    if keys is None:
        name = _name(animation)
        kt = np.asarray(animation.key_times, dtype=np.float64)
        if kt.ndim != 1 or kt.shape[0] == 0:
            raise InputError(f"{name}: animation has no key_times")
        keys = _KEYS_CACHE[animation] = _Keys(kt, animation.local_transforms(kt), name)
    return keys


def _motion(animation: Animation, times: npt.ArrayLike, interp: Interpolation,
            player: npt.ArrayLike | None = None
            ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Local transforms, derivatives, DQs and DQ derivatives of ``animation`` at ``times``;
    ``player``: ``animation.local_transforms(times)`` when the caller has it ("trs")."""
    _check_interp(interp)
    t = check_times(times)
    local, local_dot, eta, eta_dot = _keys_of(animation, t, interp).local(t, interp)
    if interp == "trs" and not getattr(animation, "linear_trs", True):
        raise InputError(f"{_name(animation)}: not linear TRS between its key_times (STEP or "
                         "CUBICSPLINE keys), so 'trs' velocities are unknown; use "
                         "interp='sclerp', 'dlb', 'spline' or 'catmull-rom'")
    if interp == "trs" and not isinstance(animation, KeyedAnimation):
        name = _name(animation)
        player = np.asarray(animation.local_transforms(t) if player is None else player,
                            dtype=np.float64)
        if player.shape != local.shape:
            raise InputError(f"{name}: local_transforms returned {player.shape}, expected "
                             f"{local.shape}")
        err = np.abs(player - local) / (1.0 + np.abs(player))
        bad = np.nonzero(np.any(err > _TRS_TOLERANCE, axis=(1, 2, 3)))[0]
        if bad.size:
            raise InputError(
                f"{name}: not linear TRS between its key_times (off by "
                f"{err[bad[0]].max():.3g} at time {t[bad[0]]}), so 'trs' velocities are unknown; "
                "use interp='sclerp', 'dlb', 'spline' or 'catmull-rom'")
        local = player
    return local, local_dot, eta, eta_dot


# ---------------------------------------------------------------------------------------------
# public sampling and kinematics


def sample(animation: Animation, times: npt.ArrayLike,
           interp: Interpolation = DEFAULT_INTERP) -> np.ndarray:
    """Local joint transforms of ``animation`` at ``times``.

    Parameters
    ----------
    animation : Animation
        Needs ``key_times`` and ``local_transforms``.
    times : (F,) float
        In the animation's time unit; clamped to the key range.
    interp : {"trs", "sclerp", "dlb", "spline", "catmull-rom"}
        See the module docstring. "trs" returns ``animation.local_transforms(times)``.

    Returns
    -------
    (F, J, 4, 4) float64
        Parent-relative transforms, column-vector convention.
    """
    _check_interp(interp)
    t = check_times(times)
    if interp == "trs":
        return np.asarray(animation.local_transforms(t), dtype=np.float64)
    return _keys_of(animation, t, interp).local(t, interp, derivative=False)[0]


def sample_with_derivative(animation: Animation, times: npt.ArrayLike,
                           interp: Interpolation = DEFAULT_INTERP, *,
                           local: npt.ArrayLike | None = None
                           ) -> tuple[np.ndarray, np.ndarray]:
    """Local joint transforms and their analytic time derivatives.

    Parameters
    ----------
    animation, times, interp
        As :func:`sample`. For "trs" the animation must interpolate linearly in TRS between its
        ``key_times`` (glTF LINEAR, USD); otherwise ``ValueError``.
    local : (F, J, 4, 4) float, optional
        ``sample(animation, times, "trs")`` when the caller already has it (not sampled again;
        other interpolations ignore it).

    Returns
    -------
    local : (F, J, 4, 4) float64
        Equal to ``sample(animation, times, interp)``.
    local_dot : (F, J, 4, 4) float64
        ``d local / dt`` per unit of the animation's time; zero outside the key range.
    """
    local, local_dot, _, _ = _motion(animation, times, interp, local)
    return local, local_dot


class TransformTrack(abc.ABC):
    """One 4×4 transform over time with its analytic time derivative (e.g. a USD prim's space
    relative to its skeleton's). Loaders implement it; :meth:`dqskin.Scene.skin` applies it to
    the skinned results and differentiates through it for velocities.

    Attributes
    ----------
    key_times : (K,) float64
        Times where the transform's inputs have samples.
    """

    key_times: np.ndarray

    @abc.abstractmethod
    def with_derivative(self, times: npt.ArrayLike) -> tuple[np.ndarray, np.ndarray]:
        """(F, 4, 4) float64 transforms at ``times`` and their time derivatives (per unit time),
        column-vector convention."""

    def at(self, times: npt.ArrayLike) -> np.ndarray:
        """(F, 4, 4) float64 transforms at ``times``."""
        return self.with_derivative(times)[0]


class Deformer(abc.ABC):
    """Rest points (and normals, tangents) that change over time before skinning: time-sampled
    points, USD blend shapes, glTF morph targets. Loaders subclass it; :meth:`dqskin.Scene.skin`
    uses it when ``blend_shapes``."""

    @abc.abstractmethod
    def points_at(self, times: npt.ArrayLike) -> np.ndarray:
        """(F, V, 3) float32 rest points at ``times``, mesh space."""

    @abc.abstractmethod
    def point_velocities_at(self, times: npt.ArrayLike) -> np.ndarray:
        """(F, V, 3) float64 ``d points / dt`` per unit time, the derivative of the interpolant
        :meth:`points_at` evaluates (at an interior key: the mean of both sides)."""

    def normals_at(self, times: npt.ArrayLike) -> np.ndarray | None:
        """(F, N, 3) float32 rest normals at ``times`` (not normalized), or None when the normals
        do not change."""
        return None

    def tangents_at(self, times: npt.ArrayLike) -> np.ndarray | None:
        """(F, V, 3) float32 rest tangent directions at ``times`` (not normalized), or None when
        the tangents do not change."""
        return None


def segment_rates(key_times: npt.ArrayLike, values_at: Callable[[int], npt.ArrayLike],
                  times: npt.ArrayLike) -> list[np.ndarray]:
    """Derivative of the linear interpolant through keyed values, as :class:`Deformer` needs.

    Parameters
    ----------
    key_times : (K,) float
        Strictly increasing.
    values_at : callable
        ``values_at(k)`` → the value (any shape) at key ``k``.
    times : (F,) float

    Returns
    -------
    list of F arrays
        ``(value[k+1] − value[k]) / (t[k+1] − t[k])`` of the interval ``[t[k], t[k+1])`` holding
        each time (the last interval at the last key; at an interior key, where the interpolant
        has a kink, the mean of both sides), zero outside the keys or with one key.
    """
    kt = np.asarray(key_times, dtype=np.float64)
    t = check_times(times)
    cache: dict[int, np.ndarray] = {}

    def rate(k: int) -> np.ndarray:
        if k not in cache:
            lo, hi = (np.asarray(values_at(i), np.float64) for i in (k, k + 1))
            cache[k] = (hi - lo) / (kt[k + 1] - kt[k])
        return cache[k]

    out: list[np.ndarray | None] = []
    for ti in t:
        if kt.shape[0] < 2 or ti < kt[0] or ti > kt[-1]:
            out.append(None)
            continue
        k = int(np.clip(np.searchsorted(kt, ti, side="right") - 1, 0, kt.shape[0] - 2))
        inner_key = 0 < k and ti == kt[k]
        out.append(0.5 * (rate(k - 1) + rate(k)) if inner_key else rate(k))
    shape = next((r.shape for r in out if r is not None), np.shape(values_at(0)))
    return [np.zeros(shape) if r is None else r for r in out]
