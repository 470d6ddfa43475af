"""Files written past the page cache (``O_DIRECT``, Linux) where the file system takes it;
ordinary buffered writes elsewhere.

A bake writes hundreds of MB that nothing reads soon. Through the page cache the kernel
allocates and fills a cache page for every 4 KiB first, which can cost as much system time as
the bake spends skinning. ``O_DIRECT`` hands the device whole aligned blocks from the process's
own memory, at a small fraction of that system time. Nothing should read such a file back at
once (read past the cache, it waits on the device): a clip layer is hashed as it is written
(:attr:`AppendFile.observe`).

:class:`AppendFile` stages appended bytes in an aligned buffer and writes whole :data:`BLOCK`
multiples of it directly; then its descriptor's ``O_DIRECT`` flag is cleared (``fcntl``) and
the unaligned tail and writes at an offset (a crate file's bootstrap, written last) go through
the page cache, which Linux keeps coherent with the direct writes. Where ``O_DIRECT`` is
refused (``EINVAL`` setting the flag or at a direct write: some network or FUSE file systems,
tmpfs before Linux 6.6), after a short direct write, or with ``DQSKIN_DIRECT_IO=0``, the
writes are buffered from there on.
"""

import errno
import mmap
import os
from collections.abc import Callable, Sequence

import numpy as np
import numpy.typing as npt

from ..errors import InputError

__all__ = ["BLOCK", "STAGE", "AppendFile", "BytesLike", "Records", "enabled", "nbytes", "pays"]

BytesLike = bytes | bytearray | memoryview | np.ndarray
"""What the writers take: bytes, or a C-contiguous array written as its raw bytes."""

BLOCK = 4096
"""Alignment of direct transfers (address, offset and size): the largest logical block size of
common devices (512 or 4096 bytes)."""

STAGE = 4 << 20
"""Bytes staged before a direct write (a multiple of :data:`BLOCK`)."""

_GATHER = 512 << 10  # bytes of records gathered for one buffered write (at most STAGE): larger
# page-cache writes cost the kernel more system time per byte (Linux 6.18, ext4)

_O_DIRECT = getattr(os, "O_DIRECT", 0)
_CLOEXEC = getattr(os, "O_CLOEXEC", 0)
_REFUSED = (errno.EINVAL, errno.EOPNOTSUPP, errno.ENOTSUP)


def enabled() -> bool:
    """Whether direct I/O is tried at all (``O_DIRECT`` exists, ``DQSKIN_DIRECT_IO`` is not 0)."""
    return bool(_O_DIRECT) and os.environ.get("DQSKIN_DIRECT_IO", "1") != "0"


def pays(nbytes: int | None) -> bool:
    """Whether a new file of about ``nbytes`` should be written past the page cache: True
    unless it fits in what the kernel lets dirty pages take before it slows their writer (half
    way between ``vm.dirty_background_ratio`` and ``vm.dirty_ratio`` of the available memory, or
    their ``_bytes`` forms, less the dirty and writeback pages already there). A file that fits
    is written sooner through the page cache: the writer returns once its bytes are in memory and
    the kernel writes them out after; a larger one would be throttled to the device's speed
    anyway, and past the cache it costs less system time. True for None (unknown) and where
    ``/proc`` does not say (not Linux)."""
    if nbytes is None:
        return True
    try:
        with open("/proc/meminfo") as fh:
            info = {k: int(v.split()[0]) * 1024 for k, _, v in
                    (line.partition(":") for line in fh) if v.strip()}

        def limit(name: str) -> float:
            with open(f"/proc/sys/vm/{name}_bytes") as fh:
                given = int(fh.read())
            if given:
                return float(given)
            with open(f"/proc/sys/vm/{name}_ratio") as fh:
                return int(fh.read()) / 100 * info["MemAvailable"]
        room = (limit("dirty_background") + limit("dirty")) / 2 \
            - info.get("Dirty", 0) - info.get("Writeback", 0)
    except (OSError, ValueError, KeyError):
        return True
    return int(nbytes) > room


def _set_direct(fd: int, on: bool) -> bool:
    """Set or clear ``O_DIRECT`` on ``fd``; whether it is now set (False where refused)."""
    import fcntl
    flags = fcntl.fcntl(fd, fcntl.F_GETFL)
    try:
        fcntl.fcntl(fd, fcntl.F_SETFL, flags | _O_DIRECT if on else flags & ~_O_DIRECT)
    except OSError as exc:
        if exc.errno not in _REFUSED:
            raise
    return bool(fcntl.fcntl(fd, fcntl.F_GETFL) & _O_DIRECT)


def _byte_view(buffer: BytesLike) -> memoryview:
    """The bytes of ``buffer`` as a flat memoryview (no copy)."""
    # NumPy's stubs give arrays the buffer protocol only from Python 3.12 (__buffer__)
    return memoryview(buffer).cast("B")  # type: ignore[arg-type,unused-ignore]


def _pwrite_all(fd: int, data: BytesLike, offset: int) -> None:
    """Write all of ``data`` at ``offset`` (``os.pwrite``; where there is none, as on Windows,
    a seek and writes: only the buffered path runs there)."""
    view = _byte_view(data)
    if not hasattr(os, "pwrite"):
        os.lseek(fd, offset, os.SEEK_SET)
        while view.nbytes:
            view = view[os.write(fd, view):]
        return
    while view.nbytes:
        n = os.pwrite(fd, view, offset)
        view, offset = view[n:], offset + n


def nbytes(buffer: BytesLike) -> int:
    """Bytes of a bytes-like ``buffer``."""
    return buffer.nbytes if isinstance(buffer, (np.ndarray, memoryview)) else len(buffer)


def _writev(fd: int, buffers: Sequence[BytesLike]) -> int:
    """Write ``buffers`` (bytes, or C-contiguous arrays), in order, at ``fd``'s position;
    returns the bytes written. No Python object per buffer (a bake may write one per frame:
    GC-tracked objects there cost garbage-collector passes over the whole heap)."""
    total = 0
    for a in range(0, len(buffers), _WRITEV_MAX):
        part = buffers[a:a + _WRITEV_MAX]
        size = sum(map(nbytes, part))
        # NumPy's stubs give arrays the buffer protocol only from Python 3.12 (__buffer__)
        done = os.writev(fd, part) if hasattr(os, "writev") else 0  # type: ignore[arg-type,unused-ignore]
        if done != size:  # a short write (or no writev): the rest one by one
            for b in part:
                n = nbytes(b)
                if done >= n:
                    done -= n
                    continue
                view = _byte_view(b)[done:]
                while view.nbytes:
                    view = view[os.write(fd, view):]
                done = 0
        total += size
    return total


_WRITEV_MAX = 1024  # IOV_MAX on Linux

Records = tuple[bytes, np.ndarray, int, "npt.ArrayLike | None"]
"""One group of :meth:`AppendFile.append_records`: ``(head, rows, pad, select)``."""


class AppendFile:
    """A new file (created or truncated) written by appending, then :meth:`pwrite` at an offset
    already appended (a header written last). Where direct I/O is taken, appended bytes are
    staged and written past the page cache in whole :data:`BLOCK` multiples; :meth:`flush`
    (called by :meth:`pwrite` and :meth:`close`) writes the partial block that remains through
    the page cache, and later appends are buffered. ``direct=False``: buffered throughout. One
    writer at a time (calls may come from different threads in turn).

    Attributes
    ----------
    size : int
        Bytes appended so far (the file's size once closed).
    observe : callable or None
        Called with every appended byte range, in file order (a bytes-like object, valid
        during the call): e.g. a hash's ``update``. Not with :meth:`pwrite`'s bytes.
    """

    def __init__(self, path: str | os.PathLike, mode: int = 0o666, *, direct: bool = True) -> None:
        self.path = os.fspath(path)
        self.size = 0
        self.observe: Callable[[BytesLike], object] | None = None
        self._written = 0  # bytes of the file written (a BLOCK multiple while direct)
        self._stage: mmap.mmap | None = None
        self._view: np.ndarray | None = None  # the stage's bytes: set while direct I/O is on
        self._fill = 0  # bytes staged
        self._block: np.ndarray | None = None  # records gathered for a buffered write
        self._blocked = 0  # bytes of them in it
        self._direct = False
        self._fd: int | None = os.open(self.path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC | _CLOEXEC,
                                       mode)
        try:
            if direct and enabled() and _set_direct(self._fd, True):
                self._stage = mmap.mmap(-1, STAGE, flags=mmap.MAP_PRIVATE | mmap.MAP_ANONYMOUS)
                self._view = np.frombuffer(self._stage, np.uint8)  # page aligned
                self._direct = True
        except BaseException:
            self.close(flush=False)
            raise

    @property
    def direct(self) -> bool:
        """Whether appends go past the page cache now."""
        return self._direct

    def append(self, buffers: Sequence[BytesLike]) -> int:
        """Append ``buffers`` (bytes-like: bytes, C-contiguous arrays), in order; returns the
        bytes appended."""
        if self.observe is not None:
            for b in buffers:
                self.observe(b)
        total = 0
        for i, b in enumerate(buffers):
            if not self._direct:
                total += self._append_buffered(buffers[i:])
                break
            src = np.frombuffer(_byte_view(b), np.uint8)
            total += src.nbytes
            while src.nbytes:
                k = min(src.nbytes, STAGE - self._fill)
                view = self._staged()
                view[self._fill:self._fill + k] = src[:k]  # NumPy: the GIL released
                self._fill += k
                src = src[k:]
                if self._fill == STAGE:
                    self._write_stage()
                    if not self._direct and src.nbytes:  # refused: the rest buffered
                        self._append_buffered([src])
                        break
        self.size += total
        return total

    def append_records(self, groups: Sequence[Records]) -> int:
        """Append, for each ``(head, rows, pad, select)`` of ``groups`` in order, one record per
        row of ``rows`` ((K, M) uint8, each row contiguous; with ``select``, only those row
        indices, in that order): ``head``, the row's M bytes, ``pad`` zero bytes.

        Direct: the records are copied straight into the stage, many rows a copy; buffered:
        copied into a block (512 KiB, at most :data:`STAGE`), the groups one after the other,
        one write each time it fills and one at the end (a record larger than the block:
        ``writev`` of its parts). Returns the bytes appended; raises InputError for rows that
        are not (K, M) uint8."""
        checked: list[tuple[bytes, np.ndarray, int, np.ndarray | None]] = []
        for head, rows, pad, select in groups:
            rows = np.asarray(rows)
            if rows.ndim != 2 or rows.dtype != np.uint8:
                raise InputError(f"append_records: expected (K, M) uint8 rows, got {rows.dtype} "
                                 f"{rows.shape}")
            if rows.shape[1] > 1 and rows.strides[1] != 1:
                rows = np.ascontiguousarray(rows)
            index = None if select is None else np.asarray(select, np.intp)
            if (len(rows) if index is None else len(index)) and len(head) + rows.shape[1] + pad:
                checked.append((head, rows, int(pad), index))
        try:
            return sum(self._append_group(*group) for group in checked)
        finally:
            self._write_block()

    def _write_block(self) -> None:
        """Write the records gathered in the block (buffered)."""
        if self._blocked:
            assert self._block is not None
            done, self._blocked = self._blocked, 0  # (not written again after an error)
            self._append_buffered([self._block[:done]])

    def _append_group(self, head: bytes, rows: np.ndarray, pad: int,
                      index: np.ndarray | None) -> int:
        """One group of :meth:`append_records`, copied (into the stage, or a block written
        through the page cache)."""
        h, m = len(head), rows.shape[1]
        stride = h + m + pad
        count = len(rows) if index is None else len(index)
        total = stride * count
        hv = np.frombuffer(head, np.uint8)
        a = 0
        while a < count and self._direct:
            room = (STAGE - self._fill) // stride
            if not room:
                self._write_stage()  # leaves less than a block staged
                room = (STAGE - self._fill) // stride
            if not room or not self._direct:  # a record larger than the stage; refused
                break
            k = min(room, count - a)
            self._records(self._staged()[self._fill:self._fill + k * stride], hv, rows,
                          index, a, k)
            self._fill += k * stride
            a += k
            if self._fill == STAGE:
                self._write_stage()
        self.size += stride * a
        if a < count and not self._direct and self._block is None:
            self._block = np.empty(min(STAGE, _GATHER), np.uint8)
        block = self._block
        while block is not None and a < count and not self._direct:
            # buffered: the records copied into the block (after other groups' records), one
            # write each time it fills (no Python object per record: the writer thread
            # seldom needs the GIL)
            room = (len(block) - self._blocked) // stride
            if not room:
                if not self._blocked:  # a record larger than the block (written below)
                    break
                self._write_block()
                continue
            k = min(room, count - a)
            self._records(block[self._blocked:self._blocked + k * stride], hv, rows, index, a,
                          k)
            self._blocked += k * stride
            self.size += k * stride
            a += k
        if a < count:  # the rest record by record (each across stages, or larger)
            zeros = bytes(pad)
            rest = range(a, count) if index is None else index[a:]
            self.append([part for i in rest for part in (head, rows[i], zeros)])
        return total

    def _records(self, dst: np.ndarray, head: np.ndarray, rows: np.ndarray,
                 index: np.ndarray | None, a: int, k: int) -> None:
        """Copy records ``a .. a + k - 1`` of a group (``head``, the row, zero padding) into the
        bytes ``dst`` (``k`` records long) and show them to :attr:`observe`."""
        out = dst.reshape(k, -1)
        h, m = len(head), rows.shape[1]
        out[:, :h] = head
        out[:, h:h + m] = rows[a:a + k] if index is None else rows[index[a:a + k]]
        out[:, h + m:] = 0
        if self.observe is not None:
            self.observe(out)

    def _append_buffered(self, buffers: Sequence[BytesLike]) -> int:
        if self._view is not None:  # bytes a failed switch left staged come first
            self._to_buffered()
        fd = self._open()
        os.lseek(fd, self._written, os.SEEK_SET)
        n = _writev(fd, list(buffers))
        self._written += n
        return n

    def _write_stage(self) -> None:
        """Write the staged whole blocks directly and keep the partial one staged. Refused
        (EINVAL: an alignment this file system does not take) or short (the device filling
        up): every staged byte is written through the page cache, and buffered from then on
        (a full disk then reports itself)."""
        whole = self._fill - self._fill % BLOCK
        if not whole:
            return
        view = self._staged()
        try:
            n = os.pwrite(self._open(), view[:whole].data, self._written)
        except OSError as exc:
            if exc.errno not in _REFUSED:
                raise
            n = 0
        if n != whole:
            self._to_buffered()
            return
        self._written += whole
        rest = self._fill - whole
        view[:rest] = view[whole:self._fill]
        self._fill = rest

    def _to_buffered(self) -> None:
        """Clear O_DIRECT and write what is staged through the page cache (the state changes
        only once that write succeeded: a failed one leaves the bytes staged)."""
        if self._direct:
            self._direct = False
            if _set_direct(self._open(), False):
                raise OSError(errno.EINVAL, f"{self.path}: cannot clear O_DIRECT")
        staged = self._staged()[:self._fill]
        _pwrite_all(self._open(), staged, self._written)
        self._written += staged.nbytes
        self._fill = 0
        # the staging memory goes with its last reference (not closed here: a traceback may
        # still hold a view of it)
        self._view = self._stage = None

    def _staged(self) -> np.ndarray:
        """The staging memory (held while direct I/O is on, or bytes a failed switch left)."""
        assert self._view is not None, "nothing staged"
        return self._view

    def _open(self) -> int:
        """The file descriptor (until :meth:`close`)."""
        assert self._fd is not None, f"{self.path}: closed"
        return self._fd

    def flush(self) -> None:
        """Write everything staged; later appends are buffered."""
        if self._direct:
            self._write_stage()
        if self._view is not None:  # staged bytes remain (or a failed switch left them)
            self._to_buffered()

    def pwrite(self, data: BytesLike, offset: int) -> None:
        """Write ``data`` at ``offset``, within the bytes appended (after a :meth:`flush`)."""
        if offset < 0 or offset + nbytes(data) > self.size:
            raise InputError(f"{self.path}: a write at {offset} past the {self.size} bytes "
                             "appended")
        self.flush()
        _pwrite_all(self._open(), data, offset)

    def close(self, flush: bool = True) -> None:
        """Flush (unless ``flush`` is False: the file is abandoned) and close; again: nothing."""
        try:
            if flush and self._fd is not None:
                self.flush()
        finally:
            self._direct = False
            self._view = self._stage = self._block = None
            fd, self._fd = self._fd, None
            if fd is not None:
                os.close(fd)
