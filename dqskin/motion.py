"""Joint motion between keys: pose interpolation with dual quaternions and analytic velocities.

Sampling
--------
:func:`sample` evaluates an :class:`~dqskin.scene.Animation` at any times with one of
:data:`INTERPOLATIONS`:

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

Velocities
----------
Every interpolant is differentiated analytically (no finite differences): ``η̇`` from the
interpolant's derivative (the derivative of the dual-number normalization for the normalized
ones), the twist ``φ = η⁻¹·η̇ = ω/2 + ε·v/2`` (Montgomery-Smith eq. 25–26, :func:`dqskin.dq.twist`),
``Ṁ = [R·[ω]×·S + R·Ṡ | R·v]``. For ``"trs"`` the keyed TRS interpolant is differentiated (slerp:
``q̇ = q·log(qₖ*·qₖ₊₁)/Δt``; lerp: ``(xₖ₊₁ − xₖ)/Δt``), which reproduces any linear TRS player
whose key times are all in ``animation.key_times`` (glTF LINEAR, USD); STEP or CUBICSPLINE clips
are detected and rejected. World transforms are differentiated through the hierarchy by the
product rule, ``Ẇⱼ = Ẇₚ·Lⱼ + Wₚ·L̇ⱼ`` (:func:`forward_kinematics_derivative`), skinning transforms
as ``Ȧ = Ẇ·B⁻¹``, and skinned points by the chain rule through LBS or DQS
(:func:`skinned_velocities`, Warp kernels in :mod:`dqskin.kernels.velocity`).

Derivatives are per unit of the animation's time (USD time codes, glTF seconds) unless stated;
:func:`scene_velocities` converts to per second. At a key time the derivative is the one of the
interval starting there (of the last interval at the last key).

References
----------
[K] B. Kenwright, "Dual-Quaternions: From Classical Mechanics to Computer Graphics and Beyond",
    2012 (shared/references/000_e688072581e8ee3b.txt).
[MS] S. Montgomery-Smith and C. Shy, "An Introduction to Using Dual Quaternions to Study
    Kinematics", 2023 (shared/references/003_d8d7d9932a992693.txt).
"""

import weakref

import numpy as np
import warp as wp

from . import dq, quat
from ._warp import FRAME_BLOCK, launch_blocks, resolve_device
from .kernels import velocity as KV
from .kernels.dqmath import vec8
from .kernels.skin import mat34
from .scene import Animation
from .skeleton import check_parents
from .skinning import check_influences

__all__ = [
    "INTERPOLATIONS",
    "KeyedAnimation",
    "ramp",
    "sample",
    "sample_with_derivative",
    "forward_kinematics_derivative",
    "joint_twists",
    "skinning_transforms_with_derivative",
    "skinned_velocities",
    "scene_velocities",
]

INTERPOLATIONS = ("trs", "sclerp", "dlb", "spline", "catmull-rom")
"""Pose interpolation methods accepted by :func:`sample` (see the module docstring)."""

_RESIDUAL_TOLERANCE = 1e-6  # as kernels/skin.py: residuals within this of I count as rigid
_TRS_TOLERANCE = 1e-5  # relative: "trs" velocities need the player to be linear TRS between keys
_FD_STEP = 1e-3  # time units; only for opaque callables (output transforms, blend-shaped points)


# ---------------------------------------------------------------------------------------------
# small linear-algebra pieces


def _hat(w):
    """(..., 3) → (..., 3, 3) cross-product matrices ``[w]×`` ([MS] eq. 21)."""
    z = np.zeros_like(w[..., 0])
    return np.stack([np.stack([z, -w[..., 2], w[..., 1]], -1),
                     np.stack([w[..., 2], z, -w[..., 0]], -1),
                     np.stack([-w[..., 1], w[..., 0], z], -1)], -2)


def _vee(k):
    """Axial vector of the skew-symmetric part of (..., 3, 3) ``k``."""
    return 0.5 * np.stack([k[..., 2, 1] - k[..., 1, 2], k[..., 0, 2] - k[..., 2, 0],
                           k[..., 1, 0] - k[..., 0, 1]], -1)


def _pure(v):
    """3-vectors as pure quaternions ``(0, v)``."""
    return np.concatenate([np.zeros_like(v[..., :1]), v], -1)


def _polar(a):
    """Polar split ``a = R·S`` of (..., 3, 3) float64: ``R`` proper rotation, ``S`` symmetric.

    As the skinning and FK kernels (``GfMatrix4d::Factor``): ``R = U·Vᵀ`` from the SVD, negated
    when ``det a < 0`` (a reflection then lives in ``S``).
    """
    u, _, vt = np.linalg.svd(a)
    r = u @ vt
    r = np.where((np.linalg.det(r) < 0)[..., None, None], -r, r)
    return r, np.swapaxes(r, -1, -2) @ a


def _polar_derivative(r, s, a_dot):
    """Derivative of the polar split: body angular velocity ``ω`` (``Ṙ = R·[ω]×``) and ``Ṡ``.

    From ``Rᵀ·Ȧ = [ω]×·S + Ṡ`` with ``Ṡ`` symmetric: the skew part gives
    ``[ω]×·S + S·[ω]× = [((tr S)·I − S)·ω]×``.
    """
    x = np.swapaxes(r, -1, -2) @ a_dot
    lhs = np.trace(s, axis1=-2, axis2=-1)[..., None, None] * np.eye(3) - s
    omega = np.linalg.solve(lhs, 2 * _vee(x)[..., None])[..., 0]
    return omega, x - _hat(omega) @ s


def _times(times, name="times"):
    t = np.atleast_1d(np.asarray(times, dtype=np.float64))
    if t.ndim != 1 or not np.all(np.isfinite(t)):
        raise ValueError(f"{name}: expected a 1-D array of finite times, got shape {t.shape}")
    return t


def _check_interp(interp):
    if interp not in INTERPOLATIONS:
        raise ValueError(f"interp must be one of {INTERPOLATIONS}, got {interp!r}")


def _normalize_with_derivative(g, g_dot):
    """``normalize(g)`` ([MS] eq. 14) and its derivative along ``g_dot``, both (..., 8).

    With ``n = |r|``, ``c = r·d``: ``η = r/n + ε·(d/n − c·r/n³)``.
    """
    r, d = g[..., :4], g[..., 4:]
    rd, dd = g_dot[..., :4], g_dot[..., 4:]
    n2 = np.sum(r * r, -1, keepdims=True)
    if np.any(n2 == 0):
        raise ValueError("interpolated dual quaternion has a zero real part (keys too far apart)")
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


def ramp(times, key_times):
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
    t = _times(times)
    k = np.asarray(key_times, dtype=np.float64)
    if k.ndim != 1 or k.shape[0] < 3:
        raise ValueError(f"key_times: ramp needs at least 3 keys, got shape {k.shape}")
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


class _Keys:
    """Key poses split into sign-aligned unit DQs, rotations, translations and residuals."""

    def __init__(self, key_times, local, where):
        kt = np.asarray(key_times, dtype=np.float64)
        if kt.ndim != 1 or kt.shape[0] == 0 or not np.all(np.isfinite(kt)):
            raise ValueError(f"{where}: key_times must be a non-empty 1-D array of finite times, "
                             f"got shape {kt.shape}")
        if np.any(np.diff(kt) <= 0):
            raise ValueError(f"{where}: key_times must be strictly increasing")
        m = np.asarray(local, dtype=np.float64)
        if m.ndim != 4 or m.shape[0] != kt.shape[0] or m.shape[2:] != (4, 4):
            raise ValueError(f"{where}: key transforms must be ({kt.shape[0]}, J, 4, 4), "
                             f"got {m.shape}")
        if not np.all(np.isfinite(m)):
            raise ValueError(f"{where}: key transforms have NaN or infinite entries")
        self.times = kt
        self.joint_count = m.shape[1]
        rot, self.residual = _polar(m[..., :3, :3])
        q = quat.from_matrix(rot)
        if kt.shape[0] > 1:
            flips = np.where(quat.dot(q[:-1], q[1:]) < 0, -1.0, 1.0)
            q[1:] *= np.cumprod(flips, axis=0)[..., None]
        self.q = q
        self.t = m[..., :3, 3].copy()
        self.eta = dq.from_rt(q, self.t)
        self._cache = {}

    def segments(self, t):
        """Interval index ``i``, parameter ``u`` in [0, 1] and ``du/dt`` (0 outside the keys)."""
        kt = self.times
        if kt.shape[0] == 1:
            z = np.zeros(t.shape)
            return np.zeros(t.shape, dtype=np.int64), z, z
        i = np.clip(np.searchsorted(kt, t, side="right") - 1, 0, kt.shape[0] - 2)
        dt = kt[i + 1] - kt[i]
        u = np.clip((t - kt[i]) / dt, 0.0, 1.0)
        du = np.where((t >= kt[0]) & (t <= kt[-1]), 1.0 / dt, 0.0)
        return i, u, du

    def _cached(self, name, build):
        if name not in self._cache:
            self._cache[name] = build()
        return self._cache[name]

    def residual_at(self, t):
        """(F, J, 3, 3) residuals and derivatives, linear between keys."""
        if self.times.shape[0] == 1:
            s = np.broadcast_to(self.residual, (t.shape[0],) + self.residual.shape[1:])
            return s, np.zeros_like(s)
        i, u, du = self.segments(t)
        s0, s1 = self.residual[i], self.residual[i + 1]
        uu = u[:, None, None, None]
        return (1 - uu) * s0 + uu * s1, (s1 - s0) * du[:, None, None, None]

    def dual_quaternions(self, t, interp):
        """(F, J, 8) interpolated unit DQs ``η`` and their derivatives ``η̇``."""
        if self.times.shape[0] == 1:
            eta = np.broadcast_to(self.eta, (t.shape[0],) + self.eta.shape[1:])
            return eta, np.zeros_like(eta)
        return getattr(self, "_" + interp.replace("-", "_"))(t)

    def _trs(self, t):
        """Rotation slerp, translation lerp: ``q = qₖ·exp(u·Lₖ)``, ``Lₖ = log(qₖ*·qₖ₊₁)``."""
        log = self._cached("rot_log", lambda: quat.log(
            quat.mul(quat.conjugate(self.q[:-1]), self.q[1:])) * np.array([0.0, 1, 1, 1]))
        i, u, du = self.segments(t)
        lk = log[i]
        q = quat.mul(self.q[i], quat.exp(u[:, None, None] * lk))
        q_dot = quat.mul(q, lk) * du[:, None, None]
        uu = u[:, None, None]
        tr = (1 - uu) * self.t[i] + uu * self.t[i + 1]
        tr_dot = (self.t[i + 1] - self.t[i]) * du[:, None, None]
        eta = dq.from_rt(q, tr)
        dual_dot = 0.5 * (quat.mul(_pure(tr_dot), q) + quat.mul(_pure(tr), q_dot))
        return eta, np.concatenate([q_dot, dual_dot], -1)

    def _sclerp(self, t):
        """``ηₖ·exp(u·ξₖ)``, ``ξₖ = log(ηₖ*·ηₖ₊₁)``; ``η̇ = η·ξₖ/Δt`` ([MS] eq. 25, 41)."""
        xi = self._cached("screw_log", lambda: dq.log(dq.mul(
            dq.conjugate_quat(self.eta[:-1]), self.eta[1:])) * np.array([0.0, 1, 1, 1, 0, 1, 1, 1]))
        i, u, du = self.segments(t)
        eta = dq.mul(self.eta[i], dq.exp(u[:, None, None] * xi[i]))
        return eta, dq.mul(eta, xi[i]) * du[:, None, None]

    def _dlb(self, t):
        i, u, du = self.segments(t)
        a, b = self.eta[i], self.eta[i + 1]
        uu = u[:, None, None]
        return _normalize_with_derivative((1 - uu) * a + uu * b, (b - a) * du[:, None, None])

    def _catmull_rom(self, t):
        """Cubic Hermite per component with Catmull-Rom tangents, normalized."""
        kt, p = self.times, self.eta

        def tangents():
            m = np.empty_like(p)
            m[0] = (p[1] - p[0]) / (kt[1] - kt[0])
            m[-1] = (p[-1] - p[-2]) / (kt[-1] - kt[-2])
            m[1:-1] = (p[2:] - p[:-2]) / (kt[2:] - kt[:-2])[:, None, None]
            return m

        m = self._cached("catmull_rom", tangents)
        i, u, du = self.segments(t)
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

    def _spline(self, t):
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

        Without ``derivative`` only the transforms are computed (the rest is None).
        """
        eta, eta_dot = self.dual_quaternions(t, interp)
        s, s_dot = self.residual_at(t)
        q, tr = dq.to_rt(eta)
        rot = quat.to_matrix(q)
        m = np.zeros(eta.shape[:-1] + (4, 4))
        m[..., :3, :3] = rot @ s
        m[..., :3, 3] = tr
        m[..., 3, 3] = 1
        if not derivative:
            return m, None, None, None
        omega, v = dq.twist(eta, eta_dot, "body")
        m_dot = np.zeros_like(m)
        m_dot[..., :3, :3] = rot @ _hat(omega) @ s + rot @ s_dot
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
    """

    def __init__(self, key_times, local, *, name="KeyedAnimation"):
        self.name = name
        self._keys = _Keys(key_times, local, name)
        self.key_times = self._keys.times

    def local_transforms(self, times):
        """(F, J, 4, 4) float64 parent-relative transforms at ``times`` ("trs" interpolation)."""
        return self._keys.local(_times(times), "trs", derivative=False)[0]


def _name(animation):
    return getattr(animation, "name", type(animation).__name__)


_KEYS_CACHE = weakref.WeakKeyDictionary()


def _keys_of(animation):
    """The decomposed key poses of ``animation``, computed once per animation object."""
    if isinstance(animation, KeyedAnimation):
        return animation._keys
    keys = _KEYS_CACHE.get(animation)
    if keys is None:
        name = _name(animation)
        kt = np.asarray(animation.key_times, dtype=np.float64)
        if kt.ndim != 1 or kt.shape[0] == 0:
            raise ValueError(f"{name}: animation has no key_times")
        keys = _KEYS_CACHE[animation] = _Keys(kt, animation.local_transforms(kt), name)
    return keys


def _motion(animation, times, interp):
    """Local transforms, derivatives, DQs and DQ derivatives of ``animation`` at ``times``."""
    _check_interp(interp)
    t = _times(times)
    local, local_dot, eta, eta_dot = _keys_of(animation).local(t, interp)
    if interp == "trs" and not isinstance(animation, KeyedAnimation):
        name = _name(animation)
        player = np.asarray(animation.local_transforms(t), dtype=np.float64)
        if player.shape != local.shape:
            raise ValueError(f"{name}: local_transforms returned {player.shape}, expected "
                             f"{local.shape}")
        err = np.abs(player - local) / (1.0 + np.abs(player))
        bad = np.nonzero(np.any(err > _TRS_TOLERANCE, axis=(1, 2, 3)))[0]
        if bad.size:
            raise ValueError(
                f"{name}: not linear TRS between its key_times (off by "
                f"{err[bad[0]].max():.3g} at time {t[bad[0]]}), so 'trs' velocities are unknown; "
                "use interp='sclerp', 'dlb', 'spline' or 'catmull-rom'")
        local = player
    return local, local_dot, eta, eta_dot


# ---------------------------------------------------------------------------------------------
# public sampling and kinematics


def sample(animation, times, interp="trs"):
    """Local joint transforms of ``animation`` at ``times``.

    Parameters
    ----------
    animation : dqskin.scene.Animation
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
    t = _times(times)
    if interp == "trs":
        return np.asarray(animation.local_transforms(t), dtype=np.float64)
    return _keys_of(animation).local(t, interp, derivative=False)[0]


def sample_with_derivative(animation, times, interp="trs"):
    """Local joint transforms and their analytic time derivatives.

    Parameters
    ----------
    animation, times, interp
        As :func:`sample`. For "trs" the animation must interpolate linearly in TRS between its
        ``key_times`` (glTF LINEAR, USD); otherwise ``ValueError``.

    Returns
    -------
    local : (F, J, 4, 4) float64
        Equal to ``sample(animation, times, interp)``.
    local_dot : (F, J, 4, 4) float64
        ``d local / dt`` per unit of the animation's time; zero outside the key range.
    """
    local, local_dot, _, _ = _motion(animation, times, interp)
    return local, local_dot


def forward_kinematics_derivative(parents, local, local_dot):
    """World transforms and their derivatives by the product rule, float64.

    ``Wⱼ = Wₚ·Lⱼ`` and ``Ẇⱼ = Ẇₚ·Lⱼ + Wₚ·L̇ⱼ`` (roots: ``Wⱼ = Lⱼ``), exact also with scale or shear.

    Parameters
    ----------
    parents : (J,) int
        Parents first, -1 for roots.
    local, local_dot : (..., J, 4, 4) float
        Parent-relative transforms and their time derivatives.

    Returns
    -------
    world, world_dot : (..., J, 4, 4) float64
        Skeleton-space transforms and their derivatives.
    """
    par = check_parents(parents)
    loc = np.asarray(local, dtype=np.float64)
    loc_dot = np.asarray(local_dot, dtype=np.float64)
    J = par.shape[0]
    if loc.ndim < 3 or loc.shape[-3:] != (J, 4, 4) or loc_dot.shape != loc.shape:
        raise ValueError(f"local {loc.shape} and local_dot {loc_dot.shape} must both be "
                         f"(..., {J}, 4, 4)")
    world = np.empty_like(loc)
    world_dot = np.empty_like(loc)
    for j, p in enumerate(par):
        if p < 0:
            world[..., j, :, :] = loc[..., j, :, :]
            world_dot[..., j, :, :] = loc_dot[..., j, :, :]
        else:
            world[..., j, :, :] = world[..., p, :, :] @ loc[..., j, :, :]
            world_dot[..., j, :, :] = (world_dot[..., p, :, :] @ loc[..., j, :, :]
                                       + world[..., p, :, :] @ loc_dot[..., j, :, :])
    return world, world_dot


def joint_twists(animation, times, interp="trs", *, frame="local", parents=None):
    """Angular and linear velocity of every joint, from the interpolant's analytic derivative.

    Parameters
    ----------
    animation, times, interp
        As :func:`sample_with_derivative`.
    frame : {"local", "world"}
        ``"local"``: the body twist ``φ = η⁻¹·η̇ = ω/2 + ε·v/2`` ([MS] eq. 25–26) of each joint's
        parent-relative rigid transform ``η`` (rotation and translation; a residual scale is not
        part of it): ``ω`` and ``v`` in the joint's own axes, ``ṫ = R·v`` the velocity of the joint
        origin in the parent's axes (eq. 23). ``"world"``: through the hierarchy
        (:func:`forward_kinematics_derivative`): ``ω`` the angular velocity in skeleton axes, the
        axial vector of ``Ȧ·A⁻¹`` for the world linear part ``A`` (``Ṙ·Rᵀ`` when rigid), and ``v``
        the skeleton-space velocity of the joint origin, ``d/dt`` of the world translation.
    parents : (J,) int
        Required for ``frame="world"``.

    Returns
    -------
    omega : (F, J, 3) float64
        Angular velocity [rad per unit of the animation's time].
    v : (F, J, 3) float64
        Linear velocity [length units per unit of the animation's time].
    """
    if frame == "local":
        _, _, eta, eta_dot = _motion(animation, times, interp)
        return dq.twist(eta, eta_dot, "body")
    if frame != "world":
        raise ValueError(f'frame must be "local" or "world", got {frame!r}')
    if parents is None:
        raise ValueError('frame="world" needs parents')
    local, local_dot, _, _ = _motion(animation, times, interp)
    world, world_dot = forward_kinematics_derivative(parents, local, local_dot)
    lin = world[..., :3, :3]
    omega = _vee(world_dot[..., :3, :3] @ np.linalg.inv(lin))
    return omega, world_dot[..., :3, 3].copy()


def skinning_transforms_with_derivative(skeleton, animation, times, interp="trs"):
    """Bind-relative skinning transforms ``W·B⁻¹`` and their derivatives ``Ẇ·B⁻¹``, float64.

    Parameters
    ----------
    skeleton : dqskin.skeleton.Skeleton
    animation : dqskin.scene.Animation or None
        None holds the skeleton at rest (zero derivative).
    times : (F,) float
    interp : str
        As :func:`sample`.

    Returns
    -------
    xforms, xforms_dot : (F, J, 4, 4) float64
        Column-vector convention; derivatives per unit of the animation's time.
    """
    t = _times(times)
    if animation is None:
        rest = skeleton.rest_transforms
        local = np.broadcast_to(rest, (t.shape[0],) + rest.shape)
        local_dot = np.zeros(local.shape)
    else:
        local, local_dot = sample_with_derivative(animation, t, interp)
    world, world_dot = forward_kinematics_derivative(skeleton.parents, local, local_dot)
    inv = skeleton.inverse_bind_transforms
    return world @ inv, world_dot @ inv


# ---------------------------------------------------------------------------------------------
# skinned point velocities


def _frames_of(name, a, frames, count):
    a = np.asarray(a, dtype=np.float64)
    if a.ndim == 2:
        a = a[None]
    if a.ndim != 3 or a.shape[0] not in (1, frames) or a.shape[1:] != (count, 3):
        raise ValueError(f"{name}: expected ({count}, 3) or ({frames}, {count}, 3), got {a.shape}")
    return a


def skinned_velocities(points, joint_indices, joint_weights, skinning_transforms,
                       skinning_transform_derivatives, method="lbs", *, geom_bind_transform=None,
                       point_velocities=None, device=None):
    """Velocities of LBS- or DQS-skinned points, by the chain rule (Warp, one thread per vertex).

    Same skinning semantics as :func:`dqskin.skin_points` (UsdSkel): weights used as given, DQS
    with sign alignment to the largest-weight influence and the residual (scale/shear) path
    ``Σ wᵢ·Sᵢ·p`` on frames where any joint has one. The joint DQs and their derivatives come from
    the polar split ``A = R·S`` and its derivative (``Rᵀ·Ȧ = [ω]×·S + Ṡ``) in float64.

    Parameters
    ----------
    points : (V, 3) or (F, V, 3) float
        Rest points, mesh space.
    joint_indices, joint_weights : (V, K) int, (V, K) float
    skinning_transforms : (J, 4, 4) or (F, J, 4, 4) float
        Bind-relative transforms ``A`` (world ∘ inverse bind), column-vector convention.
    skinning_transform_derivatives : same shape
        ``dA/dt``.
    method : {"lbs", "dqs"}
    geom_bind_transform : (4, 4) float, optional
        Mesh space → bind space (constant).
    point_velocities : (V, 3) or (F, V, 3) float, optional
        ``d points / dt`` in mesh space (e.g. from blend shapes); zero by default.
    device : str, optional
        Warp device.

    Returns
    -------
    (V, 3) or (F, V, 3) float32
        ``d/dt`` of the skinned points, skeleton space, per unit of time of the derivatives.
    """
    if method not in ("lbs", "dqs"):
        raise ValueError(f'method must be "lbs" or "dqs", got {method!r}')
    x = np.asarray(skinning_transforms, dtype=np.float64)
    x_dot = np.asarray(skinning_transform_derivatives, dtype=np.float64)
    if x.ndim not in (3, 4) or x.shape[-2:] != (4, 4) or x_dot.shape != x.shape:
        raise ValueError(f"skinning_transforms {x.shape} and skinning_transform_derivatives "
                         f"{x_dot.shape} must both be (J, 4, 4) or (F, J, 4, 4)")
    batched = x.ndim == 4
    if not batched:
        x, x_dot = x[None], x_dot[None]
    frames, joints = x.shape[:2]
    idx, wts = check_influences(joint_indices, joint_weights, joint_count=joints)
    count = idx.shape[0]
    pts = _frames_of("points", points, frames, count)
    vel = (np.zeros((1, count, 3)) if point_velocities is None else
           _frames_of("point_velocities", point_velocities, frames, count))
    g = np.eye(4) if geom_bind_transform is None else np.asarray(geom_bind_transform, np.float64)
    if g.shape != (4, 4):
        raise ValueError(f"geom_bind_transform: expected (4, 4), got {g.shape}")
    pts = pts @ g[:3, :3].T + g[:3, 3]
    vel = vel @ g[:3, :3].T
    order = np.argsort(-wts, axis=1, kind="stable")  # slot 0 = antipodality pivot, as Skinner
    idx, wts = np.take_along_axis(idx, order, 1), np.take_along_axis(wts, order, 1)

    d = resolve_device(device)
    arrays = [wp.array(pts.astype(np.float32), dtype=wp.vec3, device=d),
              wp.array(vel.astype(np.float32), dtype=wp.vec3, device=d),
              wp.array(idx.astype(np.int32), dtype=wp.int32, device=d),
              wp.array(wts, dtype=wp.float32, device=d)]
    if method == "lbs":
        kernel = KV.lbs_velocity_kernel
        arrays += [wp.array(np.ascontiguousarray(a[..., :3, :], dtype=np.float32), dtype=mat34,
                            device=d) for a in (x, x_dot)]
    else:
        kernel = KV.dqs_velocity_kernel
        rot, res = _polar(x[..., :3, :3])
        omega, res_dot = _polar_derivative(rot, res, x_dot[..., :3, :3])
        q = quat.from_matrix(rot)
        q_dot = 0.5 * quat.mul(q, _pure(omega))
        tr, tr_dot = x[..., :3, 3], x_dot[..., :3, 3]
        eta = dq.from_rt(q, tr)
        eta_dot = np.concatenate(
            [q_dot, 0.5 * (quat.mul(_pure(tr_dot), q) + quat.mul(_pure(tr), q_dot))], -1)
        has_res = (np.any(np.abs(res - np.eye(3)) > _RESIDUAL_TOLERANCE, axis=(1, 2, 3))
                   | np.any(np.abs(res_dot) > _RESIDUAL_TOLERANCE, axis=(1, 2, 3)))
        arrays += [wp.array(eta.astype(np.float32), dtype=vec8, device=d),
                   wp.array(eta_dot.astype(np.float32), dtype=vec8, device=d),
                   wp.array(res.astype(np.float32), dtype=wp.mat33, device=d),
                   wp.array(res_dot.astype(np.float32), dtype=wp.mat33, device=d),
                   wp.array(has_res.astype(np.int32), dtype=wp.int32, device=d)]
    out = wp.empty((frames, count), dtype=wp.vec3, device=d)

    def launch(block_offset, blocks, offset, n):
        wp.launch(kernel, dim=(blocks, n), inputs=arrays + [FRAME_BLOCK, block_offset, offset],
                  outputs=[out], device=d)

    if count:
        launch_blocks(launch, count, frames, d)
    res = out.numpy()
    return res if batched else res[0]


def scene_velocities(scene, times=None, method=None, interp="trs", time_codes_per_second=None, *,
                     device=None):
    """Per-mesh point velocities of a scene, in units per second, for motion blur.

    Joint motion is differentiated analytically (:func:`skinning_transforms_with_derivative`) and
    pushed through the skinning by the chain rule (:func:`skinned_velocities`); the velocities are
    those of the motion that ``sample(animation, times, interp)`` describes (for "trs": what
    :meth:`dqskin.scene.Scene.skin` shows). Two inputs are opaque callables and are differentiated
    by a central difference of step 1e-3 time units: a time-varying ``mesh.output_transforms``
    and blend-shaped rest points ``mesh.rest_points_at``.

    Parameters
    ----------
    scene : dqskin.scene.Scene
    times : (F,) float, optional
        Scene time unit (USD time codes, glTF seconds); default ``scene.times``.
    method : {"lbs", "dqs"} or None
        None uses each mesh's ``skinning_method``.
    interp : str
        As :func:`sample`.
    time_codes_per_second : float, optional
        Default ``scene.time_codes_per_second`` (1 for glTF).

    Returns
    -------
    dict name → (F, V, 3) float32
        Velocities in each mesh's output space, length units per second.
    """
    t = scene.times if times is None else times
    t = _times(t)
    tcps = float(scene.time_codes_per_second if time_codes_per_second is None
                 else time_codes_per_second)
    if not np.isfinite(tcps) or tcps <= 0:
        raise ValueError(f"time_codes_per_second must be positive, got {tcps}")
    xforms = {}
    out = {}
    h = _FD_STEP
    for m in scene.meshes:
        if m.skeleton not in xforms:
            xforms[m.skeleton] = skinning_transforms_with_derivative(
                scene.skeletons[m.skeleton], scene.animations[m.skeleton], t, interp)
        x, x_dot = xforms[m.skeleton]
        meth = method or m.skinning_method
        rest = m.points if m.rest_points_at is None else np.asarray(m.rest_points_at(t))
        rest_dot = (None if m.rest_points_at is None else
                    (np.asarray(m.rest_points_at(t + h), np.float64)
                     - np.asarray(m.rest_points_at(t - h), np.float64)) / (2 * h))
        v = skinned_velocities(rest, m.joint_indices, m.joint_weights, x, x_dot, meth,
                               geom_bind_transform=m.geom_bind_transform,
                               point_velocities=rest_dot, device=device).astype(np.float64)
        if m.output_transforms is not None:
            o = np.asarray(m.output_transforms(t), np.float64)
            o_dot = (np.asarray(m.output_transforms(t + h), np.float64)
                     - np.asarray(m.output_transforms(t - h), np.float64)) / (2 * h)
            v = np.einsum("fij,fvj->fvi", o[:, :3, :3], v)
            if np.any(o_dot):
                p = scene.skinner(m, device).skin(
                    x, meth, points=None if m.rest_points_at is None else rest)
                v += np.einsum("fij,fvj->fvi", o_dot[:, :3, :3], p) + o_dot[:, None, :3, 3]
        out[m.name] = (v * tcps).astype(np.float32)
    return out
