"""Biovision Hierarchy (``.bvh``) motion capture: a skeleton and its animation.

A BVH file is a ``HIERARCHY`` of joints (``ROOT``/``JOINT`` with an ``OFFSET`` from the parent,
``CHANNELS`` and optional ``End Site`` leaves) followed by ``MOTION``: ``Frames:``, ``Frame Time:``
(seconds) and one line of channel values per frame, in the order the channels were declared.

How dqskin reads it (the conventions of the format as Biovision, CMU and Blender use them):

* Joint order is the order of declaration (depth first), so parents come before children. End
  Sites are not joints (nothing can be weighted to them); their offsets are kept in
  :attr:`BvhMotion.end_sites` (they give leaf bones their length for automatic weights).
* A joint's local transform is ``T(offset + p) · R``: ``p`` its position channels (``Xposition``
  a translation along x, …), wherever they are written among the channels, and ``R = R₁ · R₂ ·
  … · Rₙ`` its rotation channels in the order written (``Zrotation`` a rotation about z, degrees,
  right-handed): ``Zrotation Yrotation Xrotation`` gives ``R = Rz·Ry·Rx`` (column vectors). This
  is how Blender and three.js read them. Every joint may have its own order; real files mix
  ``Zrotation Yrotation Xrotation`` and ``Zrotation Xrotation Yrotation``.
* The rest pose (bind pose) is every channel at zero: joints at their offsets, unrotated. Position
  channels add to the offset (a root with offset 0, as CMU's, gets exactly its positions).
* Times are frame numbers 0 … F−1; ``time_codes_per_second`` is ``1 / Frame Time`` (a whole
  number when within 1e-4 of one). Between frames the animation interpolates like USD and glTF
  players (rotation slerp, translation lerp: :class:`dqskin.KeyedAnimation`).

Malformed files raise InputError (a ValueError) naming the file, the line and what was expected.
"""

import os
import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..animation import KeyedAnimation
from ..errors import InputError, Param, Spelling
from ..files.inputs import open_input
from ..limits import MAX_INPUT_GIB, check_bytes
from ..scene import Scene
from ..skeleton import Skeleton
from ..validation import FLOAT32_MAX
from . import LOADER_SUFFIXES

__all__ = ["CHANNELS", "SUFFIXES", "BvhMotion", "load", "read_bvh", "scaled", "summary_lines"]

SUFFIXES = LOADER_SUFFIXES["bvh"]

CHANNELS = ("Xposition", "Yposition", "Zposition", "Xrotation", "Yrotation", "Zrotation")
"""Channel names the format defines (case-insensitive in files)."""

MAX_FRAMES = 10_000_000
"""Refuse a ``Frames:`` count beyond this (a corrupt header would otherwise allocate without
bound)."""


@dataclass
class BvhMotion:
    """What a ``.bvh`` file holds, as read.

    Attributes
    ----------
    path : str
    joint_names : list of str, length J
        Declaration order (parents first).
    parents : (J,) int32
        ``-1`` for the root(s).
    offsets : (J, 3) float64
        Rest translation of each joint from its parent (the file's length unit).
    channels : list of tuple of str
        Each joint's channels in file order, canonical spelling (:data:`CHANNELS`).
    end_sites : list of (joint, (3,) float64)
        Each End Site's joint and offset from it.
    frame_time : float
        Seconds per frame.
    values : (F, C) float64
        Channel values per frame, C the total channel count (degrees for rotations), columns in
        the order of ``channels`` (joint by joint).
    """

    path: str
    joint_names: list
    parents: np.ndarray
    offsets: np.ndarray
    channels: list
    end_sites: list
    frame_time: float
    values: np.ndarray

    def __post_init__(self) -> None:
        self.values = np.asarray(self.values, np.float64)
        counts = [len(ch) for ch in self.channels]
        if len(counts) != len(self.joint_names):
            raise InputError(f"{self.path}: {len(self.joint_names)} joints but channels for "
                             f"{len(counts)}")
        if self.values.ndim != 2 or self.values.shape[1] != sum(counts):
            raise InputError(f"{self.path}: values of shape {self.values.shape}: expected (F, "
                             f"{sum(counts)}), one column per channel")
        starts = np.concatenate([[0], np.cumsum(counts)]).astype(int)
        self._columns = [list(range(a, a + n)) for a, n in zip(starts, counts)]

    @property
    def frame_count(self) -> int:
        return int(self.values.shape[0])

    @property
    def frame_rate(self) -> float:
        """Frames per second: ``1 / frame_time``, a whole number when within 1e-4 of one
        (``Frame Time: 0.0083333`` is 120 fps, :func:`dqskin.times.nominal_rate`)."""
        from ..times import nominal_rate
        return nominal_rate(1.0 / self.frame_time)

    def rest_world(self) -> np.ndarray:
        """(J, 4, 4) float64 world rest pose: translations by the summed offsets."""
        J = len(self.joint_names)
        bind = np.tile(np.eye(4), (J, 1, 1))
        for j in range(J):
            p = self.parents[j]
            bind[j, :3, 3] = self.offsets[j] + (bind[p, :3, 3] if p >= 0 else 0.0)
        return bind

    def local_transforms(self, frames: np.ndarray | None = None) -> np.ndarray:
        """(F, J, 4, 4) float64 parent-relative transforms at integer ``frames`` (all by
        default): ``T(offset + positions) · R₁ · … · Rₙ`` (rotation channels in file order)."""
        v = self.values if frames is None else self.values[np.asarray(frames, dtype=np.int64)]
        F, J = v.shape[0], len(self.joint_names)
        local = np.tile(np.eye(4), (F, J, 1, 1))
        local[:, :, :3, 3] = self.offsets
        for j, (names, cols) in enumerate(zip(self.channels, self._columns)):
            rot = np.tile(np.eye(4), (F, 1, 1))
            for name, col in zip(names, cols):
                if name.endswith("position"):
                    local[:, j, "XYZ".index(name[0]), 3] += v[:, col]
                else:
                    rot = rot @ _channel_matrix(name, v[:, col])
            local[:, j, :3, :3] = rot[:, :3, :3]
        return local

    def skeleton(self, name: str | None = None) -> Skeleton:
        """The :class:`dqskin.Skeleton` (bind = rest = all channels zero) driven by the motion."""
        anim = KeyedAnimation(np.arange(self.frame_count, dtype=np.float64),
                              self.local_transforms(), name=self.path)
        return Skeleton(self.joint_names, self.parents, self.rest_world(),
                        name=name or Path(self.path).stem, animation=anim)

    def scene(self) -> Scene:
        """A :class:`dqskin.Scene` with the skeleton and no meshes; times are frame numbers."""
        return Scene(self.path, [], [self.skeleton()],
                     np.arange(self.frame_count, dtype=np.float64),
                     time_codes_per_second=self.frame_rate, up_axis="Y")


def summary_lines(motion: BvhMotion, spell: Spelling = str) -> list[str]:
    """What ``dqskin info`` adds for a BVH file: channels, End Sites, frame time, rotation
    orders and the rest skeleton's size (a mesh of any size and pose is fitted by embedding the
    skeleton; one bound as it is, ``as_is`` of :func:`dqskin.rigging.rig_mesh`, must be in this
    unit and pose, or be matched with ``scale``), with parameters written by
    ``spell`` (as :meth:`dqskin.errors.DqskinError.message`; the CLI: its flags)."""
    from collections import Counter
    orders = Counter("".join(c[0] for c in ch if c.endswith("rotation")) or "none"
                     for ch in motion.channels)
    positions = sum(any(c.endswith("position") for c in ch) for ch in motion.channels)
    rest = motion.rest_world()[:, :3, 3]  # (translations only: End Sites are offsets from it)
    pts = np.concatenate([rest] + [rest[j] + o[None] for j, o in motion.end_sites])
    size = np.ptp(pts, axis=0)
    return [f"BVH: {sum(map(len, motion.channels))} channels, {len(motion.end_sites)} End Sites, "
            f"{motion.frame_count} frames of {motion.frame_time:g} s; position channels on "
            f"{positions} joint{'s' if positions != 1 else ''}",
            "rotation orders (as written, intrinsic): "
            + ", ".join(f"{o} ×{n}" for o, n in orders.most_common()),
            f"rest skeleton: {size[0]:.4g} × {size[1]:.4g} × {size[2]:.4g} units (x × y × z); a "
            "mesh of any size and pose is fitted by embedding this skeleton in it and "
            "retargeting the motion; with " + spell(Param("as_is", True)) + " a mesh must be in "
            "this unit and pose, or be matched with " + spell(Param("scale"))]


def scaled(motion: BvhMotion, scale: float) -> BvhMotion:
    """A copy of ``motion`` with every length (offsets, End Sites, position channels) times
    ``scale``: a skeleton in the units of a mesh."""
    scale = float(scale)
    if not (np.isfinite(scale) and scale > 0):
        raise InputError(Param("scale", scale), ": must be a positive finite number")
    values = motion.values.copy()
    for names, cols in zip(motion.channels, motion._columns):
        for name, col in zip(names, cols):
            if name.endswith("position"):
                values[:, col] *= scale
    return BvhMotion(motion.path, list(motion.joint_names), motion.parents.copy(),
                     motion.offsets * scale, list(motion.channels),
                     [(j, o * scale) for j, o in motion.end_sites], motion.frame_time, values)


def _channel_matrix(name, values):
    """(F, 4, 4) rotations of one rotation channel (``values`` in degrees)."""
    F = values.shape[0]
    m = np.tile(np.eye(4), (F, 1, 1))
    axis = "XYZ".index(name[0])
    a = np.radians(values)
    c, s = np.cos(a), np.sin(a)
    i, k = [(1, 2), (2, 0), (0, 1)][axis]  # the plane the rotation turns
    m[:, i, i] = c
    m[:, k, k] = c
    m[:, i, k] = -s
    m[:, k, i] = s
    return m


class _Tokens:
    """Whitespace-separated words of the HIERARCHY section with their line numbers."""

    def __init__(self, path, lines):
        self.path = path
        self.words = [(w, n + 1) for n, line in enumerate(lines) for w in line.split()]
        self.i = 0

    def error(self, message, line=None):
        if line is None:
            line = self.words[min(self.i, len(self.words) - 1)][1] if self.words else 1
        return InputError(f"{self.path}: line {line}: {message}")

    def next(self, what):
        if self.i >= len(self.words):
            raise self.error(f"unexpected end of file, expected {what}")
        w, n = self.words[self.i]
        self.i += 1
        return w, n

    def expect(self, word):
        w, n = self.next(repr(word))
        if w.upper() != word.upper():
            raise self.error(f"expected {word!r}, got {w!r}", n)
        return w

    def number(self, what):
        w, n = self.next(what)
        if not _NUMBER.fullmatch(w):
            raise self.error(f"expected a number for {what}, got {w!r}", n)
        x = float(w)
        if not abs(x) <= FLOAT32_MAX:
            raise self.error(f"{what}: {w} is not finite or beyond float32 range", n)
        return x

    def peek(self):
        return self.words[self.i][0] if self.i < len(self.words) else None


def _parse_hierarchy(tok, motion):
    tok.expect("HIERARCHY")
    w, n = tok.next("ROOT")
    if w.upper() != "ROOT":
        raise tok.error(f"expected ROOT, got {w!r}", n)
    _parse_joints(tok, motion)
    while tok.peek() is not None and tok.peek().upper() == "ROOT":  # more than one root
        tok.next("ROOT")
        _parse_joints(tok, motion)


def _parse_joints(tok, motion):
    """One ROOT and the joints below it, depth first without recursion (a chain of any depth)."""
    open_joints = [_parse_joint_head(tok, motion, -1)]  # the joints whose '}' is still to come
    while open_joints:
        j = open_joints[-1]
        name = motion.joint_names[j]
        w, n = tok.next(f"JOINT, End Site or '}}' closing {name!r}")
        key = w.upper()
        if key == "}":
            open_joints.pop()
        elif key == "JOINT":
            open_joints.append(_parse_joint_head(tok, motion, j))
        elif key == "END":
            tok.expect("Site")
            tok.expect("{")
            tok.expect("OFFSET")
            site = np.array([tok.number(f"End Site OFFSET of {name!r}") for _ in range(3)])
            tok.expect("}")
            motion.end_sites.append((j, site))
        else:
            raise tok.error(f"expected JOINT, End Site or '}}' in joint {name!r}, got {w!r}", n)


def _parse_joint_head(tok, motion, parent):
    """A joint's name, OFFSET and CHANNELS (up to its children); returns its index."""
    name, n = tok.next("a joint name")
    if name == "{":
        raise tok.error("joint without a name", n)
    j = len(motion.joint_names)
    if name in motion.names:
        raise tok.error(f"duplicate joint name {name!r}", n)
    motion.names.add(name)
    motion.joint_names.append(name)
    motion._parents.append(parent)
    tok.expect("{")
    tok.expect("OFFSET")
    offset = [tok.number(f"OFFSET of {name!r}") for _ in range(3)]
    motion._offsets.append(offset)
    chans = []
    if tok.peek() is not None and tok.peek().upper() == "CHANNELS":
        tok.next("CHANNELS")
        count, cn = tok.next("the channel count")
        if not _COUNT.fullmatch(count) or int(count) > 6:
            raise tok.error(f"joint {name!r}: CHANNELS count must be 0 to 6, got {count!r}", cn)
        for _ in range(int(count)):
            c, cn = tok.next(f"a channel name of {name!r}")
            canon = next((k for k in CHANNELS if k.lower() == c.lower()), None)
            if canon is None:
                raise tok.error(f"joint {name!r}: unknown channel {c!r}; expected one of "
                                f"{', '.join(CHANNELS)}", cn)
            if canon in chans:
                raise tok.error(f"joint {name!r}: channel {canon} listed twice", cn)
            chans.append(canon)
    motion.channels.append(tuple(chans))
    return j


class _Building:
    """Mutable state while parsing."""

    def __init__(self):
        self.joint_names, self._parents, self._offsets = [], [], []
        self.channels, self.end_sites = [], []
        self.names = set()  # (a duplicate name is found in O(1))


_HEADER = re.compile(r"^\s*(frames|frame\s+time)\s*:\s*(\S+)\s*$", re.IGNORECASE)
_COUNT = re.compile(r"[0-9]+")
_NUMBER = re.compile(r"[+-]?([0-9]+\.?[0-9]*|\.[0-9]+)([eE][+-]?[0-9]+)?")

MIN_FRAME_TIME = 1e-6
"""Shortest ``Frame Time:`` (seconds) read: a million frames a second."""


def read_bvh(path: str | os.PathLike, *, max_input_gib: float = MAX_INPUT_GIB) -> BvhMotion:
    """Parse a ``.bvh`` file (UTF-8, with or without a byte-order mark).

    Parameters
    ----------
    path : str or Path
    max_input_gib : float
        Largest array the file may ask for (:func:`dqskin.limits.check_bytes`): the frames ×
        channels values and the frames × joints transforms of its animation.

    Raises
    ------
    InputError
        (a ValueError) Unreadable file (not a regular file); missing or misplaced keywords,
        unknown channels, non-numbers (ASCII decimal numbers only), duplicate joint names; a
        missing ``Frames:`` (a whole number from 1 to :data:`MAX_FRAMES`) or ``Frame Time:``
        (at least :data:`MIN_FRAME_TIME`); fewer frame lines or values than the header says;
        values beyond float32 range. The message names the file and line.
    LimitError
        Frames × channels or frames × joints beyond ``max_input_gib``.
    """
    p = Path(path)
    try:
        with open_input(p) as fh:
            text = fh.read().decode("utf-8-sig", errors="replace")
    except OSError as exc:
        raise InputError(f"{p}: cannot read ({exc.strerror or exc})") from None
    lines = text.splitlines()
    motion_line = next((n for n, line in enumerate(lines) if line.strip().upper() == "MOTION"),
                       None)
    if motion_line is None:
        if not lines or not lines[0].strip().upper().startswith("HIERARCHY"):
            raise InputError(f"{p}: not a BVH file (it does not start with HIERARCHY)")
        raise InputError(f"{p}: no MOTION section")
    tok = _Tokens(p, lines[:motion_line])
    b = _Building()
    _parse_hierarchy(tok, b)
    if tok.peek() is not None:
        raise tok.error(f"unexpected {tok.peek()!r} after the hierarchy")
    header = {}
    n = motion_line + 1
    for key in ("frames", "frame time"):
        m = _HEADER.match(lines[n]) if n < len(lines) else None
        if m is None or re.sub(r"\s+", " ", m.group(1).lower()) != key:
            want = "Frames: N" if key == "frames" else "Frame Time: SECONDS"
            raise InputError(f"{p}: line {n + 1}: expected {want!r}")
        header[key] = (m.group(1), m.group(2), n + 1)
        n += 1
    label, value, line = header["frames"]
    if not _COUNT.fullmatch(value) or not 1 <= int(value) <= MAX_FRAMES:
        raise InputError(f"{p}: line {line}: {label}: {value!r}: expected a whole number from 1 "
                         f"to {MAX_FRAMES}")
    frames = int(value)
    label, value, line = header["frame time"]
    frame_time = float(value) if _NUMBER.fullmatch(value) else None
    if frame_time is None or not (MIN_FRAME_TIME <= frame_time < np.inf):
        raise InputError(f"{p}: line {line}: {label}: {value!r}: expected seconds per frame, at "
                         f"least {MIN_FRAME_TIME:g}")
    c = sum(map(len, b.channels))
    data_lines = [(n + k + 1, r) for k, r in enumerate(lines[n:]) if r.strip()]
    if len(data_lines) < frames:
        raise InputError(f"{p}: Frames: {frames} but only {len(data_lines)} frame lines")
    # before anything is allocated: every value takes two characters at least ("0 ")
    data = sum(len(r) + 1 for _, r in data_lines[:frames])
    if frames * c * 2 > data:  # then some line has fewer values than channels: name it
        for f, (ln, r) in enumerate(data_lines[:frames]):
            _check_count(p, ln, f, len(r.split()), c)
        raise InputError(f"{p}: Frames: {frames} of {c} channels need {frames * c * 2:,} "
                         f"characters at least; its {frames} frame lines have {data:,}")
    check_bytes(frames * c * 8, f"{p}: Frames × channels ({frames:,} × {c:,})", max_input_gib)
    check_bytes(frames * len(b.joint_names) * 128,
                f"{p}: Frames × joints ({frames:,} × {len(b.joint_names):,} transforms)",
                max_input_gib)
    values = np.empty((frames, c), np.float64)
    for f, (ln, r) in enumerate(data_lines[:frames]):
        words = r.split()
        _check_count(p, ln, f, len(words), c)
        try:
            values[f] = [float(w) for w in words]
            ok = r.isascii()  # (float() reads other scripts' digits too)
        except ValueError:
            ok = False
        if not ok:
            bad = next(w for w in words if not _NUMBER.fullmatch(w))
            raise InputError(f"{p}: line {ln}: frame {f}: not a number: {bad!r}")
        if not np.all(np.abs(values[f]) <= FLOAT32_MAX):
            col = int(np.argmax(~(np.abs(values[f]) <= FLOAT32_MAX)))
            raise InputError(f"{p}: line {ln}: frame {f}: channel {col}: {words[col]} is not "
                             f"finite or beyond float32 range")
    return BvhMotion(str(p), b.joint_names, np.asarray(b._parents, np.int32),
                     np.asarray(b._offsets, np.float64).reshape(-1, 3), b.channels, b.end_sites,
                     float(frame_time), values)


def _check_count(path, line, frame, count, channels):
    if count != channels:
        raise InputError(f"{path}: line {line}: frame {frame} has {count} values, expected "
                         f"{channels} (one per channel)")


def load(path: str | os.PathLike, *, clip: str | int | None = None,
         max_input_gib: float = MAX_INPUT_GIB) -> Scene:
    """Read a ``.bvh`` file as a :class:`dqskin.Scene` with one animated skeleton and no meshes
    (``clip`` is accepted for a uniform loader signature; a BVH file has one take)."""
    return read_bvh(path, max_input_gib=max_input_gib).scene()
