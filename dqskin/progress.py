"""Progress bars: every bar dqskin draws is a tqdm bar on stderr made here, drawn only when
stderr is a terminal (a log file or a pipe gets nothing, not even ``\\r`` lines) and asked for.
tqdm is imported only when a bar is drawn."""

import sys
from collections.abc import Iterable, Iterator
from types import TracebackType
from typing import Any, Literal

__all__ = ["NoBar", "on_terminal", "progress_bar"]


def on_terminal() -> bool:
    """Whether ``sys.stderr`` is a terminal (False when it is closed, missing or a file)."""
    try:
        return bool(sys.stderr is not None and sys.stderr.isatty())
    except (AttributeError, ValueError, OSError):
        return False


class NoBar:
    """What :func:`progress_bar` returns when nothing is drawn: tqdm's methods, doing nothing
    (iterating it iterates ``iterable``)."""

    def __init__(self, iterable: Iterable[Any] | None = None, total: float | None = None,
                 **_: Any) -> None:
        self.iterable = iterable
        self.total = total
        self.n: float = 0

    def __iter__(self) -> Iterator[Any]:
        return iter(() if self.iterable is None else self.iterable)

    def update(self, n: float = 1) -> None:
        self.n += n

    def set_postfix_str(self, text: str = "", refresh: bool = True) -> None:
        pass

    def set_description(self, desc: str | None = None, refresh: bool = True) -> None:
        pass

    def refresh(self) -> None:
        pass

    def close(self) -> None:
        pass

    def __enter__(self) -> "NoBar":
        return self

    def __exit__(self, exc_type: type[BaseException] | None, exc: BaseException | None,
                 tb: TracebackType | None) -> Literal[False]:
        return False


def progress_bar(iterable: Iterable[Any] | None = None, *, enabled: bool = True,
                 **kwargs: Any) -> Any:
    """A tqdm bar on stderr when ``enabled`` and stderr is a terminal, else a :class:`NoBar`.

    Parameters
    ----------
    iterable : iterable, optional
        As tqdm's first argument.
    enabled : bool
        False draws nothing (``--quiet``, ``progress=False``).
    **kwargs
        tqdm's keyword arguments (``total``, ``desc``, ``unit``, ``initial``, ``leave``, ...);
        ``file`` is always stderr.

    Returns
    -------
    tqdm.tqdm or NoBar
        Both count with ``update``, close with ``close`` and work as context managers.
    """
    if not (enabled and on_terminal()):
        return NoBar(iterable, **kwargs)
    from tqdm import tqdm
    return tqdm(iterable, file=sys.stderr, **kwargs)
