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
* Times are frame numbers 0 … F−1; ``time_codes_per_second`` is ``1 / Frame Time``. Between
  frames the animation interpolates like USD and glTF players (rotation slerp, translation lerp:
  :class:`dqskin.KeyedAnimation`).

Malformed files raise InputError (a ValueError) naming the file, the line and what was expected.
"""

import os
import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..animation import KeyedAnimation
from ..errors import InputError, Param, Spelling
from ..scene import Scene
from ..skeleton import Skeleton
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
                     time_codes_per_second=1.0 / self.frame_time, up_axis="Y")


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
    pts = np.concatenate([motion.rest_world()[:, :3, 3]]
                         + [(motion.rest_world()[j] @ np.append(o, 1.0))[None, :3]
                            for j, o in motion.end_sites])
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
        try:
            x = float(w)
        except ValueError:
            raise self.error(f"expected a number for {what}, got {w!r}", n) from None
        if not np.isfinite(x):
            raise self.error(f"{what}: {w} is not finite", n)
        return x

    def peek(self):
        return self.words[self.i][0] if self.i < len(self.words) else None


def _parse_hierarchy(tok, motion):
    tok.expect("HIERARCHY")
    w, n = tok.next("ROOT")
    if w.upper() != "ROOT":
        raise tok.error(f"expected ROOT, got {w!r}", n)
    _parse_joint(tok, motion, -1, n)
    while tok.peek() is not None and tok.peek().upper() == "ROOT":  # more than one root
        _, n = tok.next("ROOT")
        _parse_joint(tok, motion, -1, n)


def _parse_joint(tok, motion, parent, line):
    name, n = tok.next("a joint name")
    if name == "{":
        raise tok.error("joint without a name", n)
    j = len(motion.joint_names)
    if name in motion.joint_names:
        raise tok.error(f"duplicate joint name {name!r}", n)
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
        if not count.isdigit() or int(count) > 6:
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
    while True:
        w, n = tok.next(f"JOINT, End Site or '}}' closing {name!r}")
        key = w.upper()
        if key == "}":
            return
        if key == "JOINT":
            _parse_joint(tok, motion, j, n)
        elif key == "END":
            tok.expect("Site")
            tok.expect("{")
            tok.expect("OFFSET")
            site = np.array([tok.number(f"End Site OFFSET of {name!r}") for _ in range(3)])
            tok.expect("}")
            motion.end_sites.append((j, site))
        else:
            raise tok.error(f"expected JOINT, End Site or '}}' in joint {name!r}, got {w!r}", n)


class _Building:
    """Mutable state while parsing."""

    def __init__(self):
        self.joint_names, self._parents, self._offsets = [], [], []
        self.channels, self.end_sites = [], []


_HEADER = re.compile(r"^\s*(frames|frame\s+time)\s*:\s*(\S+)\s*$", re.IGNORECASE)


def read_bvh(path: str | os.PathLike) -> BvhMotion:
    """Parse a ``.bvh`` file.

    Raises
    ------
    InputError
        (a ValueError) Unreadable file; missing or misplaced keywords, unknown channels,
        non-numbers, duplicate joint names; a missing or non-positive ``Frames:``/``Frame Time:``; a
        frame line with the wrong number of values. The message names the file and line.
    """
    p = Path(path)
    try:
        text = p.read_text(encoding="utf-8", errors="replace")
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
        try:
            header[key] = float(m.group(2))
        except ValueError:
            raise InputError(f"{p}: line {n + 1}: {m.group(1)}: not a number: "
                             f"{m.group(2)!r}") from None
        n += 1
    frames, frame_time = header["frames"], header["frame time"]
    if not (frames == int(frames) and 1 <= frames <= MAX_FRAMES):
        raise InputError(f"{p}: line {motion_line + 2}: Frames: {frames:g}: expected a whole "
                         f"number from 1 to {MAX_FRAMES}")
    if not (np.isfinite(frame_time) and frame_time > 0):
        raise InputError(f"{p}: line {motion_line + 3}: Frame Time: {frame_time:g}: must be "
                         "positive")
    frames = int(frames)
    c = sum(map(len, b.channels))
    data_lines = [(n + k + 1, r) for k, r in enumerate(lines[n:]) if r.strip()]
    if len(data_lines) < frames:
        raise InputError(f"{p}: Frames: {frames} but only {len(data_lines)} frame lines")
    values = np.empty((frames, c), np.float64)
    for f, (ln, r) in enumerate(data_lines[:frames]):
        words = r.split()
        if len(words) != c:
            raise InputError(f"{p}: line {ln}: frame {f} has {len(words)} values, expected {c} "
                             "(one per channel)")
        try:
            values[f] = [float(w) for w in words]
        except ValueError:
            bad = next(w for w in words if not _is_float(w))
            raise InputError(f"{p}: line {ln}: frame {f}: not a number: {bad!r}") from None
    if not np.all(np.isfinite(values)):
        f, col = np.argwhere(~np.isfinite(values))[0]
        raise InputError(f"{p}: frame {f}: channel {col}: value is not finite")
    return BvhMotion(str(p), b.joint_names, np.asarray(b._parents, np.int32),
                     np.asarray(b._offsets, np.float64).reshape(-1, 3), b.channels, b.end_sites,
                     float(frame_time), values)


def _is_float(w):
    try:
        float(w)
        return True
    except ValueError:
        return False


def load(path: str | os.PathLike, *, clip: str | int | None = None) -> Scene:
    """Read a ``.bvh`` file as a :class:`dqskin.Scene` with one animated skeleton and no meshes
    (``clip`` is accepted for a uniform loader signature; a BVH file has one take)."""
    return read_bvh(path).scene()
