"""Time samples streamed straight into a USD crate file (``.usdc``), without an Sdf layer.

A layer that holds nothing but time samples (a clip layer of :mod:`.usd_clips`) is written here
as its arrays arrive: :meth:`CrateSamples.add` writes a block of frames of one attribute to the
file at once (one ``writev``, the GIL released, no ``Vt`` array per frame, nothing kept but
their file offsets), and :meth:`CrateSamples.close` writes what makes it a layer: the prims (as
``over``), the attributes with their sample tables, the layer's time range and rate, the
structural sections and the table of contents. Memory holds one block, not the layer.

The file is crate version 0.8.0, what usd-core writes by default, laid out as
``pxr/usd/sdf/crateFile.cpp`` reads it:

* an 88-byte bootstrap (``PXR-USDC``, version, table-of-contents offset);
* values: each ``Vec3f`` array at an 8-byte aligned offset as a ``uint64`` count and the floats
  (uncompressed, so readers map them without a copy), each ``Matrix4d`` as 16 row-major doubles
  (Gf's row-vector layout), the sample times of each attribute once as a ``vector<double>``, and
  each attribute's ``TimeSamples`` record (times rep, count, one value rep per time);
* the structural sections ``TOKENS``, ``STRINGS``, ``FIELDS``, ``FIELDSETS``, ``PATHS``,
  ``SPECS``: their integer lists coded as ``Sdf_IntegerCompression`` reads them (every delta as
  32 bits) and wrapped, as every compressed section, in one LZ4 block of literals (valid LZ4 that
  any LZ4 decoder reads; the sections are a few hundred bytes);
* the table of contents (name, start, size of each section).

A file is complete only after :meth:`CrateSamples.close`; the caller writes it under a temporary
name and renames it (:class:`~.atomic.atomic_path`). ``tests/test_crate.py`` reads every file
back with usd-core and compares it, value by value and as text, with the same layer written
by Sdf.
"""

import os
import struct
from pathlib import Path

import numpy as np
from pxr import Sdf

__all__ = ["CrateSamples", "VERSION", "VALUE_TYPES"]

VERSION = (0, 8, 0)
"""Crate file version written (usd-core's default for new files)."""

_IDENT = b"PXR-USDC"
_BOOTSTRAP = 88  # ident[8], version[8], tocOffset int64, reserved int64[8]

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

_WRITEV_MAX = 1024  # IOV_MAX on Linux


def _rep(kind, payload=0, *, array=False, inlined=False):
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


def _compressed_ints(values) -> bytes:
    """32-bit integers as ``Sdf_IntegerCompression`` output, with its ``uint64`` size first:
    the most common delta (0, unused), one 2-bit code per integer (all ``11``: a 32-bit delta),
    the deltas to the previous integer, then LZ4."""
    v = np.asarray(values, dtype=np.int64) & 0xFFFFFFFF
    deltas = (np.diff(v, prepend=0) & 0xFFFFFFFF).astype(np.uint32)
    encoded = (struct.pack("<i", 0) + b"\xff" * ((len(v) * 2 + 7) // 8)
               + deltas.astype("<u4").tobytes())
    packed = _lz4_literals(encoded)
    return struct.pack("<Q", len(packed)) + packed


def _nbytes(buffer) -> int:
    return buffer.nbytes if isinstance(buffer, np.ndarray) else len(buffer)


def _writev(fd, buffers) -> int:
    """Write ``buffers`` (bytes, or C-contiguous arrays), in order, at the file position;
    returns the bytes written. No Python object per buffer (a bake writes one per frame: GC-
    tracked objects there cost garbage-collector passes over the whole heap)."""
    total = 0
    for a in range(0, len(buffers), _WRITEV_MAX):
        part = buffers[a:a + _WRITEV_MAX]
        size = sum(map(_nbytes, part))
        done = os.writev(fd, part) if hasattr(os, "writev") else 0
        if done != size:  # a short write (or no writev): the rest one by one
            for b in part:
                n = _nbytes(b)
                if done >= n:
                    done -= n
                    continue
                _write_all(fd, memoryview(b).cast("B")[done:])
                done = 0
        total += size
    return total


def _write_all(fd, data):
    while data.nbytes:
        data = data[os.write(fd, data):]


class _Attribute:
    __slots__ = ("type_name", "info", "times", "reps")

    def __init__(self, type_name, info):
        self.type_name, self.info, self.times, self.reps = type_name, info, [], []


class CrateSamples:
    """A crate layer of time samples, written to ``path`` as they are added.

    Parameters
    ----------
    path : str or os.PathLike
        The file to create (a temporary name: the layer is valid only after :meth:`close`).
    time_codes_per_second : float
        The layer's ``timeCodesPerSecond`` and ``framesPerSecond``.

    Use :meth:`add` for each block of frames of each attribute, then :meth:`close` with the
    layer's time range (or :meth:`abort`). Prims above the attributes are ``over`` specs.
    """

    def __init__(self, path, time_codes_per_second: float):
        self.path = Path(path)
        self.time_codes_per_second = float(time_codes_per_second)
        self._attrs = {}  # attribute path → _Attribute, in first-added order
        self._fd = os.open(self.path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC
                           | getattr(os, "O_CLOEXEC", 0), 0o666)
        self._pos = 0
        self._write([bytes(_BOOTSTRAP)])

    def _write(self, buffers):
        self._pos += _writev(self._fd, buffers)

    def _align(self):
        pad = -self._pos % 8
        if pad:
            self._write([bytes(pad)])

    def add(self, attr: str, type_name: str, times, values, info=()) -> None:
        """Write samples of attribute ``attr`` (``/Prim/Path.name``) at ``times`` now.

        Parameters
        ----------
        attr : str
            Attribute path; the same attribute may be added again with later times.
        type_name : str
            Its Sdf value type, one of :data:`VALUE_TYPES`.
        times : (F,) float
            Time codes, increasing, after any added earlier for ``attr``.
        values : (F, N, 3) float32 for the ``*3f[]`` types, (F, 4, 4) float64 for ``matrix4d``
            (column-vector convention: ``p' = M @ [p, 1]``; stored transposed, as Gf's
            row-vector matrices).
        info : tuple of (str, str)
            Token-valued metadata authored with the attribute (a primvar's ``interpolation``).
        """
        if self._fd is None:
            raise ValueError(f"{self.path}: the layer is closed")
        kind = VALUE_TYPES.get(type_name)
        if kind is None:
            raise ValueError(f"{attr}: cannot write type {type_name!r} as crate samples; one of "
                             f"{', '.join(VALUE_TYPES)}")
        t = np.atleast_1d(np.asarray(times, dtype=np.float64))
        if kind == "vec3f[]":
            v = np.ascontiguousarray(values, dtype=np.float32)
            ok = v.ndim == 3 and v.shape[2] == 3
        else:
            v = np.ascontiguousarray(np.swapaxes(values, -1, -2), dtype=np.float64)
            ok = v.shape[1:] == (4, 4)
        if not ok or v.shape[0] != t.shape[0] or t.ndim != 1:
            raise ValueError(f"{attr}: expected {len(t)} frames of "
                             f"{'(N, 3)' if kind == 'vec3f[]' else '(4, 4)'} values, got "
                             f"{np.shape(values)}")
        rec = self._attrs.get(attr)
        if rec is None:
            path = Sdf.Path(attr)
            if not path.IsPrimPropertyPath():
                raise ValueError(f"{attr}: not an attribute path (/Prim.name)")
            rec = self._attrs[attr] = _Attribute(type_name, tuple(info))
        elif rec.type_name != type_name:
            raise ValueError(f"{attr}: added as {rec.type_name} before, now {type_name}")
        last = rec.times[-1][-1] if rec.times else -np.inf
        if not np.all(np.isfinite(t)) or np.any(np.diff(t) <= 0) or (t.size and t[0] <= last):
            raise ValueError(f"{attr}: sample times must be finite and increasing, after "
                             f"{last} (got {t.min() if t.size else '-'}..."
                             f"{t.max() if t.size else '-'})")
        if not t.size:
            return
        F = len(t)
        self._align()
        if kind == "vec3f[]":
            n = v.shape[1]
            if n == 0:  # an empty array is inlined: payload 0, nothing in the file
                reps = np.full(F, _rep(_VEC3F, array=True), np.uint64)
            else:
                pad = -(12 * n) % 8
                stride = 8 + 12 * n + pad
                per = 3 if pad else 2  # count, floats[, padding] per frame
                buffers = [bytes(pad)] * (per * F)
                buffers[0::per] = [struct.pack("<Q", n)] * F
                buffers[1::per] = list(v.reshape(F, -1))
                self._write(buffers)
                offsets = self._pos - F * stride + stride * np.arange(F, dtype=np.uint64)
                reps = np.uint64(_rep(_VEC3F, array=True)) | offsets
        else:
            self._write([v])
            offsets = self._pos - F * 128 + 128 * np.arange(F, dtype=np.uint64)
            reps = np.uint64(_rep(_MATRIX4D)) | offsets
        rec.times.append(t)
        rec.reps.append(reps)

    def abort(self) -> None:
        """Close the file unfinished (the caller removes it)."""
        if self._fd is not None:
            os.close(self._fd)
            self._fd = None

    def close(self, start: float, end: float) -> Path:
        """Write the layer's structure (``startTimeCode`` ``start``, ``endTimeCode`` ``end``)
        and close the file; returns its path."""
        if self._fd is None:
            raise ValueError(f"{self.path}: the layer is closed")
        try:
            self._finish(float(start), float(end))
        finally:
            self.abort()
        return self.path

    # -- the layer's structure -------------------------------------------------------------

    def _finish(self, start, end):
        tokens = {"": 0}  # the root's element token; index 0 is never a property name

        def token(s):
            return tokens.setdefault(s, len(tokens))

        # Values: sample times (each distinct vector once) and TimeSamples records.
        self._align()
        times_reps, samples = {}, {}
        for attr, rec in self._attrs.items():
            t = np.concatenate(rec.times)
            key = t.tobytes()
            if key not in times_reps:
                times_reps[key] = _rep(_DOUBLE_VECTOR, self._pos)
                self._write([struct.pack("<Q", len(t)), t.astype("<f8")])
            reps = np.concatenate(rec.reps)
            samples[attr] = _rep(_TIME_SAMPLES, self._pos)
            # _RecursiveWrite offsets of 8: nothing nested after either.
            self._write([np.array([8, times_reps[key], 8, len(reps)], "<u8"), reps.astype("<u8")])

        doubles = {}
        for name, value in (("startTimeCode", start), ("endTimeCode", end),
                            ("framesPerSecond", self.time_codes_per_second),
                            ("timeCodesPerSecond", self.time_codes_per_second)):
            doubles[name] = _rep(_DOUBLE, self._pos)
            self._write([struct.pack("<d", value)])

        # The namespace: prims in first-used order, their children and properties.
        root = Sdf.Path.absoluteRootPath
        children, props = {root: []}, {}
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

        fields, field_index, fieldsets, fieldset_index = [], {}, [], {}

        def fieldset(pairs):
            ids = []
            for name, rep in pairs:
                key = (token(name), rep)
                if key not in field_index:
                    field_index[key] = len(fields)
                    fields.append(key)
                ids.append(field_index[key])
            key = tuple(ids)
            if key not in fieldset_index:
                fieldset_index[key] = len(fieldsets)
                fieldsets.extend(ids + [_NO_FIELD])
            return fieldset_index[key]

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

        # The path tree, depth first: (path index, element token, jump) per node.
        tree_paths, tree_tokens, jumps = [], [], []

        def walk(node):
            kids = list(children.get(node, ())) + list(props.get(node, ()))
            for i, child in enumerate(kids):
                here = len(tree_paths)
                tree_paths.append(path_index[child])
                name = token(child.name)
                tree_tokens.append(-name if child.IsPropertyPath() else name)
                jumps.append(None)
                has_child = bool(children.get(child) or props.get(child))
                if has_child:
                    walk(child)
                has_sibling = i + 1 < len(kids)
                jumps[here] = (len(tree_paths) - here if has_child and has_sibling else
                               0 if has_sibling else -1 if has_child else -2)

        tree_paths.append(0)
        tree_tokens.append(0)
        jumps.append(-1 if len(paths) > 1 else -2)
        walk(root)

        # Structural sections, then the table of contents, then the bootstrap.
        self._align()
        sections = []

        def section(name, *parts):
            sections.append((name, self._pos, sum(len(p) for p in parts)))
            self._write(list(parts))

        names = b"".join(s.encode() + b"\0" for s in tokens)
        packed = _lz4_literals(names)
        section(b"TOKENS", struct.pack("<QQQ", len(tokens), len(names), len(packed)), packed)
        section(b"STRINGS", struct.pack("<Q", 0))
        reps = np.array([r for _, r in fields], "<u8").tobytes()
        packed_reps = _lz4_literals(reps)
        section(b"FIELDS", struct.pack("<Q", len(fields)),
                _compressed_ints([t for t, _ in fields]),
                struct.pack("<Q", len(packed_reps)), packed_reps)
        section(b"FIELDSETS", struct.pack("<Q", len(fieldsets)), _compressed_ints(fieldsets))
        section(b"PATHS", struct.pack("<QQ", len(paths), len(tree_paths)),
                _compressed_ints(tree_paths), _compressed_ints(tree_tokens),
                _compressed_ints(jumps))
        spec_cols = list(zip(*specs))
        section(b"SPECS", struct.pack("<Q", len(specs)), *(_compressed_ints(c) for c in spec_cols))
        toc = self._pos
        self._write([struct.pack("<Q", len(sections))]
                    + [struct.pack("<16sqq", n, s, z) for n, s, z in sections])
        boot = struct.pack("<8s8Bq", _IDENT, *VERSION, 0, 0, 0, 0, 0, toc) + bytes(64)
        os.lseek(self._fd, 0, os.SEEK_SET)
        _write_all(self._fd, memoryview(boot))
