"""Which times to skin: the ``--frames`` grammar, resampling, sub-frames and frame numbers.

One grammar for every command: ``START:END[:STEP]`` (END inclusive) or ``T1,T2,...``, in the
asset's time unit (USD time codes, glTF seconds). Ranges are evaluated in decimal arithmetic, so
``0:48:0.1`` gives ``0.3`` and ``47.9``, not ``0.30000000000000004``.
"""

from decimal import Decimal, InvalidOperation

import numpy as np
import numpy.typing as npt

from .errors import InputError, LimitError, Param

__all__ = ["MAX_FRAMES", "default_frames", "frame_numbers", "parse_frames", "select_times"]

MAX_FRAMES = 100_000
"""Default limit on the number of times one command skins (``--max-frames`` raises it): a
selection above it is refused before anything is allocated."""


def _check_count(count: int, what: tuple[str | Param, ...], max_frames: int) -> None:
    """LimitError when ``count`` frames exceed ``max_frames``; ``what`` (message parts) names the
    selection."""
    if count > max_frames:
        raise LimitError(*what, f" selects {count:,} frames, more than the limit of "
                         f"{max_frames:,}; raise ", Param("max_frames"), " to allow more")


def _decimal(text: str) -> Decimal:
    d = Decimal(text.strip())
    if not d.is_finite():
        raise InvalidOperation
    return d


def _range(start: Decimal, end: Decimal, step: Decimal,
           what: tuple[str | Param, ...] = (Param("frames"),),
           max_frames: int = MAX_FRAMES) -> np.ndarray:
    """Decimal ``start, start + step, …`` up to ``end`` (inclusive within 1e-6 step), as floats;
    counted before anything is allocated."""
    count = int((end - start) / step + Decimal("1e-6")) + 1
    _check_count(count, what, max_frames)
    return np.array([float(start + k * step) for k in range(count)], dtype=np.float64)


def parse_frames(text: str, default_step: float = 1.0, max_frames: int = MAX_FRAMES) -> np.ndarray:
    """``--frames`` text → times.

    Parameters
    ----------
    text : str
        ``START:END[:STEP]`` (END inclusive) or a comma-separated list ``T1,T2,...``.
    default_step : float
        STEP when the range gives none (``--fps`` sets it).
    max_frames : int
        Refuse selections of more frames (``--max-frames``).

    Returns
    -------
    (F,) float64

    Raises
    ------
    InputError
        Naming ``frames`` and the expected grammar; LimitError beyond ``max_frames``.
    """
    what = (Param("frames", text),)
    message = (*what, ": expected START:END[:STEP] or a comma-separated list of times")
    ranged = ":" in text
    try:
        parts = [_decimal(p) for p in text.split(":" if ranged else ",")]
    except InvalidOperation:
        raise InputError(*message) from None
    if not ranged:
        _check_count(len(parts), what, max_frames)
        return np.array([float(p) for p in parts], dtype=np.float64)
    if len(parts) not in (2, 3):
        raise InputError(*message)
    start, end = parts[:2]
    step = parts[2] if len(parts) == 3 else Decimal(repr(float(default_step)))
    if not step > 0 or not end >= start:
        raise InputError(*what, ": need END >= START and STEP > 0")
    return _range(start, end, step, what, max_frames)


def select_times(times: npt.ArrayLike, time_codes_per_second: float, frames: str | None = None,
                 fps: float | None = None, substeps: int = 1,
                 max_frames: int = MAX_FRAMES) -> np.ndarray:
    """Sample times: the asset's own, an explicit ``--frames`` selection, or ``--fps`` resampling
    (which also sets the default STEP of ``--frames``); ``substeps`` samples per interval
    (motion-blur sub-frames).

    Parameters
    ----------
    times : (T,) float
        The asset's sample times.
    time_codes_per_second : float
        Rate of ``times`` (1 for glTF seconds).
    frames : str, optional
        ``--frames`` text (:func:`parse_frames`).
    fps : float, optional
    substeps : int
    max_frames : int
        Refuse selections of more frames, sub-frames included (``--max-frames``).

    Returns
    -------
    (F,) float64
    """
    t = np.asarray(times, np.float64)
    if fps is not None and not (np.isfinite(fps) and fps > 0):
        raise InputError(Param("fps", fps), ": must be a positive number")
    step = 1.0 if fps is None else time_codes_per_second / fps
    if frames is not None:
        t = parse_frames(frames, step, max_frames)
    elif fps is not None:
        t = _range(Decimal(repr(float(t[0]))), Decimal(repr(float(t[-1]))),
                   Decimal(repr(float(step))), (Param("fps", fps),), max_frames)
    if t.size == 0:
        raise InputError(Param("frames"), ": no frames selected")
    if substeps < 1:
        raise InputError(Param("substeps", substeps), ": must be at least 1")
    # (--frames and --fps checked their own counts above)
    what = (Param("substeps", substeps),) if substeps > 1 else ("the animation's time range",)
    _check_count(max(t.size - 1, 0) * substeps + 1, what, max_frames)
    if substeps > 1 and t.size > 1:
        d = [Decimal(repr(float(x))) for x in t]
        t = np.array([float(a + (b - a) * k / substeps) for a, b in zip(d[:-1], d[1:])
                      for k in range(substeps)] + [float(d[-1])], dtype=np.float64)
    return t


def default_frames(times: npt.ArrayLike, count: int = 10) -> np.ndarray:
    """Up to ``count`` evenly spaced samples of ``times`` (first and last included).

    Parameters
    ----------
    times : (T,) float
        The asset's sample times.

    Returns
    -------
    (F,) float64, F = min(T, count).
    """
    t = np.asarray(times, dtype=np.float64).reshape(-1)
    if t.size == 0:
        raise InputError("times: the asset has no sample times")
    pick = np.unique(np.round(np.linspace(0, t.size - 1, min(t.size, count))).astype(int))
    return t[pick]


def frame_numbers(times: npt.ArrayLike, seconds: bool) -> np.ndarray:
    """Integer frame numbers for file names.

    Parameters
    ----------
    times : (F,) float
    seconds : bool
        Whether ``times`` are seconds (glTF): then frames of the sample rate (24 fps, or finer
        when the samples are); otherwise they are time codes, rounded.

    Returns
    -------
    (F,) int; InputError when two frames would share a number (sub-frame times).
    """
    t = np.asarray(times, dtype=np.float64)
    rate = 1.0
    if seconds:
        step = np.diff(t).min() if t.size > 1 else 1.0
        rate = max(24.0, float(np.round(1.0 / step)) if step > 0 else 24.0)
    numbers = np.round(t * rate).astype(int)
    if len(set(numbers.tolist())) != len(numbers):
        raise InputError(Param("out"), f": {len(numbers)} frames map to "
                         f"{len(set(numbers.tolist()))} file names (sub-frame times); write .npz"
                         + ("" if seconds else " or .usd/.usdc") + " instead")
    return numbers
