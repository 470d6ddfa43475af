"""The on-disk cache of computed arrays (automatic weights, rotation centers).

Entries are ``.npz`` files under :func:`cache_dir`, one folder per kind (``weights/``, ``cor/``),
named by a hash of everything the result depends on (the caller's key), so nothing goes stale:
a changed input is another file. :func:`store` writes atomically (:mod:`dqskin.files.atomic`)
and skips a cache it cannot write; :func:`load` treats anything it cannot use (missing, empty,
truncated, not an archive, a missing array, another shape or dtype) as a miss.
"""

import os
from pathlib import Path

import numpy as np
import numpy.typing as npt

from .errors import InputError
from .files.atomic import atomic_path
from .files.inputs import read_npz

__all__ = ["cache_dir", "load", "store"]


def cache_dir() -> Path:
    """The cache folder: ``$DQSKIN_CACHE_DIR``, else ``$XDG_CACHE_HOME/dqskin``, else
    ``~/.cache/dqskin``."""
    root = os.environ.get("DQSKIN_CACHE_DIR")
    if root:
        return Path(root)
    xdg = os.environ.get("XDG_CACHE_HOME")
    return (Path(xdg) if xdg else Path.home() / ".cache") / "dqskin"


def load(path: str | os.PathLike,
         expected: dict[str, tuple[tuple[int | None, ...], npt.DTypeLike]]
         ) -> dict[str, np.ndarray] | None:
    """The arrays of the entry at ``path``, or None when it cannot be used.

    ``expected`` maps each array name to ``(shape, dtype)``; ``None`` in a shape matches any
    length (e.g. ``((V, None), np.int32)``). Any failure to read (a FIFO or other non-regular
    file is not opened: :func:`dqskin.files.inputs.read_npz`), a missing array, another shape
    or dtype is a miss (None), never an exception.
    """
    try:
        out = read_npz(path, list(expected), what="cache")
    except InputError:  # missing, not a regular file, empty, truncated, not a zip, too large
        return None
    for name, (shape, dtype) in expected.items():
        a = out[name]
        if (a.dtype != np.dtype(dtype) or a.ndim != len(shape)
                or any(s is not None and s != n for s, n in zip(shape, a.shape))):
            return None
    return out


def store(path: str | os.PathLike, **arrays: npt.ArrayLike) -> None:
    """Write ``arrays`` as the ``.npz`` entry ``path`` (atomically, replacing an unreadable
    one); a cache that cannot be written (read-only, full) costs a recomputation next time,
    nothing more."""
    try:
        with atomic_path(path, overwrite=True) as tmp:
            np.savez(tmp, allow_pickle=False, **arrays)
    except OSError:
        pass
