"""Time samples streamed straight into a USD crate file (``.usdc``), without an Sdf layer.

A layer that holds nothing but time samples (a clip layer of :mod:`.usd_clips`) is written here
as its arrays arrive: :meth:`CrateSamples.add_many` queues a chunk of frames of many
attributes for the writer thread as one write (a :class:`~.direct.AppendFile`: the frames
copied into its aligned stage and written past the page cache, or into a block written through
it; the GIL released, no ``Vt`` array per frame; once written, nothing kept but each sample's
time and file offset, and a copy of each attribute's last frame), and
:meth:`CrateSamples.close` writes what makes it a layer: the prims (as ``over``), the
attributes with their sample tables, the layer's time range and rate, the structural sections
and the table of contents. Memory holds a few blocks, not the layer.

The file is crate version 0.8.0, what usd-core writes by default (with a ``base``, the base's
version), laid out as ``pxr/usd/sdf/crateFile.cpp`` reads it:

* an 88-byte bootstrap (``PXR-USDC``, version, table-of-contents offset);
* values: each ``Vec3f`` array at an 8-byte aligned offset as a ``uint64`` count and the floats
  (uncompressed, so readers map them without a copy), each ``Matrix4d`` as 16 row-major doubles
  (Gf's row-vector layout), a frame equal to the one added before it once (its times share
  the value, as usd-core's writer shares equal arrays), each distinct vector of sample times
  once as a ``vector<double>``, and each attribute's ``TimeSamples`` record (times rep, count,
  one value rep per time);
* the structural sections ``TOKENS``, ``STRINGS``, ``FIELDS``, ``FIELDSETS``, ``PATHS``,
  ``SPECS``: their integer lists coded as ``Sdf_IntegerCompression`` reads them (every delta as
  32 bits) and wrapped, as every compressed section, in one LZ4 block of literals (valid LZ4 that
  any LZ4 decoder reads; the sections are small beside the samples);
* the table of contents (name, start, size of each section).

With a ``base`` (a crate file usd-core wrote: the single-layer cache's topology, UVs, materials
and attribute specs, without samples) the new file starts with the base's values, byte for byte
at the same offsets so every reference into them stays valid, then the samples; at
:meth:`CrateSamples.close` the base's structural sections are read (their LZ4 blocks and integer
codes decoded here), each baked attribute spec gets its ``timeSamples`` field, the time range is
replaced, and the sections are written again (tokens, fields, field sets and specs re-encoded;
strings and paths copied).

A file is complete only after :meth:`CrateSamples.close`; the caller writes it under a temporary
name and renames it (:class:`~.atomic.atomic_path`). ``tests/test_crate.py`` reads every file
back with usd-core and compares it, value by value and as text, with the same layer written
by Sdf.
"""

import collections
import os
import struct
import threading
import weakref
from collections.abc import Callable, Sequence
from concurrent.futures import Future, ThreadPoolExecutor
from pathlib import Path
from typing import Any, Protocol

import numpy as np
import numpy.typing as npt
from pxr import Sdf

from ..errors import InputError
from .direct import AppendFile, BytesLike, Records

__all__ = ["BOOTSTRAP", "CrateSamples", "Hasher", "UnsupportedCrate", "VERSION", "VALUE_TYPES"]

VERSION = (0, 8, 0)
"""Crate file version written (usd-core's default for new files)."""

_IDENT = b"PXR-USDC"
BOOTSTRAP = 88
"""Bytes of a crate file's bootstrap (ident[8], version[8], tocOffset int64, reserved
int64[8]), at its start and written last."""

# Value type enumerants (pxr/usd/sdf/crateDataTypes.h).
_BOOL, _DOUBLE, _TOKEN, _MATRIX4D, _VEC3F = 1, 9, 11, 15, 24
_TOKEN_VECTOR, _SPECIFIER, _VARIABILITY, _TIME_SAMPLES, _DOUBLE_VECTOR = 41, 42, 44, 46, 48
_IS_ARRAY, _IS_INLINED = 1 << 63, 1 << 62
# SdfSpecType, SdfSpecifier, SdfVariability.
_SPEC_ATTRIBUTE, _SPEC_PRIM, _SPEC_PSEUDO_ROOT = 1, 6, 7
_SPECIFIER_OVER, _VARIABILITY_VARYING = 1, 0
_NO_FIELD = 0xFFFFFFFF  # ends each field set

VALUE_TYPES = {"point3f[]": "vec3f[]", "normal3f[]": "vec3f[]", "vector3f[]": "vec3f[]",
               "float3[]": "vec3f[]", "color3f[]": "vec3f[]", "matrix4d": "matrix4d"}
"""Sdf value type names :meth:`CrateSamples.add` writes, and how they are stored."""


class Hasher(Protocol):
    """A hash object fed the bytes of a file as they are written (hashlib's, xxhash's)."""

    def update(self, data: bytes | memoryview, /) -> None: ...

    def hexdigest(self) -> str: ...


def _rep(kind: int, payload: int = 0, *, array: bool = False, inlined: bool = False) -> int:
    return (_IS_ARRAY if array else 0) | (_IS_INLINED if inlined else 0) | (kind << 48) | payload


def _lz4_literals(data: bytes) -> bytes:
    """``data`` as ``TfFastCompression`` output: a zero chunk-count byte, then one LZ4 block of a
    single literal run (token, length extension, the bytes)."""
    n = len(data)
    if n < 15:
        head = bytes([n << 4])
    else:
        rest = n - 15
        head = b"\xf0" + b"\xff" * (rest // 255) + bytes([rest % 255])
    return b"\x00" + head + data


def _compressed_ints(values: Sequence[int | None] | np.ndarray) -> bytes:
    """32-bit integers as ``Sdf_IntegerCompression`` output, with its ``uint64`` size first:
    the most common delta (0, unused), one 2-bit code per integer (all ``11``: a 32-bit delta),
    the deltas to the previous integer, then LZ4."""
    v = np.asarray(values, dtype=np.int64) & 0xFFFFFFFF
    deltas = (np.diff(v, prepend=0) & 0xFFFFFFFF).astype(np.uint32)
    encoded = (struct.pack("<i", 0) + b"\xff" * ((len(v) * 2 + 7) // 8)
               + deltas.astype("<u4").tobytes())
    packed = _lz4_literals(encoded)
    return struct.pack("<Q", len(packed)) + packed


def _lz4_decode(src: bytes) -> bytes:
    """``TfFastCompression`` output back to its bytes: a zero chunk-count byte (one chunk: the
    only kind a structural section is), then an LZ4 block (literal runs and back-references)."""
    if not src or src[0] != 0:
        raise InputError("not a one-chunk LZ4 buffer")
    out, i, n = bytearray(), 1, len(src)
    while i < n:
        token = src[i]
        length, i = _lz4_length(src, i + 1, token >> 4)
        out += src[i:i + length]
        i += length
        if i >= n:
            break
        offset = src[i] | src[i + 1] << 8
        length, i = _lz4_length(src, i + 2, token & 15)
        length += 4
        if not 0 < offset <= len(out):
            raise InputError("LZ4 offset out of range")
        start = len(out) - offset
        if offset >= length:
            out += out[start:start + length]
        else:  # overlapping: the last `offset` bytes repeat
            period = out[start:]
            out += (period * (length // offset + 1))[:length]
    return bytes(out)


def _lz4_length(src: bytes, i: int, length: int) -> tuple[int, int]:
    """A 4-bit LZ4 length and its extension bytes at ``src[i:]`` (each 255 means another)."""
    if length == 15:
        while True:
            length += src[i]
            i += 1
            if src[i - 1] != 255:
                break
    return length, i


_INT_WIDTHS = np.array([0, 1, 2, 4])  # bytes of a delta by its 2-bit code


def _decode_ints(data: bytes, pos: int, count: int) -> tuple[np.ndarray, int]:
    """``count`` integers coded by ``Sdf_IntegerCompression`` at ``data[pos:]`` (``uint64`` size
    first); returns them (int64, wrapped to signed 32 bits) and the position after them."""
    size = struct.unpack_from("<Q", data, pos)[0]
    end = pos + 8 + size
    if not count:
        return np.zeros(0, np.int64), end
    enc = np.frombuffer(_lz4_decode(data[pos + 8:end]), np.uint8)
    common = int(enc[:4].view("<i4")[0])
    n_codes = (count * 2 + 7) // 8
    codes = ((enc[4:4 + n_codes, None] >> np.array([0, 2, 4, 6], np.uint8)) & 3).ravel()[:count]
    widths = _INT_WIDTHS[codes]
    at = 4 + n_codes + np.cumsum(widths) - widths  # where each delta's bytes start
    if at.size and at[-1] + widths[-1] > enc.size:
        raise InputError("integer codes run past their buffer")
    deltas = np.full(count, common, np.int64)
    for code, dtype in ((1, np.int8), (2, np.int16), (3, np.int32)):
        sel = codes == code
        if sel.any():
            little = np.dtype(dtype).newbyteorder("<")
            raw = enc[at[sel, None] + np.arange(little.itemsize)]  # (k, width) bytes
            deltas[sel] = np.ascontiguousarray(raw).view(little).ravel()
    values = (np.cumsum(deltas) + 2**31) % 2**32 - 2**31
    return values, end


class UnsupportedCrate(InputError):
    """A base crate file of a version :class:`CrateSamples` cannot extend (before 0.7.0, or
    1.0 and later): the caller can write the layer another way."""


class _Base:
    """The structure of a crate file usd-core wrote (the sections :class:`CrateSamples` merges
    with its samples): version, where its values end, tokens, fields, field sets, specs, the
    path of each path index, and the raw STRINGS and PATHS sections."""

    def __init__(self, path: str | os.PathLike) -> None:
        data = Path(path).read_bytes()
        self.data: bytes | None = data
        self.kept: dict[str, bytes] = {}
        if data[:8] != _IDENT:
            raise InputError(f"{path}: not a USD crate file")
        self.version = tuple(data[8:11])
        if not (0, 7, 0) <= self.version < (1, 0, 0):
            raise UnsupportedCrate(f"{path}: crate version {self.version} is not one this "
                                   "writer can extend (0.7.0 or later)")
        toc = struct.unpack_from("<q", data, 16)[0]
        count = struct.unpack_from("<Q", data, toc)[0]
        sections = {}
        for k in range(count):
            name, start, size = struct.unpack_from("<16sqq", data, toc + 8 + 32 * k)
            sections[name.rstrip(b"\0").decode()] = (start, size)
        self.data_end = min(start for start, _ in sections.values())
        self.sections = sections

        pos = sections["TOKENS"][0]
        n, size, packed = struct.unpack_from("<QQQ", data, pos)
        names = _lz4_decode(data[pos + 24:pos + 24 + packed])
        if len(names) != size:
            raise InputError(f"{path}: tokens do not decode")
        self.tokens = [t.decode() for t in names.split(b"\0")[:n]]

        pos = sections["FIELDS"][0]
        n = struct.unpack_from("<Q", data, pos)[0]
        token_ids, pos = _decode_ints(data, pos + 8, n)
        size = struct.unpack_from("<Q", data, pos)[0]
        reps = np.frombuffer(_lz4_decode(data[pos + 8:pos + 8 + size]), "<u8", count=n)
        self.fields = [(int(t) & 0xFFFFFFFF, int(r)) for t, r in zip(token_ids, reps)]

        pos = sections["FIELDSETS"][0]
        n = struct.unpack_from("<Q", data, pos)[0]
        self.fieldsets = (_decode_ints(data, pos + 8, n)[0] & 0xFFFFFFFF).tolist()

        pos = sections["PATHS"][0]
        total, n = struct.unpack_from("<QQ", data, pos)
        index, pos = _decode_ints(data, pos + 16, n)
        element, pos = _decode_ints(data, pos, n)
        jumps, pos = _decode_ints(data, pos, n)
        index, element, jumps = index.tolist(), element.tolist(), jumps.tolist()
        self.paths: list[Sdf.Path] = [None] * total
        # (item, parent path) of each sibling run still to walk
        stack: list[tuple[int, Sdf.Path | None]] = [(0, None)]
        while stack:
            item, parent = stack.pop()
            while True:
                here = item
                item += 1
                if parent is None:
                    node = Sdf.Path.absoluteRootPath
                elif element[here] < 0:
                    node = parent.AppendProperty(self.tokens[-element[here]])
                else:
                    node = parent.AppendElementString(self.tokens[element[here]])
                self.paths[index[here]] = node
                has_child, has_sibling = jumps[here] > 0 or jumps[here] == -1, jumps[here] >= 0
                if has_child and has_sibling:
                    stack.append((here + jumps[here], parent))
                if has_child:
                    parent = node
                elif not has_sibling:
                    break

        pos = sections["SPECS"][0]
        n = struct.unpack_from("<Q", data, pos)[0]
        paths, pos = _decode_ints(data, pos + 8, n)
        sets, pos = _decode_ints(data, pos, n)
        kinds, _ = _decode_ints(data, pos, n)
        self.specs = [list(spec) for spec in zip(paths.tolist(), sets.tolist(), kinds.tolist())]
        self.spec_of = {self.paths[p]: k for k, (p, _, _) in enumerate(self.specs)}

    def values(self) -> memoryview:
        """The file's bytes after the bootstrap up to the end of its values (before
        :meth:`release`)."""
        assert self.data is not None, "released"
        return memoryview(self.data)[BOOTSTRAP:self.data_end]

    def section(self, name: str) -> bytes:
        """The raw bytes of section ``name`` (kept by :meth:`release` for STRINGS and PATHS)."""
        start, size = self.sections[name]
        return self.data[start:start + size] if self.data is not None else self.kept[name]

    def release(self) -> None:
        """Drop the file's bytes once its values are copied, keeping the sections written
        again as they are."""
        self.kept = {name: self.section(name) for name in ("STRINGS", "PATHS")}
        self.data = None

    def spec_fields(self, spec: int) -> list[int]:
        """Field indices of spec number ``spec`` (its field set, up to the terminator)."""
        start = self.specs[spec][1]
        end = self.fieldsets.index(_NO_FIELD, start)
        return self.fieldsets[start:end]


WRITES_AHEAD = 1
"""Writes a :class:`CrateSamples` may have queued for the writer thread before
:meth:`~CrateSamples.add_many` waits: each holds its frames in memory until written (a bake's
whole chunk); one is written while the caller skins and checks the next."""


class _Writer:
    """The process's writer thread (:func:`_writer`) and the lock that creates it once."""

    executor: ThreadPoolExecutor | None = None
    lock = threading.Lock()


_WRITER = _Writer()


def _writer() -> ThreadPoolExecutor:
    """The process's one writer thread (created on first use; a forked child makes its own):
    file writes release the GIL, so the caller skins and checks the next frames meanwhile."""
    with _WRITER.lock:
        if _WRITER.executor is None:
            _WRITER.executor = ThreadPoolExecutor(max_workers=1,
                                                  thread_name_prefix="dqskin-crate-write")
        return _WRITER.executor


def _forget_writer() -> None:
    _WRITER.executor, _WRITER.lock = None, threading.Lock()


if hasattr(os, "register_at_fork"):
    os.register_at_fork(after_in_child=_forget_writer)


def _close_after(file: AppendFile, queued: collections.deque[Future[Any]],
                 wait: bool = True) -> None:
    """Close ``file`` (an abandoned :class:`~.direct.AppendFile`: nothing staged is written)
    after the writes ``queued`` for it (their errors dropped): now, after waiting for them, or
    (``wait=False``, a writer dropped unclosed) as the writer thread's next task, behind them."""
    pending = [f for f in queued if not f.done()]
    queued.clear()
    if pending and not wait:
        try:
            _writer().submit(file.close, False)
            return
        except RuntimeError:  # the interpreter is shutting the thread down: wait instead
            pass
    try:
        for done in pending:
            try:
                done.result()
            except Exception:
                pass
    except BaseException:  # interrupted while waiting: closed behind the writes still queued
        if any(not f.done() for f in pending):
            try:
                _writer().submit(file.close, False)
            except RuntimeError:
                file.close(False)
        else:
            file.close(False)
        raise
    file.close(False)


class _Attribute:
    __slots__ = ("type_name", "info", "times", "reps", "last")

    def __init__(self, type_name: str, info: tuple[tuple[str, str], ...]) -> None:
        self.type_name, self.info = type_name, info
        self.times: list[np.ndarray] = []
        self.reps: list[np.ndarray] = []
        self.last: tuple[np.ndarray, int] | None = None  # (copy of the last frame added, its rep)


def _holds(rows: Sequence[np.ndarray], lasts: Sequence[np.ndarray | None]) -> np.ndarray:
    """Which frames of each block ``rows[b]`` ((F_b, K_b) floats) equal the frame before them
    (a block's first: ``lasts[b]``, a (K_b,) array or None), as a crate file stores an array
    once; one (sum of F_b,) bool array, the blocks in order. A few elements of every frame are
    compared first (up to 16 evenly spaced ones, gathered for all blocks of the same frame
    count at once), the whole frame only when they all match (a hold, not a move)."""
    F = np.array([len(r) for r in rows], np.intp)
    starts = np.cumsum(F) - F
    same = np.zeros(int(F.sum()), bool)
    by_count: dict[int, list[int]] = {}
    for k, r in enumerate(rows):
        if len(r) and r.shape[1]:
            by_count.setdefault(len(r), []).append(k)
    for count, blocks in by_count.items():
        probes, firsts = [], []
        for k in blocks:
            r, last = rows[k], lasts[k]
            step = -(-r.shape[1] // 16)
            probes.append(r[:, ::step])
            firsts.append(last[::step] if last is not None and last.shape == r.shape[1:]
                          else np.full(probes[-1].shape[1], np.nan, r.dtype))  # never equal
        probe = np.concatenate(probes, axis=1)
        eq = np.empty(probe.shape, bool)
        np.equal(probe[0], np.concatenate(firsts), out=eq[0])
        np.equal(probe[1:], probe[:-1], out=eq[1:])
        widths = np.array([p.shape[1] for p in probes])
        held = np.logical_and.reduceat(eq, np.cumsum(widths) - widths, axis=1)  # (count, B)
        same[starts[blocks] + np.arange(count)[:, None]] = held
    if same.any():
        for i in np.flatnonzero(same):
            k = int(np.searchsorted(starts, i, side="right")) - 1
            f = i - starts[k]
            before = rows[k][f - 1] if f else lasts[k]
            assert before is not None  # frame 0 is a hold only after a last frame
            same[i] = np.array_equal(rows[k][f], before)
    return same


class CrateSamples:
    """A crate layer of time samples, written to ``path`` as they are added.

    Parameters
    ----------
    path : str or os.PathLike
        The file to create (a temporary name: the layer is valid only after :meth:`close`).
    time_codes_per_second : float
        The layer's ``timeCodesPerSecond`` and ``framesPerSecond`` (unused with a ``base``,
        whose own are kept).
    base : str or os.PathLike, optional
        A crate file usd-core wrote (crate version 0.7.0 or later) that already holds a spec,
        without time samples and of a type stored as the samples are (``float3[]`` takes
        ``normal3f[]`` samples), for every attribute that will be added: the new file is that layer
        with the samples (its ``timeCodesPerSecond`` and every other field kept; the time range
        replaced by :meth:`close`'s). Without it, prims above the attributes are ``over`` specs.
    direct : bool
        Write past the page cache where the file system allows it (:mod:`.direct`); False:
        through it.
    hasher : hashlib-like object, optional
        Fed every byte of the file as it is written: the bytes after the bootstrap (its first
        :data:`BOOTSTRAP` bytes) in file order, then the bootstrap, written last. Its digest
        is then the file's without reading it back (a clip layer's checksum).

    Use :meth:`add` for each block of frames of each attribute, then :meth:`close` with the
    layer's time range (or :meth:`abort`).
    """

    def __init__(self, path: str | os.PathLike, time_codes_per_second: float, *,
                 base: str | os.PathLike | None = None, direct: bool = True,
                 hasher: Hasher | None = None) -> None:
        self.path = Path(path)
        self.time_codes_per_second = float(time_codes_per_second)
        self._base = None if base is None else _Base(base)
        self._attrs: dict[str, _Attribute] = {}  # attribute path → its samples, first-added order
        self._keys: dict[str, str] = {}  # an attribute as added → its path's spelling
        self._file: AppendFile | None = AppendFile(self.path, direct=direct)
        self._pos = 0
        self._queued: collections.deque[Future[Any]] = collections.deque()  # not yet known done
        # if never closed: close once the queued writes ended (the descriptor's number could
        # otherwise be reused by another file while they wait for the writer thread)
        self._closer = weakref.finalize(self, _close_after, self._file, self._queued, False)
        self._hasher = hasher
        try:
            self._write([bytes(BOOTSTRAP)])
            if hasher is not None:  # what follows the bootstrap, as it is written
                # arrays are buffers too: NumPy's stubs say so only from Python 3.12
                self._file.observe = hasher.update  # type: ignore[assignment,unused-ignore]
            if self._base is not None:  # its values at their own offsets
                self._write([self._base.values()])
                self._base.release()
        except BaseException:
            self.abort()
            raise

    def _write(self, buffers: Sequence[BytesLike]) -> None:
        self._drain()
        self._pos += self._open().append(buffers)

    def _open(self) -> AppendFile:
        """The file being written (until :meth:`abort` or :meth:`close`)."""
        assert self._file is not None, f"{self.path}: the layer is closed"
        return self._file

    def _write_later(self, write: Callable[..., object], *args: object, size: int) -> None:
        """Queue ``write(*args)`` of ``size`` bytes (a method of the file) for the writer thread,
        in order after the queued ones; waits while :data:`WRITES_AHEAD` are queued. An error
        of a queued write is raised here or later."""
        self._room()
        self._queued.append(_writer().submit(write, *args))
        self._pos += size

    def _room(self) -> None:
        """Wait while :data:`WRITES_AHEAD` writes are queued (raising a queued write's error)."""
        while len(self._queued) >= WRITES_AHEAD:
            self._queued[0].result()  # then dropped: an interrupt while waiting leaves it queued
            self._queued.popleft()

    def _drain(self) -> None:
        """Wait for every queued write (raising the first error)."""
        while self._queued:
            self._queued[0].result()  # (abort then still waits for it before closing)
            self._queued.popleft()

    def _align(self) -> None:
        pad = -self._pos % 8
        if pad:
            self._write([bytes(pad)])

    def add(self, attr: str, type_name: str, times: npt.ArrayLike, values: npt.ArrayLike,
            info: Sequence[tuple[str, str]] = ()) -> None:
        """Write samples of attribute ``attr`` (``/Prim/Path.name``) at ``times`` now.

        Parameters
        ----------
        attr : str
            Attribute path; the same attribute may be added again (a sample at a time already
            added replaces the earlier one, as ``Sdf.Layer.SetTimeSample`` does).
        type_name : str
            Its Sdf value type, one of :data:`VALUE_TYPES` (with a ``base``, the one its spec
            declares).
        times : (F,) float
            Time codes, finite, in any order.
        values : (F, N, 3) float32 for the ``*3f[]`` types, (F, 4, 4) float64 for ``matrix4d``
            (column-vector convention: ``p' = M @ [p, 1]``; stored transposed, as Gf's
            row-vector matrices).
        info : tuple of (str, str)
            Token-valued metadata authored with the attribute (a primvar's ``interpolation``).
        """
        self.add_many([(attr, type_name, times, values, info)])

    def add_many(self, blocks: "Sequence[tuple[str, str, npt.ArrayLike, npt.ArrayLike, "
                 "Sequence[tuple[str, str]]]]") -> None:
        """:meth:`add` of each ``(attr, type_name, times, values, info)`` of ``blocks``, in
        order, queued for the writer thread as one write (a chunk of frames of many attributes:
        one hand-over to the writer instead of one per attribute). Every block is checked
        before any is written."""
        if self._file is None:
            raise InputError(f"{self.path}: the layer is closed")
        new: dict[str, _Attribute] = {}  # attributes first added by these blocks
        seen: dict[int, tuple[Any, np.ndarray]] = {}  # times checked, by id (blocks share them)
        checked = [self._checked(*block, new=new, seen=seen) for block in blocks]
        # waits (and errors of earlier writes) before the records change: what they record
        # is then queued at once
        self._room()
        self._align()  # (every record's size is a multiple of 8: the blocks stay aligned)
        groups: list[Records] = []
        size = 0
        run: list[tuple[str, _Attribute, np.ndarray, np.ndarray, str]] = []
        keys: set[str] = set()
        for item in checked:
            if not item[2].size:
                continue
            self._attrs.setdefault(item[0], item[1])
            if item[0] in keys:  # an attribute again: after its earlier block is recorded
                size += self._plan(run, self._pos + size, groups)
                run, keys = [], set()
            run.append(item)
            keys.add(item[0])
        if run:
            size += self._plan(run, self._pos + size, groups)
        if groups:
            self._write_later(self._open().append_records, groups, size=size)

    def _checked(self, attr: str, type_name: str, times: npt.ArrayLike, values: npt.ArrayLike,
                 info: Sequence[tuple[str, str]] = (), *, new: dict[str, _Attribute],
                 seen: dict[int, tuple[Any, np.ndarray]]
                 ) -> tuple[str, _Attribute, np.ndarray, np.ndarray, str]:
        """``(key, record, times, values, kind)`` of one :meth:`add` (InputError naming
        ``attr`` for what it refuses); the record is the attribute's, or one of ``new`` (the
        records of attributes first added in the same :meth:`add_many`, made here). ``seen``:
        the times objects of the same call already checked (by id; with the object, so the id
        stays its own), and their float64 arrays."""
        kind = VALUE_TYPES.get(type_name)
        if kind is None:
            raise InputError(f"{attr}: cannot write type {type_name!r} as crate samples; one of "
                             f"{', '.join(VALUE_TYPES)}")
        known = seen.get(id(times))
        t = known[1] if known is not None else np.atleast_1d(np.asarray(times, dtype=np.float64))
        if kind == "vec3f[]":
            v = np.asarray(values, dtype=np.float32)
            ok = v.ndim == 3 and v.shape[2] == 3
            if ok and v.size and v.strides[1:] != (12, 4):  # each frame's values in one run
                v = np.ascontiguousarray(v)  # (a mesh's columns of a batch's frames are)
        else:
            v = np.asarray(values, dtype=np.float64)
            ok = v.ndim == 3 and v.shape[1:] == (4, 4)
            if ok:
                v = np.ascontiguousarray(v.transpose(0, 2, 1))
        if not ok or t.ndim != 1 or v.shape[0] != t.shape[0]:
            raise InputError(f"{attr}: expected {len(t)} frames of "
                             f"{'(N, 3)' if kind == 'vec3f[]' else '(4, 4)'} values, got "
                             f"{np.shape(values)}")
        if known is None:
            if not np.all(np.isfinite(t)):
                raise InputError(f"{attr}: sample times must be finite")
            seen[id(times)] = (times, t)
        # an attribute added before: its path was checked then (one parse per attribute)
        key = self._keys.get(attr, "")
        rec = self._attrs.get(key) or new.get(key) if key else None
        if rec is None:
            path = Sdf.Path(attr) if attr else Sdf.Path()
            key = str(path)  # one spelling per attribute (a variant selection's spaces)
            rec = self._attrs.get(key) or new.get(key)
            if rec is None:
                if not (path.IsAbsolutePath() and path.IsPrimPropertyPath()):
                    raise InputError(f"{attr}: not an attribute path (/Prim.name)")
                if self._base is not None:
                    self._check_base_spec(self._base, path, type_name)
                elif path.ContainsPrimVariantSelection():
                    raise InputError(f"{attr}: a variant's attribute needs a base layer that "
                                     "declares it")
                rec = new[key] = _Attribute(type_name, tuple(info))
            self._keys[attr] = key
        if rec.type_name != type_name:
            raise InputError(f"{attr}: added as {rec.type_name} before, now {type_name}")
        return key, rec, t, v, kind

    def _plan(self, run: "Sequence[tuple[str, _Attribute, np.ndarray, np.ndarray, str]]",
              pos: int, groups: list[Records]) -> int:
        """Record the samples of the blocks ``run`` (checked, each of another attribute) from
        file offset ``pos`` (8-byte aligned) on, in order, and append the records that store
        them to ``groups``; returns their bytes. Each frame's value rep is that of the last
        frame written up to it (before the block: the attribute's last one's), computed for
        all blocks at once."""
        rows = [v.reshape(len(t), -1) for _, _, t, v, _ in run]
        F = np.array([len(r) for r in rows], np.intp)
        vec = np.array([kind == "vec3f[]" for *_, kind in run])
        n = np.array([r.shape[1] // 3 for r in rows], np.int64)  # points of a vec3f[] block
        empty = np.repeat(vec & (n == 0), F)  # an empty array is inlined: nothing in the file
        lasts = [None if rec.last is None else rec.last[0] for _, rec, *_ in run]
        written = ~_holds(rows, lasts)
        written[empty] = False
        ends = np.cumsum(F)
        starts = ends - F
        upto = np.cumsum(written)
        nth = upto - np.repeat(upto[starts] - written[starts], F)  # its block's written so far
        count = nth[ends - 1]
        pad = np.where(vec, -(12 * n) % 8, 0)
        stride = np.where(vec, 8 + 12 * n + pad, 128)
        sizes = stride * count
        at = pos + np.cumsum(sizes) - sizes  # where each block's records start
        head = np.where(vec, np.uint64(_rep(_VEC3F, array=True)), np.uint64(_rep(_MATRIX4D)))
        prior = np.array([0 if rec.last is None else rec.last[1] for _, rec, *_ in run],
                         np.uint64)
        offset = np.repeat(at, F) + np.repeat(stride, F) * np.maximum(nth - 1, 0)
        reps = np.where(nth > 0, np.repeat(head, F) | offset.astype(np.uint64),
                        np.repeat(prior, F))
        reps[empty] = _rep(_VEC3F, array=True)
        last_reps = reps[ends - 1].tolist()
        counts, frames, lo, hi = count.tolist(), F.tolist(), starts.tolist(), ends.tolist()
        for k, (_, rec, t, _, _) in enumerate(run):
            rec.times.append(t)
            rec.reps.append(reps[lo[k]:hi[k]])
            r = rows[k]
            if not r.size:  # (an empty array's frames: the last one written stays)
                continue
            rec.last = (r[-1].copy(), last_reps[k])
            if counts[k]:
                groups.append((struct.pack("<Q", int(n[k])) if vec[k] else b"", r.view(np.uint8),
                               int(pad[k]), None if counts[k] == frames[k]
                               else np.flatnonzero(written[lo[k]:hi[k]])))
        return int(sizes.sum())

    @staticmethod
    def _check_base_spec(base: _Base, path: Sdf.Path, type_name: str) -> None:
        spec = base.spec_of.get(path)
        if spec is None or base.specs[spec][2] != _SPEC_ATTRIBUTE:
            raise InputError(f"{path}: the base layer has no attribute spec for it (only "
                             "attributes it declares take samples)")
        for f in base.spec_fields(spec):
            name, rep = base.fields[f]
            if base.tokens[name] == "typeName":
                declared = base.tokens[rep & 0xFFFFFFFF]
                if VALUE_TYPES.get(declared) != VALUE_TYPES[type_name]:  # same storage: ok
                    raise InputError(f"{path}: declared {declared} in the base layer, which "
                                     f"{type_name} samples cannot fill")
            elif base.tokens[name] == "timeSamples":
                raise InputError(f"{path}: has time samples in the base layer already (they "
                                 "would be replaced, not merged)")

    def abort(self) -> None:
        """Close the file unfinished (the caller removes it), once its queued writes ended."""
        if self._file is not None:
            self._closer.detach()
            _close_after(self._file, self._queued)  # the queued writes end first
            self._file = None

    def close(self, start: float, end: float) -> Path:
        """Write the layer's structure (``startTimeCode`` ``start``, ``endTimeCode`` ``end``)
        and close the file; returns its path."""
        if self._file is None:
            raise InputError(f"{self.path}: the layer is closed")
        try:
            self._finish(float(start), float(end))
        finally:
            self.abort()
        return self.path

    # -- the layer's structure -------------------------------------------------------------

    def _finish(self, start: float, end: float) -> None:
        base = self._base
        tokens = {t: i for i, t in enumerate(base.tokens)} if base else {"": 0}
        # without a base, token 0 is the root's element token, never a property name

        def token(s):
            return tokens.setdefault(s, len(tokens))

        # Values: sample times (each distinct vector once), TimeSamples records, the time range.
        self._align()
        times_reps, samples = {}, {}
        self._attrs = {a: rec for a, rec in self._attrs.items() if rec.times}
        for attr, rec in self._attrs.items():
            t, reps = np.concatenate(rec.times), np.concatenate(rec.reps)
            order = np.argsort(t, kind="stable")
            t, reps = t[order], reps[order]
            last = np.append(t[1:] != t[:-1], True)  # a time added again: the later sample
            t, reps = t[last], reps[last]
            key = t.tobytes()
            if key not in times_reps:
                times_reps[key] = _rep(_DOUBLE_VECTOR, self._pos)
                self._write([struct.pack("<Q", len(t)), t.astype("<f8")])
            samples[attr] = _rep(_TIME_SAMPLES, self._pos)
            # _RecursiveWrite offsets of 8: nothing nested after either.
            self._write([np.array([8, times_reps[key], 8, len(reps)], "<u8"), reps.astype("<u8")])
        doubles = {}
        for name, value in (("startTimeCode", start), ("endTimeCode", end),
                            ("framesPerSecond", self.time_codes_per_second),
                            ("timeCodesPerSecond", self.time_codes_per_second)):
            if base is None or name.endswith("TimeCode"):  # a base keeps its rate
                doubles[name] = _rep(_DOUBLE, self._pos)
                self._write([struct.pack("<d", value)])

        fields = list(base.fields) if base else []
        field_index = {f: i for i, f in enumerate(fields)}
        fieldsets = list(base.fieldsets) if base else []
        fieldset_index = {}

        def fieldset(pairs):
            ids = []
            for name, rep in pairs:
                key = (token(name), rep) if isinstance(name, str) else (name, rep)
                if key not in field_index:
                    field_index[key] = len(fields)
                    fields.append(key)
                ids.append(field_index[key])
            members = tuple(ids)
            if members not in fieldset_index:
                fieldset_index[members] = len(fieldsets)
                fieldsets.extend(ids + [_NO_FIELD])
            return fieldset_index[members]

        if base is None:
            specs, paths = self._new_namespace(token, fieldset, samples, doubles)
        else:
            specs, paths = [list(spec) for spec in base.specs], base.section("PATHS")
            replaced = {token(name) for name in doubles} | {token("timeSamples")}
            for k, (path, _, kind) in enumerate(specs):
                attr = str(base.paths[path])
                if kind == _SPEC_PSEUDO_ROOT:
                    extra = list(doubles.items())
                elif attr in samples:
                    extra = [("timeSamples", samples[attr])]
                else:
                    continue
                kept = [fields[f] for f in base.spec_fields(k) if fields[f][0] not in replaced]
                specs[k][1] = fieldset(kept + extra)

        # Structural sections, then the table of contents, then the bootstrap.
        self._align()
        sections = []

        def section(name, *parts):
            sections.append((name, self._pos, sum(len(p) for p in parts)))
            self._write(list(parts))

        names = b"".join(t.encode() + b"\0" for t in tokens)
        packed = _lz4_literals(names)
        section(b"TOKENS", struct.pack("<QQQ", len(tokens), len(names), len(packed)), packed)
        section(b"STRINGS", base.section("STRINGS") if base else struct.pack("<Q", 0))
        rep_bytes = np.array([r for _, r in fields], "<u8").tobytes()
        packed_reps = _lz4_literals(rep_bytes)
        section(b"FIELDS", struct.pack("<Q", len(fields)),
                _compressed_ints([t for t, _ in fields]),
                struct.pack("<Q", len(packed_reps)), packed_reps)
        section(b"FIELDSETS", struct.pack("<Q", len(fieldsets)), _compressed_ints(fieldsets))
        section(b"PATHS", paths)
        section(b"SPECS", struct.pack("<Q", len(specs)),
                *(_compressed_ints(c) for c in zip(*specs)))
        toc = self._pos
        self._write([struct.pack("<Q", len(sections))]
                    + [struct.pack("<16sqq", n, s, z) for n, s, z in sections])
        version = base.version if base else VERSION
        boot = struct.pack("<8s8Bq", _IDENT, *version, 0, 0, 0, 0, 0, toc) + bytes(64)
        self._drain()
        self._open().pwrite(boot, 0)
        self._open().close()
        if self._hasher is not None:
            self._hasher.update(boot)

    def _new_namespace(self, token, fieldset, samples, doubles):
        """Specs and the PATHS section of a layer of ``over`` prims holding the attributes."""
        root = Sdf.Path.absoluteRootPath
        children: dict[Sdf.Path, list[Sdf.Path]] = {root: []}
        props: dict[Sdf.Path, list[Sdf.Path]] = {}
        for attr in self._attrs:
            path = Sdf.Path(attr)
            prim = path.GetPrimPath()
            for p in prim.GetPrefixes():
                if p not in children:
                    children[p] = []
                    children[p.GetParentPath()].append(p)
            props.setdefault(prim, []).append(path)

        def token_vector(names):
            rep = _rep(_TOKEN_VECTOR, self._pos)
            ids = np.array([token(n) for n in names], "<u4")
            self._write([struct.pack("<Q", len(ids)), ids])
            self._align()
            return rep

        paths = [root] + [p for p in children if p != root] + [a for ps in props.values()
                                                               for a in ps]
        path_index = {p: i for i, p in enumerate(paths)}
        specs = []  # (path index, field set index, spec type)
        top = [("primChildren", token_vector([c.name for c in children[root]]))] \
            if children[root] else []
        specs.append((0, fieldset(top + [(k, doubles[k]) for k in sorted(doubles)]),
                      _SPEC_PSEUDO_ROOT))
        over = _rep(_SPECIFIER, _SPECIFIER_OVER, inlined=True)
        for prim, kids in children.items():
            if prim == root:
                continue
            pairs = [("specifier", over)]
            if kids:
                pairs.append(("primChildren", token_vector([c.name for c in kids])))
            if prim in props:
                pairs.append(("properties", token_vector([a.name for a in props[prim]])))
            specs.append((path_index[prim], fieldset(pairs), _SPEC_PRIM))
        not_custom = _rep(_BOOL, 0, inlined=True)
        varying = _rep(_VARIABILITY, _VARIABILITY_VARYING, inlined=True)
        for attr, rec in self._attrs.items():
            pairs = [("custom", not_custom),
                     ("typeName", _rep(_TOKEN, token(rec.type_name), inlined=True)),
                     ("variability", varying)]
            pairs += [(k, _rep(_TOKEN, token(str(val)), inlined=True)) for k, val in rec.info]
            pairs.append(("timeSamples", samples[attr]))
            specs.append((path_index[Sdf.Path(attr)], fieldset(pairs), _SPEC_ATTRIBUTE))

        # The path tree, depth first: (path index, element token, jump) per node; a node with
        # a child and a sibling jumps to the sibling, written after the child's subtree.
        tree_paths: list[int] = []
        tree_tokens: list[int] = []
        jumps: list[int | None] = []  # None until the node's next sibling is written
        stack = [(root, False)]  # (path, has a sibling after it)
        open_jumps: list[tuple[int, int]] = []  # (node index, depth): sibling not written yet
        depth = {root: 0}
        while stack:
            node, has_sibling = stack.pop()
            here = len(tree_paths)
            while open_jumps and open_jumps[-1][1] >= depth[node]:
                at, _ = open_jumps.pop()
                jumps[at] = here - at  # this node is that one's next sibling
            tree_paths.append(path_index[node])
            name = 0 if node == root else token(node.name)
            tree_tokens.append(-name if node.IsPropertyPath() else name)
            kids = list(children.get(node, ())) + list(props.get(node, ()))
            jumps.append(0 if has_sibling and not kids else -1 if kids and not has_sibling
                         else -2 if not kids else None)
            if kids and has_sibling:
                open_jumps.append((here, depth[node]))
            for i, kid in reversed(list(enumerate(kids))):
                depth[kid] = depth[node] + 1
                stack.append((kid, i + 1 < len(kids)))
        return specs, b"".join([struct.pack("<QQ", len(paths), len(tree_paths)),
                                _compressed_ints(tree_paths), _compressed_ints(tree_tokens),
                                _compressed_ints(jumps)])
