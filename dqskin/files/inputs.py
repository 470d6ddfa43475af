"""The one check every input passes where dqskin opens it: a regular file, read with a bound.

* :func:`regular_file`: InputError unless a path names a regular file (a FIFO, a device, a
  socket or a folder would block a read forever or never end); for readers that open files by
  name (USD, trimesh).
* :func:`open_input`: the same check on the opened file itself (opened without blocking, so a
  FIFO swapped in after the check cannot hang the open, and checked with ``fstat``).
* :func:`read_npz`: arrays of an ``.npz``, each ``.npy`` header read first and its size checked
  against what the archive holds and against the limit (:func:`dqskin.limits.check_bytes`)
  before the array is allocated.
"""

from __future__ import annotations

import os
import stat
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING, BinaryIO

from ..errors import InputError
from ..limits import MAX_INPUT_GIB, check_bytes

if TYPE_CHECKING:  # (imported where used: the command line imports this module at start-up)
    import zipfile

    import numpy as np

__all__ = ["open_input", "read_npz", "regular_file"]


def _kind(mode: int) -> str:
    return ("a folder" if stat.S_ISDIR(mode) else "a FIFO" if stat.S_ISFIFO(mode)
            else "a socket" if stat.S_ISSOCK(mode) else "a device" if stat.S_ISCHR(mode)
            or stat.S_ISBLK(mode) else "a special file")


def regular_file(path: str | os.PathLike, what: str = "") -> Path:
    """``path`` as a Path when it names a regular file (symbolic links followed).

    ``what`` (e.g. "clip layer") prefixes the reason. Raises InputError (a ValueError), one line
    naming the file: missing, a folder, a FIFO, a socket or a device.
    """
    p = Path(path)
    try:
        mode = os.stat(p).st_mode
    except (OSError, ValueError) as exc:  # (ValueError: a NUL in the name)
        reason = ("no such file" if isinstance(exc, (FileNotFoundError, ValueError))
                  else exc.strerror or exc)
        raise InputError(f"{p}: {what + ': ' if what else ''}{reason}") from None
    if not stat.S_ISREG(mode):
        raise InputError(f"{p}: {what + ': ' if what else ''}{_kind(mode)}, not a regular file")
    return p


def open_input(path: str | os.PathLike, what: str = "") -> BinaryIO:
    """``path`` opened for binary reading, once it is known to be a regular file (the check of
    :func:`regular_file`, made on the open file: the open does not block on a FIFO)."""
    p = regular_file(path, what)
    try:
        fd = os.open(p, os.O_RDONLY | getattr(os, "O_NONBLOCK", 0) | getattr(os, "O_CLOEXEC", 0))
    except OSError as exc:
        raise InputError(f"{p}: cannot read ({exc.strerror or exc})") from None
    try:
        mode = os.fstat(fd).st_mode
        if not stat.S_ISREG(mode):
            raise InputError(f"{p}: {_kind(mode)}, not a regular file")
        if hasattr(os, "set_blocking"):
            os.set_blocking(fd, True)
        return os.fdopen(fd, "rb")
    except BaseException:
        os.close(fd)
        raise


def read_npz(path: str | os.PathLike, fields: Sequence[str], *, what: str = "arrays",
             max_input_gib: float = MAX_INPUT_GIB) -> dict[str, np.ndarray]:
    """The arrays ``fields`` of the ``.npz`` archive ``path``, read with bounds.

    Each array's ``.npy`` header is read first: an object dtype is refused, and its shape ×
    itemsize must fit in the bytes the archive records for it and within ``max_input_gib``
    (:func:`dqskin.limits.check_bytes`) before the array is allocated.

    Parameters
    ----------
    path : str or Path
    fields : sequence of str
        Names of the arrays to read (without ``.npy``).
    what : str
        What the file holds, for messages ("weights").
    max_input_gib : float
        Largest array, GiB.

    Returns
    -------
    dict of str to ndarray

    Raises
    ------
    InputError
        (a ValueError) One line naming the file (and the array): not a regular file, not an
        ``.npz`` (a plain ``.npy``, text), a missing array, a damaged or truncated archive.
    LimitError
        An array larger than ``max_input_gib``.
    """
    import zipfile
    with open_input(path) as fh:
        p = Path(path)
        try:
            archive = zipfile.ZipFile(fh)
        except (zipfile.BadZipFile, OSError, EOFError, ValueError):
            fh.seek(0)
            head = fh.read(6)
            kind = ("a .npy array, not an .npz archive" if head == b"\x93NUMPY" else
                    "empty" if not head else "a damaged or truncated archive"
                    if head.startswith(b"PK") else "not an .npz archive")
            raise InputError(f"{p}: cannot read {what}: {kind}") from None
        with archive:
            members = {n[:-4] if n.endswith(".npy") else n: n for n in archive.namelist()}
            missing = [f for f in fields if f not in members]
            if missing:
                raise InputError(f"{p}: missing {', '.join(missing)} (the {what} file holds "
                                 f"{', '.join(fields)})")
            return {f: _member(archive, members[f], f"{p}: cannot read {what}: {f}", f"{p}: {f}",
                               max_input_gib) for f in fields}


def _member(archive: zipfile.ZipFile, name: str, where: str, field: str, max_input_gib: float
            ) -> np.ndarray:
    """One ``.npy`` member, its header checked before the array is allocated; ``where`` begins
    the messages, ``field`` names it for a limit."""
    import zipfile
    import zlib

    import numpy as np
    fmt = np.lib.format
    info = archive.getinfo(name)
    try:
        with archive.open(info) as m:
            version = fmt.read_magic(m)
            if version == (1, 0):
                shape, _, dtype = fmt.read_array_header_1_0(m)
            elif version == (2, 0):
                shape, _, dtype = fmt.read_array_header_2_0(m)
            else:
                raise InputError(f"{where}: .npy format version {version} is not supported")
            header = m.tell()
        if dtype.hasobject:
            raise InputError(f"{where}: an array of Python objects (not allowed)")
        count = 1
        for n in shape:
            count *= int(n)
        nbytes = count * dtype.itemsize
        if nbytes > info.file_size - header:
            raise InputError(f"{where}: the header asks for {nbytes:,} bytes, the archive holds "
                             f"{max(info.file_size - header, 0):,} (truncated or damaged)")
        check_bytes(nbytes, field, max_input_gib)
        with archive.open(info) as m:
            return fmt.read_array(m, allow_pickle=False)
    except InputError:
        raise
    except (ValueError, OSError, EOFError, zipfile.BadZipFile, zlib.error) as exc:
        raise InputError(f"{where}: {str(exc) or type(exc).__name__}") from None
