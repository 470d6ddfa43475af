"""Which times to skin: one time model for every input, the ``--frames`` grammar, resampling,
sub-frames and frame numbers.

Every output is counted in **frames at the output frame rate** (:func:`frame_rate`): ``fps`` when
given, else the file's own rate (a USD stage's ``timeCodesPerSecond``, a BVH's ``1 / Frame Time``,
:attr:`dqskin.Scene.frame_rate`), else :data:`DEFAULT_FPS` for inputs timed in seconds (glTF).
Frame ``f`` is at ``f / rate`` seconds, the asset time ``f × time_codes_per_second / rate``: on a
USD stage without ``fps`` frames are its time codes, on a glTF file seconds × 24.

One grammar for every command: ``START:END[:STEP]`` (END inclusive) or ``F1,F2,...``, in frames.
Ranges are evaluated in decimal arithmetic, so ``0:48:0.1`` gives ``0.3`` and ``47.9``, not
``0.30000000000000004``.
"""

from decimal import (
    MAX_EMAX,
    MIN_EMIN,
    ROUND_FLOOR,
    Decimal,
    InvalidOperation,
    Overflow,
    Underflow,
    localcontext,
)
from typing import TYPE_CHECKING, NamedTuple

import numpy as np
import numpy.typing as npt

from .errors import InputError, LimitError, Param

if TYPE_CHECKING:
    from .scene import Scene

__all__ = ["DEFAULT_FPS", "FRAMES_CEILING", "MAX_FRAMES", "MAX_FRAME_NUMBER", "Selection",
           "check_fps", "default_frames", "describe_range", "frame_numbers", "frame_rate",
           "nominal_rate", "parse_frames", "select", "select_times"]

MAX_FRAMES = 100_000
"""Default limit on the number of times one command skins (``--max-frames`` raises it): a
selection above it is refused before anything is allocated."""

FRAMES_CEILING = 10_000_000
"""The most ``max_frames`` may be raised to (ten million frames: 4.6 days at 24 fps)."""

MAX_FRAME_NUMBER = 10 ** 15
"""Largest frame number (in magnitude) ``--frames`` accepts."""

DEFAULT_FPS = 24.0
"""Output frame rate of inputs timed in seconds (glTF) when neither ``fps`` nor the file gives
one."""

_ON_FRAME = 1e-4  # a time within this many frames of a whole frame is on it (float32 keys)


def nominal_rate(rate: float) -> float:
    """``rate`` (frames per second) rounded to a whole number when within 1e-4 of one in
    relative terms: a rate read as a reciprocal (a BVH's ``Frame Time 0.0083333``) is
    ``120.00048``, meant as 120."""
    r = float(rate)
    whole = round(r)
    return float(whole) if whole > 0 and abs(r - whole) <= 1e-4 * whole else r


def _whole(value: object) -> bool:
    """Whether ``value`` is an integer (NumPy's too), not a bool."""
    return not isinstance(value, bool) and isinstance(value, (int, np.integer))


def check_fps(fps: float | None) -> float | None:
    """``fps`` as a float (None stays None); InputError unless a positive number."""
    value: object = fps
    if value is None:
        return None
    if isinstance(value, bool) or not isinstance(value, (int, float, np.floating, np.integer)) \
            or not (np.isfinite(value) and value > 0):
        raise InputError(Param("fps", fps), ": must be a positive number")
    return float(value)


def frame_rate(scene: "Scene", fps: float | None = None) -> float:
    """The output frame rate of ``scene``: ``fps`` when given, else ``scene.frame_rate``, else
    ``scene.time_codes_per_second`` (its times are frames: USD, BVH).

    Raises
    ------
    InputError
        ``fps`` is not a positive finite number.
    """
    given = check_fps(fps)
    if given is not None:
        return given
    own = getattr(scene, "frame_rate", None)
    return float(own) if own else float(scene.time_codes_per_second)


def _check_count(count: int | Decimal, what: tuple[str | Param, ...], max_frames: int) -> None:
    """LimitError when ``count`` frames exceed ``max_frames``; ``what`` (message parts) names the
    selection. ``count`` is only formatted when at most :data:`FRAMES_CEILING` × 10."""
    if count > max_frames:
        shown = f"{int(count):,}" if count <= FRAMES_CEILING * 10 else "over " \
            f"{FRAMES_CEILING * 10:,}"
        raise LimitError(*what, f" selects {shown} frames, more than the limit of "
                         f"{max_frames:,}; raise ", Param("max_frames"), " to allow more")


def _check_max_frames(max_frames: int) -> int:
    if not _whole(max_frames) or max_frames < 1:
        raise InputError(Param("max_frames", max_frames), ": expected a whole number >= 1")
    if max_frames > FRAMES_CEILING:
        raise LimitError(Param("max_frames", max_frames), f": at most {FRAMES_CEILING:,} (every "
                         "selected frame is held in memory)")
    return int(max_frames)


def _decimal(text: str) -> Decimal:
    d = Decimal(text.strip())
    if not d.is_finite() or d.copy_abs() > MAX_FRAME_NUMBER:
        raise InvalidOperation
    return d


def _values(start: Decimal, step: Decimal, count: int) -> np.ndarray:
    """``float(start + k × step)`` for ``k < count``, each rounded once from the exact decimal
    (scaled integers when they are exact in float64, else decimal arithmetic)."""
    e = min(start.as_tuple().exponent, step.as_tuple().exponent)
    assert isinstance(e, int), "finite decimals"
    if -22 <= e <= 22:
        s, p = int(start.scaleb(-e)), int(step.scaleb(-e))
        if max(abs(s), abs(s + (count - 1) * p)) < 2 ** 53 and abs(p) < 2 ** 53:
            k = np.arange(count, dtype=np.int64)
            ints = (s + k * p).astype(np.float64)
            return ints / 10.0 ** -e if e < 0 else ints * 10.0 ** e
    with localcontext() as ctx:
        ctx.prec = 60
        return np.array([float(start + k * step) for k in range(count)], dtype=np.float64)


def _range(start: Decimal, end: Decimal, step: Decimal,
           what: tuple[str | Param, ...] = (Param("frames"),),
           max_frames: int = MAX_FRAMES) -> np.ndarray:
    """Decimal ``start, start + step, …`` up to ``end`` (inclusive within 1e-6 step), as floats;
    counted before anything is allocated."""
    with localcontext() as ctx:  # (no overflow however small the step: infinitely many)
        ctx.prec, ctx.Emax, ctx.Emin = 40, MAX_EMAX, MIN_EMIN
        ctx.traps[Overflow] = ctx.traps[Underflow] = False
        steps = ((end - start) / step + Decimal("1e-6")).to_integral_value(ROUND_FLOOR)
        _check_count(steps + 1, what, max_frames)
        count = int(steps) + 1
    return _values(start, step, count)


def parse_frames(text: str, default_step: float = 1.0, max_frames: int = MAX_FRAMES) -> np.ndarray:
    """``--frames`` text → frame numbers (at the output frame rate: :func:`select`).

    Parameters
    ----------
    text : str
        ``START:END[:STEP]`` (END inclusive) or a comma-separated list ``F1,F2,...``; every
        number finite and at most :data:`MAX_FRAME_NUMBER` in magnitude.
    default_step : float
        STEP when the range gives none.
    max_frames : int
        Refuse selections of more frames (``--max-frames``, at most :data:`FRAMES_CEILING`).

    Returns
    -------
    (F,) float64

    Raises
    ------
    InputError
        Naming ``frames`` and the expected grammar; LimitError beyond ``max_frames``.
    """
    max_frames = _check_max_frames(max_frames)
    what = (Param("frames", _shown(text)),)
    message = (*what, ": expected START:END[:STEP] or a comma-separated list of frames, each a "
               f"finite number of at most {MAX_FRAME_NUMBER:.0e} in magnitude")
    if not isinstance(text, str):
        raise InputError(*message)
    ranged = ":" in text
    pieces = text.split(":" if ranged else ",")
    if len(pieces) > max_frames:
        _check_count(len(pieces), what, max_frames)
    try:
        parts = [_decimal(p) for p in pieces]
    except (InvalidOperation, ValueError):
        raise InputError(*message) from None
    if not ranged:
        return np.array([float(p) for p in parts], dtype=np.float64)
    if len(parts) not in (2, 3):
        raise InputError(*message)
    start, end = parts[:2]
    step = parts[2] if len(parts) == 3 else Decimal(repr(float(default_step)))
    if not step > 0 or not end >= start:
        raise InputError(*what, ": need END >= START and STEP > 0")
    return _range(start, end, step, what, max_frames)


def _shown(text: object) -> object:
    """``text`` for a message: at most 60 characters."""
    return text if not isinstance(text, str) or len(text) <= 60 else text[:57] + "..."


class Selection(NamedTuple):
    """Frames to skin and where they are in the asset.

    Attributes
    ----------
    frames : (F,) float64
        Frame numbers at ``rate`` (whole numbers unless sub-frames were asked for).
    times : (F,) float64
        The same instants in the asset's time unit (``Scene.times``).
    rate : float
        Output frames per second.
    """

    frames: np.ndarray
    times: np.ndarray
    rate: float


def _to_times(frames: np.ndarray, tcps: float, rate: float) -> np.ndarray:
    return frames.copy() if rate == tcps else frames * tcps / rate


def describe_range(times: npt.ArrayLike, time_codes_per_second: float, rate: float) -> str:
    """``"frames 1 .. 48 at 24 fps (0.04167 .. 2 s)"``: the span of ``times`` (asset unit) in
    frames at ``rate`` and in seconds."""
    t = np.asarray(times, np.float64)
    f = t * rate / time_codes_per_second
    s = t / time_codes_per_second
    return (f"frames {_number(f.min())} .. {_number(f.max())} at {rate:g} fps "
            f"({s.min():.4g} .. {s.max():.4g} s)")


def _number(x: float) -> str:
    r = round(x)
    return f"{r:d}" if abs(x - r) <= _ON_FRAME else f"{x:.6g}"


def select(times: npt.ArrayLike, time_codes_per_second: float, frames: str | None = None,
           fps: float | None = None, substeps: int = 1, max_frames: int = MAX_FRAMES, *,
           rate: float | None = None, hold: bool = False) -> Selection:
    """Frames to skin at the output frame rate: the animation's own (every frame of its range;
    its sample times when these are frames already), or an explicit ``--frames`` selection;
    ``substeps`` samples per interval (motion-blur sub-frames).

    Parameters
    ----------
    times : (T,) float
        The asset's sample times (``Scene.times``).
    time_codes_per_second : float
        Rate of ``times`` (1 for glTF seconds).
    frames : str, optional
        ``--frames`` text (:func:`parse_frames`), in frames at the output rate.
    fps : float, optional
        Output frame rate; overrides ``rate``.
    substeps : int
    max_frames : int
        Refuse selections of more frames, sub-frames included (``--max-frames``).
    rate : float, optional
        The file's own output rate (:func:`frame_rate`); default ``time_codes_per_second``.
    hold : bool
        Allow frames outside the animation's range (its first and last poses are held);
        otherwise such a selection is refused naming the range.

    Returns
    -------
    Selection

    Raises
    ------
    InputError
        A bad ``frames``/``fps``/``substeps``, or frames outside the range without ``hold``;
        LimitError beyond ``max_frames``.
    """
    max_frames = _check_max_frames(max_frames)
    t = np.asarray(times, np.float64).reshape(-1)
    if t.size == 0 or not np.all(np.isfinite(t)):
        raise InputError("times: the asset has no finite sample times")
    tcps = float(time_codes_per_second)
    out_rate = check_fps(fps)
    if out_rate is None:
        out_rate = float(rate) if rate else tcps
    first, last = float(t.min()) * out_rate / tcps, float(t.max()) * out_rate / tcps
    if frames is not None:
        f = parse_frames(frames, 1.0, max_frames)
        if not hold and (f.min() < first - _ON_FRAME or f.max() > last + _ON_FRAME):
            raise InputError(Param("frames", _shown(frames)), ": outside the animation's range, "
                             f"{describe_range(t, tcps, out_rate)}; select frames inside it, "
                             "or hold the first and last poses with ", Param("hold", True))
    elif out_rate == tcps:
        f = t.copy()
    else:
        what: tuple[str | Param, ...] = (Param("fps", fps),) if fps is not None else \
            ("the animation's time range",)
        span = last - first + 1
        _check_count(Decimal(repr(span)) if np.isfinite(span) else Decimal("Infinity"), what,
                     max_frames)
        lo = int(np.ceil(first - _ON_FRAME))
        hi = max(lo, int(np.floor(last + _ON_FRAME)))
        _check_count(hi - lo + 1, what, max_frames)
        f = np.arange(lo, hi + 1, dtype=np.float64)
    if not _whole(substeps) or substeps < 1:
        raise InputError(Param("substeps", substeps), ": must be at least 1")
    whats: tuple[str | Param, ...] = (Param("substeps", substeps),) if substeps > 1 else \
        ("the animation's time range",)
    _check_count(max(f.size - 1, 0) * int(substeps) + 1, whats, max_frames)
    if substeps > 1 and f.size > 1:
        d = [Decimal(repr(float(x))) for x in f]
        f = np.array([float(a + (b - a) * k / substeps) for a, b in zip(d[:-1], d[1:])
                      for k in range(substeps)] + [float(d[-1])], dtype=np.float64)
    return Selection(f, _to_times(f, tcps, out_rate), out_rate)


def select_times(times: npt.ArrayLike, time_codes_per_second: float, frames: str | None = None,
                 fps: float | None = None, substeps: int = 1,
                 max_frames: int = MAX_FRAMES, *, rate: float | None = None,
                 hold: bool = False) -> np.ndarray:
    """The asset times of :func:`select` (same parameters).

    Returns
    -------
    (F,) float64
    """
    return select(times, time_codes_per_second, frames, fps, substeps, max_frames, rate=rate,
                  hold=hold).times


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


def frame_numbers(times: npt.ArrayLike, time_codes_per_second: float, rate: float) -> np.ndarray:
    """Whole frame numbers at ``rate`` of asset ``times`` (file names, a USD cache's time codes).

    Parameters
    ----------
    times : (F,) float
        Asset times (``Scene.times`` unit).
    time_codes_per_second : float
        Rate of ``times``.
    rate : float
        Output frames per second (:func:`frame_rate`).

    Returns
    -------
    (F,) int64

    Raises
    ------
    InputError
        A time between frames (sub-frames: write .npz or a USD cache), or two times on one
        frame.
    """
    t = np.asarray(times, dtype=np.float64)
    f = t * float(rate) / float(time_codes_per_second)
    numbers = np.round(f)
    if np.any(np.abs(f - numbers) > _ON_FRAME) or len(set(numbers.tolist())) != len(numbers):
        raise InputError(Param("out"), f": {len(numbers)} frames are not whole, distinct frames "
                         f"at {rate:g} fps (sub-frame times) and cannot become file names; "
                         "write .npz or .usd/.usdc instead")
    return numbers.astype(np.int64)
