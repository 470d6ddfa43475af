"""Array shape checks shared by the API: one place that turns user arrays into the shapes the
engine works with, with errors naming the argument."""

from collections.abc import Sequence

import numpy as np
import numpy.typing as npt

from .errors import InputError

__all__ = ["as_array", "as_float", "as_real", "concat", "frames_of"]


def as_real(name: str, x: npt.ArrayLike, dtype: npt.DTypeLike | None = None) -> np.ndarray:
    """``x`` as a real-valued (bool, integer or float) array, of ``dtype`` when given; ValueError
    naming ``name`` for anything else (strings, complex numbers -- never silently truncated to
    their real part --, ragged nesting, objects)."""
    try:
        a = np.asarray(x)
        if a.dtype.kind == "O":
            a = np.asarray(x, dtype=np.float64)
    except (TypeError, ValueError, OverflowError) as exc:
        raise InputError(f"{name}: not an array of numbers ({' '.join(str(exc).split())})") \
            from None
    if a.dtype.kind not in "biuf":
        raise InputError(f"{name}: expected real numbers, got {a.dtype} values")
    return a if dtype is None else a.astype(dtype, copy=False)


def as_array(name: str, x: npt.ArrayLike, dtype: npt.DTypeLike | None,
             tail: Sequence[int | None]) -> np.ndarray:
    """``x`` as an array of ``dtype`` whose trailing axes are ``tail`` (None: any length).

    Raises ValueError naming ``name`` with the expected ``(..., tail)`` shape otherwise.
    """
    a = as_real(name, x, dtype)
    n = len(tail)
    if a.ndim < n or any(t is not None and a.shape[a.ndim - n + i] != t
                         for i, t in enumerate(tail)):
        want = "(..., " + ", ".join("n" if t is None else str(t) for t in tail) + ")"
        raise InputError(f"{name}: expected shape {want}, got {a.shape}")
    return a


def frames_of(name: str, a: npt.ArrayLike, frames: int | None = None, count: int | None = None, *,
              dtype: npt.DTypeLike = np.float64, finite: bool = False,
              broadcast: bool = True) -> tuple[np.ndarray, bool]:
    """Per-frame rows of 3-vectors: ``(N, 3)`` or ``(F, N, 3)`` → ``(Fp, N, 3)`` of ``dtype``.

    Parameters
    ----------
    name : str
        Used in messages (e.g. ``"points"``, ``"velocities['/Root/Mesh']"``).
    a : (N, 3) or (F, N, 3) array_like
    frames : int, optional
        Required frame count F: the result has ``Fp == frames``, or ``Fp == 1`` for a single
        ``(N, 3)`` array when ``broadcast``.
    count : int, optional
        Required row count N.
    finite : bool
        Reject NaN and infinite values.
    broadcast : bool
        Accept one frame for all (``Fp == 1``); otherwise exactly ``frames`` frames.

    Returns
    -------
    (Fp, N, 3) array of ``dtype``, and whether ``a`` had a frame axis.
    """
    x = as_real(name, a, dtype)
    batched = x.ndim == 3
    if x.ndim == 2:
        x = x[None]
    frame_ok = frames is None or x.shape[0] == frames or (broadcast and x.shape[0] == 1)
    if x.ndim != 3 or x.shape[2] != 3 or not frame_ok or (count is not None
                                                         and x.shape[1] != count):
        n = "N" if count is None else count
        want = (f"({n}, 3) or (F, {n}, 3)" if frames is None else
                f"({n}, 3) or ({frames}, {n}, 3)" if broadcast else f"({frames}, {n}, 3)")
        raise InputError(f"{name}: expected shape {want}, got {np.shape(a)}")
    if finite and not np.all(np.isfinite(x)):
        raise InputError(f"{name}: NaN or infinite values")
    return x, batched


def as_float(x: npt.ArrayLike, name: str, size: int | None = None,
             dtype: npt.DTypeLike | None = None) -> np.ndarray:
    """Return ``x`` as a floating array, checking that its last axis has ``size``.

    ``dtype`` forces the result dtype (used for scalar parameters); otherwise a
    floating dtype is kept and anything else becomes float64 (the algebra modules
    :mod:`dqskin.quat`, :mod:`dqskin.dq` check ``(..., 4)`` and ``(..., 8)`` arrays with it).
    Complex or non-numeric input is a ValueError (:func:`as_real`), never truncated.
    """
    x = as_real(name, x)
    if dtype is not None:
        x = x.astype(dtype, copy=False)
    elif not np.issubdtype(x.dtype, np.floating):
        x = x.astype(np.float64)
    if size is not None and (x.ndim == 0 or x.shape[-1] != size):
        raise InputError(f"{name} must have shape (..., {size}), got shape {x.shape}")
    return x


def concat(*parts: np.ndarray) -> np.ndarray:
    """Concatenate ``(..., n_i)`` arrays along the last axis, broadcasting batch shapes."""
    batch = np.broadcast_shapes(*(p.shape[:-1] for p in parts))
    return np.concatenate([np.broadcast_to(p, batch + p.shape[-1:]) for p in parts], axis=-1)
