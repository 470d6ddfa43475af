"""USD value clips: a long bake as one crate layer per clip of frames, read as one animation.

For ``--out SHOT.usd`` (any of ``.usd/.usdc/.usda``) a clip bake writes::

    SHOT.usd                     top level: the source flattened and unbound, as the single-layer
                                 cache (:class:`~.usd_cache.CacheLayer`), without the samples;
                                 ``clips`` metadata on each root prim above a skinned prim
    SHOT.clips/plan.json         what is baked: source, times, chunking, options, and their key
    SHOT.clips/manifest.usda     the clip manifest: the attributes the clips hold
    SHOT.clips/chunk_00000.usdc  one chunk's time samples, streamed into a crate file as they
                                 are skinned (:class:`~.usd_cache.SampleWriter` into a
                                 :class:`~.crate.CrateSamples`: no Sdf layer, no Vt arrays)
    SHOT.clips/chunk_00000.json  its checksum (XXH3-128, taken as it is written:
                                 :data:`CHECKSUM`), size and the plan key

USD never interpolates across clips: between the last sample of one clip and the first of the
next it holds the earlier one. So chunk ``k`` owns frames ``[lo_k, lo_{k+1})`` but its layer also
holds frame ``lo_{k+1}`` (the boundary sample is in both clips); clip ``k`` is ``active`` from
``lo_k`` and the ``times`` mapping is the identity, so a sub-frame inside the interval between
two chunks is interpolated within clip ``k`` exactly as in one layer. The top level has no
default value on the clip-driven attributes (a default authored there would be stronger than
every clip), so those attributes have no value at the ``Default`` time code.

Each clip layer is written beside its final name (:class:`ClipLayer`) and renamed into place
only when complete, after its checksum record (:func:`write_clip`); :meth:`ClipBake.pending`
verifies the chunks a previous run left (``resume``). :func:`flatten` turns a clip cache into
one layer for tools that do not read clips.
"""

import contextlib
import dataclasses
import errno
import hashlib
import json
import os
import re
import shutil
from collections.abc import Callable, Iterable, Iterator
from pathlib import Path
from types import TracebackType
from typing import IO, Any, Literal

import numpy as np
import numpy.typing as npt
import xxhash
from pxr import Sdf, Tf, Usd, Vt

from ..errors import InputError, OutputExistsError, Param, output_exists
from ..files.atomic import atomic_path, check_interrupted
from ..files.crate import BOOTSTRAP, CrateSamples, Hasher
from ..files.inputs import open_input
from ..options import CorOptions, SkinOptions
from ..readers.usd import _tf_message
from ..readers.usd_layers import open_stage
from ..scene import Scene
from .usd_cache import (
    CLIPS_FOLDER_SUFFIX,
    CacheLayer,
    _source_files,
    clips_folder,
    export_layer,
    frame_bytes,
)

__all__ = ["CHECKSUM", "CLIP_BYTES", "CLIP_CHUNK", "CLIPS_FOLDER_SUFFIX", "LOCK_FILE", "ClipBake",
           "ClipLayer", "bake_lock", "check_outside", "chunk_bounds", "clip_frames",
           "clips_folder", "commit_clip", "flatten", "file_checksum", "holds_clip_bake",
           "input_files", "recorded_chunk", "remove_clip_bake", "verify_chunk", "write_clip"]


_PLAN_DEFAULTS = {"blend_shapes": True, "cor": dataclasses.asdict(CorOptions())}
"""The plan's option entries written only when not these (:meth:`SkinOptions.plan`)."""


_FORMAT = "dqskin-usd-clips/1"
_OURS = re.compile(r"^(chunk_\d+\.(usdc|json)|plan\.json|manifest\.usda|"
                   r"\.(chunk_\d+|plan|manifest)\..+)$")
_TEMP = re.compile(r"^\.(chunk_\d+|plan|manifest)\..+$")


CLIP_CHUNK = 128
"""Fewest frames per clip layer by default, before the clips are evened out over workers
(:func:`clip_frames`)."""

CLIP_BYTES = 32 << 20
"""Samples a clip layer holds at least by default, workers permitting (:func:`clip_frames`): a
small mesh gets longer clips than :data:`CLIP_CHUNK` frames, since each clip has a fixed cost
beyond its frames (a layer, its record, its checksum, a task)."""


LOCK_FILE = ".lock"
"""The file in a clip folder that the bake writing it holds locked (:func:`bake_lock`)."""

_BUSY = (errno.EWOULDBLOCK, errno.EAGAIN)
_NO_LOCKS = (errno.ENOLCK, errno.EOPNOTSUPP, errno.ENOSYS, errno.EINVAL)


@contextlib.contextmanager
def bake_lock(out: str | os.PathLike) -> Iterator[None]:
    """Hold ``out``'s clip folder (:func:`clips_folder`) for one bake: an exclusive ``flock`` on
    its :data:`LOCK_FILE`, released when the block ends or the process does (however it ends).
    A second bake of ``out`` (``resume`` and ``force`` included) then fails at once with
    FileExistsError instead of removing or rewriting the files of one still running. Creates
    the folder; removes the lock file at the end (still holding it: a run that opened it
    meanwhile finds it gone and locks the next one), and the folder when this call made it
    and it is left empty (a refused bake leaves nothing). Where the system or the file system
    has no such locks (Windows; ``ENOLCK``), nothing is locked."""
    folder = clips_folder(out)
    if folder.exists() and not folder.is_dir():
        raise NotADirectoryError(errno.ENOTDIR, "exists and is not a folder", str(folder))
    made = not folder.exists()
    folder.mkdir(parents=True, exist_ok=True)
    fd = _lock(folder / LOCK_FILE)
    try:
        yield
    finally:
        if fd is not None:
            with contextlib.suppress(OSError):
                os.unlink(folder / LOCK_FILE)
            os.close(fd)
        if made:
            with contextlib.suppress(OSError):
                folder.rmdir()  # only when empty


def _lock(path: Path) -> int | None:
    """A descriptor of ``path`` holding its exclusive lock (None where locks do not exist)."""
    try:
        import fcntl
    except ImportError:
        return None
    nofollow = getattr(os, "O_NOFOLLOW", 0)  # (a link there is not followed, nor truncated)
    for _ in range(8):
        try:  # made as the umask allows: another user's bake may lock it after this one
            fd = os.open(path, os.O_RDWR | os.O_CREAT | nofollow, 0o666)
        except PermissionError:  # another user's lock file (flock needs no write access)
            fd = os.open(path, os.O_RDONLY | nofollow)
        except FileNotFoundError:
            if path.parent.is_dir():
                raise
            path.parent.mkdir(parents=True, exist_ok=True)  # the bake that made it removed it
            continue
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError as exc:
            os.close(fd)
            if exc.errno in _NO_LOCKS:
                return None
            if exc.errno in _BUSY:
                try:
                    pid = f" (pid {int(path.read_text().strip())})"
                except (OSError, ValueError):
                    pid = ""
                raise OutputExistsError(
                    f"{path.parent}: another dqskin clip bake{pid} is writing it; let it finish "
                    "or stop it, then rerun (", Param("resume", True), " completes it, ",
                    Param("force", True), " starts over)") from None
            raise
        try:
            st, now = os.fstat(fd), os.stat(path)
            if (st.st_dev, st.st_ino) == (now.st_dev, now.st_ino):
                with contextlib.suppress(OSError):  # (read-only: no pid to tell)
                    os.ftruncate(fd, 0)
                    os.write(fd, f"{os.getpid()}\n".encode())
                return fd
        except FileNotFoundError:
            pass
        os.close(fd)  # the run that held it removed it meanwhile: lock the next one
    raise OutputExistsError(f"{path}: removed and made again while locking it; rerun")


def clip_frames(scene: Scene, frames: int, normals: bool = True, velocities: bool = True,
                workers: int | None = None) -> int:
    """Default frames per clip layer of a bake of ``frames`` frames: :data:`CLIP_CHUNK`, or as
    many more as hold :data:`CLIP_BYTES` of samples (CesiumMan's 3,273 points: 854 frames
    points only, 284 with normals and velocities; a 30,000-point character: 128).

    With ``workers`` task slots, so that they share the work evenly: no more than
    ``ceil(frames / (4 workers))`` frames (but not under :data:`CLIP_CHUNK`, so each slot gets
    four clips only from ``512 workers`` frames on); then, for the ``k`` clips per slot that
    makes, ``ceil(frames / (k workers))`` frames: every slot gets ``k`` clips or one fewer, all
    of one length but the last (a mesh of 128-frame clips, 1,292 frames on 2 slots: 12 clips of
    108 frames, six each, instead of 11 of 128, six and five); with fewer frames than slots,
    one frame per clip."""
    F = int(frames)
    n = max(1, CLIP_BYTES // max(frame_bytes(scene, normals, velocities), 1))
    if not workers or F < 1:
        return max(CLIP_CHUNK, n)
    w = int(workers)
    if F < w:
        return 1
    n = max(CLIP_CHUNK, min(n, -(-F // (4 * w))))
    k = -(-(-(-F // n)) // w)  # clips per slot
    return -(-F // (k * w))


def _recorded(out: str | os.PathLike, key: str) -> Any:
    """``key`` of the plan of the earlier bake in ``out``'s clip folder (its ``plan.json``), None
    without one (or an unreadable one)."""
    return _recorded_in(clips_folder(out), key)


def _recorded_in(folder: str | os.PathLike, key: str) -> Any:
    try:
        with open_input(Path(folder) / "plan.json") as fh:  # (never a FIFO: InputError)
            return json.loads(fh.read()).get(key)
    except (OSError, ValueError, AttributeError):
        return None


def input_files(stage: Usd.Stage, src: str | os.PathLike,
                inputs: Iterable[str | os.PathLike] = ()) -> list[str]:
    """Every file a bake of ``src`` reads: the layers of its ``stage`` and ``inputs`` (the
    command's other files: ``--weights``, ``--skeleton``)."""
    return [*_source_files(stage, src), *map(str, inputs)]


def check_outside(out: str | os.PathLike, files: Iterable[str | os.PathLike],
                  src: str | os.PathLike) -> None:
    """InputError (a ValueError) when one of ``files`` (``src`` and the layers it reads) is
    inside ``out``'s clip folder, where a clip bake writes and ``force`` removes."""
    inside = clips_folder(out).resolve()
    for f in sorted(map(str, files)):
        if os.path.exists(f) and inside in Path(f).resolve().parents:
            what = "" if _same_path(f, src) else f" (read by {src})"
            raise InputError(f"{f}{what}: inside {clips_folder(out)}, where a clip bake of "
                             f"{Path(out).name} writes; move it out of that folder first")


def holds_clip_bake(out: str | os.PathLike) -> bool:
    """Whether ``out``'s clip folder holds a clip bake of ``out`` (its plan names it)."""
    return _recorded(out, "out") == Path(out).name


def remove_clip_bake(out: str | os.PathLike) -> None:
    """Remove the clip bake of ``out`` that a single layer written there replaced: dqskin's own
    files in its clip folder (others stay; the folder too)."""
    _remove_files(clips_folder(out), _OURS)


def _remove_files(folder: Path, pattern: re.Pattern[str]) -> None:
    """Remove ``folder``'s files whose names match, and its temporary folders (:mod:`.atomic`)."""
    for p in folder.iterdir():
        if pattern.match(p.name):
            if _TEMP.match(p.name) and p.is_dir() and not p.is_symlink():
                shutil.rmtree(p, ignore_errors=True)
            elif p.is_file():
                with contextlib.suppress(OSError):
                    p.unlink()


def recorded_chunk(out: str | os.PathLike) -> int | None:
    """The frames per clip of the earlier bake in ``out``'s clip folder, or None: ``--resume``
    without ``--chunk`` continues with the chunks that bake was started with, whatever the
    default would be now."""
    chunk = _recorded(out, "chunk")
    return chunk if isinstance(chunk, int) and not isinstance(chunk, bool) and chunk >= 1 \
        else None


def chunk_bounds(count: int, chunk: int) -> list[tuple[int, int]]:
    """``[(lo, hi), ...]``: chunk ``k`` owns frames ``lo..hi-1``; its clip layer holds frames
    ``lo..min(hi, count - 1)`` (the next chunk's first frame too)."""
    if int(chunk) < 1:
        raise InputError(Param("chunk", chunk), ": must be at least 1")
    return [(lo, min(lo + chunk, count)) for lo in range(0, count, chunk)]


def _chunk_name(index: int, count: int) -> str:
    return f"chunk_{index:0{max(5, len(str(count - 1)))}d}"


CHECKSUM = "xxh3_128_crate"
"""The checksum a clip layer's record holds, under this key: XXH3-128 in hex of the layer's
bytes after its crate bootstrap (the first :data:`~.crate.BOOTSTRAP` = 88), then of the
bootstrap: the order the writer writes them in (the bootstrap last), so it hashes the layer as
it goes (:class:`~.crate.CrateSamples` ``hasher``) instead of reading it back. ``(tail -c +89
FILE; head -c 88 FILE) | xxh128sum`` prints it. It guards against torn and damaged files, not
against tampering. Records of earlier bakes hold ``xxh3_128`` (the whole file in order, as
``xxh128sum FILE`` prints it) or ``sha256`` instead, and are verified by that
(:func:`verify_chunk`)."""

_HASHES: dict[str, Callable[[], Hasher]] = {CHECKSUM: xxhash.xxh3_128, "xxh3_128": xxhash.xxh3_128,
                                           "sha256": hashlib.sha256}
_BLOCK = 1 << 20


def _read_up_to(fh: IO[bytes], n: int) -> bytes:
    """``n`` bytes of ``fh`` (fewer only at its end), whatever its reads return."""
    data = b""
    while len(data) < n and (more := fh.read(n - len(data))):
        data += more
    return data


def file_checksum(path: str | os.PathLike, algorithm: str = CHECKSUM) -> str:
    """Hex digest of a file by ``algorithm`` (a key of a clip record: :data:`CHECKSUM`,
    ``"xxh3_128"`` or ``"sha256"``), read in 1 MB blocks (the GIL is released while hashing)."""
    h = _HASHES[algorithm]()
    block = bytearray(_BLOCK)
    view = memoryview(block)
    with open(path, "rb", buffering=0) as fh:
        head = _read_up_to(fh, BOOTSTRAP) if algorithm == CHECKSUM else b""
        while n := fh.readinto(block):
            h.update(view[:n])
    h.update(head)
    return h.hexdigest()


def _same_path(a: str | os.PathLike, b: str | os.PathLike) -> bool:
    return Path(a).resolve() == Path(b).resolve()


def _write_json(path: str | os.PathLike, data: object, overwrite: bool = True) -> None:
    with atomic_path(path, overwrite=overwrite) as tmp:
        Path(tmp).write_text(json.dumps(data, indent=1) + "\n")


class ClipLayer:
    """One chunk's clip layer while it is written: its :class:`~.crate.CrateSamples` (``samples``,
    for :meth:`~.usd_cache.SampleWriter.write_chunks`) in the temporary file of its claim
    (``claim``, an :class:`~.atomic.atomic_path` beside ``path``).

    :meth:`finish` completes the file, sets :attr:`digest` (its checksum) and returns the claim
    for :func:`commit_clip`;
    :meth:`discard` (or leaving the ``with`` block on an exception) removes it."""

    digest: str | None = None

    def __init__(self, path: str | os.PathLike, time_codes_per_second: float) -> None:
        self.claim = atomic_path(Path(path), overwrite=True)
        try:
            # hashed as it is written (never read back), so past the page cache too
            self._hasher = _HASHES[CHECKSUM]()
            self.samples = CrateSamples(self.claim.open(), time_codes_per_second,
                                        hasher=self._hasher)
        except BaseException:
            self.claim.discard()
            raise

    def finish(self, times: npt.ArrayLike) -> atomic_path:
        """Close the layer (its time range from ``times``); returns the claim holding it. Its
        checksum (:data:`CHECKSUM`) is then :attr:`digest`."""
        times = np.asarray(times, np.float64)
        try:
            self.samples.close(times[0], times[-1])
        except BaseException:
            self.discard()
            raise
        self.digest = self._hasher.hexdigest()
        return self.claim

    def discard(self) -> None:
        """Close and remove the unfinished layer."""
        self.samples.abort()
        self.claim.discard()

    def __enter__(self) -> "ClipLayer":
        return self

    def __exit__(self, exc_type: type[BaseException] | None, exc: BaseException | None,
                 tb: TracebackType | None) -> Literal[False]:
        if exc_type is not None:
            self.discard()
        return False


def write_clip(layer: ClipLayer, key: str, times: npt.ArrayLike) -> str:
    """Finish one chunk's ``layer``, record its checksum (:data:`CHECKSUM`) beside its final
    name (``chunk_k.json`` for ``chunk_k.usdc``), then rename it into place
    (:meth:`ClipLayer.finish`, then :func:`commit_clip`). Returns the checksum.

    A process killed at any point leaves either no layer under ``path`` or one whose record
    does not match it (the record was replaced first), which :func:`verify_chunk` rejects.
    """
    claim = layer.finish(times)
    return commit_clip(claim, key, times, layer.digest)


def commit_clip(claim: atomic_path, key: str, times: npt.ArrayLike,
                digest: str | None = None) -> str:
    """Record the checksum (:data:`CHECKSUM`) of the layer :meth:`ClipLayer.finish` left in
    ``claim`` (``path.json``, with ``key``), then rename it into place. ``digest``: that file's
    checksum if already known (:attr:`ClipLayer.digest`), else read from the file
    (:func:`file_checksum`). Returns the checksum."""
    path, times = claim.path, np.asarray(times, np.float64)
    try:
        tmp = claim.open()
        digest = digest or file_checksum(tmp)
        _write_json(path.with_suffix(".json"), {
            "layer": path.name, CHECKSUM: digest, "bytes": os.path.getsize(tmp), "plan": key,
            "first": float(times[0]), "last": float(times[-1]), "frames": int(len(times))})
        claim.commit()
    except BaseException:
        claim.discard()
        raise
    return digest


def verify_chunk(path: str | os.PathLike, key: str, record: dict[str, Any] | None = None) -> bool:
    """True when the clip layer ``path`` exists and matches its record (``record``, else read:
    :func:`_record_of`): the same plan key, size and checksum (:data:`CHECKSUM`, or
    ``xxh3_128`` or ``sha256`` in the records of earlier bakes; the first of these a record
    holds decides)."""
    path = Path(path)
    record = _record_of(path) if record is None else record
    if record is None or record["plan"] != key:
        return False
    algorithm = next(a for a in _HASHES if a in record)
    try:
        return (path.is_file() and path.stat().st_size == record.get("bytes")
                and file_checksum(path, algorithm) == record[algorithm])
    except OSError:
        return False


def _record_of(path: str | os.PathLike) -> dict[str, Any] | None:
    """The dqskin record of clip layer ``path`` (``chunk_00000.json`` beside it: a dict naming
    the layer, with a plan key and a checksum), or None (another tool's file, or none)."""
    try:
        with open_input(Path(path).with_suffix(".json")) as fh:  # (never a FIFO: InputError)
            record = json.loads(fh.read())
    except (OSError, ValueError):
        return None
    if (isinstance(record, dict) and record.get("layer") == Path(path).name
            and isinstance(record.get("plan"), str) and any(a in record for a in _HASHES)):
        return record
    return None


class ClipBake:
    """The driver's side of a clip bake: checks, the plan, resume verification, and the top
    level written last.

    Parameters
    ----------
    scene : Scene
        A USD scene (:func:`dqskin.readers.usd.load_usd`).
    out : str or Path
        ``SHOT.usd/.usdc/.usda``; the clips go to :func:`clips_folder`.
    times : (F,) float64
        Time codes to bake (in any order; baked sorted, each once).
    chunk : int
        Frames each clip layer owns.
    options : dqskin.SkinOptions
        What the clips hold (normals, velocities) and are skinned with; the fields that change
        the result (:meth:`~dqskin.options.SkinOptions.plan`) are part of the plan key.
    force : bool
        Start over: an existing ``out`` and the clip files of an earlier bake are replaced (the
        ``out`` of an earlier clip bake is removed at once: it reads those clip files).
    resume : bool
        Keep the chunks of an earlier bake of the same plan that verify; redo the rest.
    inputs : sequence of path
        Other files the bake reads (refused inside the clip folder, as the source's layers).

    Raises
    ------
    FileExistsError
        ``out`` or an earlier clip bake exists, without ``force`` (or ``resume``).
    InputError
        ``resume`` over a bake of another input or other settings (a ValueError).
    """

    def __init__(self, scene: Scene, out: str | os.PathLike, times: npt.ArrayLike, chunk: int,
                 options: SkinOptions, *, force: bool = False, resume: bool = False,
                 inputs: Iterable[str | os.PathLike] = ()) -> None:
        normals, velocities = options.normals, options.velocities
        self.cache = CacheLayer(scene, out)
        self.out, self.folder = Path(out), clips_folder(out)
        check_outside(out, input_files(self.cache.stage, self.cache.src, inputs), self.cache.src)
        # a cache is keyed by time: sorted, each once (the clip metadata's "active" and "times"
        # need increasing times: unsorted --frames gave a cache wrong at almost every time)
        self.times = np.unique(np.asarray(times, np.float64))
        self.bounds = chunk_bounds(len(self.times), chunk)
        self.targets = self.cache.all_targets(normals=normals, velocities=velocities)
        src = Path(self.cache.src).resolve()
        st = src.stat()
        plan: dict[str, Any] = {"format": _FORMAT, "source": str(src), "source_bytes": st.st_size,
                "source_mtime_ns": st.st_mtime_ns, "frames": len(self.times),
                "first": float(self.times[0]), "last": float(self.times[-1]),
                "times_sha256": hashlib.sha256(self.times.tobytes()).hexdigest(),
                "chunk": int(chunk), "chunks": len(self.bounds),
                "options": dict(sorted(options.plan().items())),
                "attributes": sorted(t.attr for t in self.targets.values())}
        self.key = hashlib.sha256(json.dumps(plan, sort_keys=True).encode()).hexdigest()
        self.plan = dict(plan, key=self.key, out=self.out.name)  # (the name: not in the key)
        self.resumed = self._check_existing(force, resume)
        self.overwrite = force or self.resumed

    def _check_existing(self, force: bool, resume: bool) -> bool:
        """True when resuming a bake of this plan; clears an earlier bake when ``force``."""
        plan_file = self.folder / "plan.json"
        if self.folder.exists() and not self.folder.is_dir():
            raise NotADirectoryError(errno.ENOTDIR, "exists and is not a folder", str(self.folder))
        if self.folder.is_dir():  # before anything is removed: a bake would fail on it midway
            layers = [self.clip_path(k) for k in range(len(self.bounds))]
            for p in [plan_file, self.folder / "manifest.usda", *layers,
                      *(q.with_suffix(".json") for q in layers)]:
                if p.exists() and not p.is_file():  # (a link to a file is one)
                    raise InputError(f"{p}: not a file, where this clip bake writes one; move it "
                                     f"out of {self.folder.name}/")
        earlier = plan_file.exists()
        self._check_owner(self.out)
        if earlier and resume and not force:
            if _recorded(self.out, "key") != self.key:
                raise InputError(f"{self.folder}: an earlier bake {self._differs()}; rerun it "
                                 "with those, or use ", Param("force", True), " to start over")
            return True
        if not force:
            self.check_free(self.out)
            self._claim(plan_file)
        elif self.folder.is_dir():
            if earlier and self.out.is_file():  # it reads the clips about to be replaced: an
                self.out.unlink()  # interrupted --force left it showing a mix of two bakes
            _remove_files(self.folder, _OURS)
        return False

    def _differs(self) -> str:
        """What the earlier bake's plan has that this one's does not, in words."""
        try:
            with open_input(self.folder / "plan.json") as fh:  # (never a FIFO: InputError)
                return self._compare_plans(json.loads(fh.read()))
        except (OSError, ValueError):
            return "with an unreadable plan.json"
        except (TypeError, AttributeError, KeyError):  # a plan.json edited by hand
            return "with other settings"

    def _compare_plans(self, old: object) -> str:
        if not isinstance(old, dict) or old.get("format") != _FORMAT:
            return "of another format"
        new = self.plan
        if old.get("source") != new["source"]:
            return f"of another input ({old.get('source')})"
        if (old.get("source_bytes"), old.get("source_mtime_ns")) != \
                (new["source_bytes"], new["source_mtime_ns"]):
            return "of this input before it changed (its size or modification time)"
        said = []
        if any(old.get(k) != new[k] for k in ("frames", "first", "last", "times_sha256")):
            said.append(f"of {old.get('frames')} frames from {old.get('first'):g} to "
                        f"{old.get('last'):g} (now {new['frames']} from {new['first']:g} to "
                        f"{new['last']:g}: other times selected)")
        if old.get("chunk") != new["chunk"]:
            said.append(f"in clips of {old.get('chunk')} frames (now {new['chunk']})")
        # (a plan leaves out the settings that are at their defaults)
        opts = {**_PLAN_DEFAULTS, **new["options"]}
        was = {**_PLAN_DEFAULTS, **(old.get("options") or {})}
        said += [f"with {k} {was.get(k)!r} (now {opts.get(k)!r})"
                 for k in sorted(set(opts) | set(was)) if opts.get(k) != was.get(k)]
        if not said and old.get("attributes") != new["attributes"]:
            said.append("of other attributes")
        return ", ".join(said) if said else "with other settings"

    @staticmethod
    def _check_owner(out: str | os.PathLike) -> None:
        """InputError (a ValueError) when ``out``'s clip folder holds an earlier bake of another
        top-level file (``shot.usda`` beside ``shot.usd``: one ``shot.clips/``), ``force`` or
        not."""
        out, folder = Path(out), clips_folder(out)
        owner = _recorded(out, "out")
        if isinstance(owner, str) and owner != out.name:
            raise InputError(f"{folder}: holds the clips of {owner}, another output; bake "
                             f"{out.name} under another name (or remove {owner} and "
                             f"{folder.name}/ first)")

    def _claim(self, plan_file: Path) -> None:
        """Write the plan exclusively: of two runs baking to one output without ``force``, the
        second to get here fails (the check before it is not enough: both can pass it, then
        write each other's clips and remove each other's temporary files)."""
        self.folder.mkdir(parents=True, exist_ok=True)
        try:
            _write_json(plan_file, self.plan, overwrite=False)
        except (FileExistsError, FileNotFoundError):  # (the other run's start-up clears temporary
            # files in the folder, this run's plan being written among them)
            raise OutputExistsError(f"{self.folder}: another clip bake is there or being "
                                    "written; use ", Param("resume", True), " to complete it or ",
                                    Param("force", True), " to start over") from None

    @staticmethod
    def check_free(out: str | os.PathLike, *, force: bool = False, resume: bool = False) -> None:
        """The refusals that need no plan (before starting workers): FileExistsError when
        ``out`` or an unfinished clip bake exists, unless ``force`` or ``resume``; InputError (a
        ValueError) when its clip folder belongs to another output (:meth:`_check_owner`)."""
        ClipBake._check_owner(out)
        if force or resume:
            return
        out, folder = Path(out), clips_folder(out)
        if out.exists():
            raise output_exists(out)
        if (folder / "plan.json").exists():
            raise OutputExistsError(f"{folder}: an unfinished clip bake is there; use ",
                                    Param("resume", True), " to complete it or ",
                                    Param("force", True), " to start over")

    def abandon(self) -> None:
        """After a failed bake: remove the plan and the manifest when no clip layer is in the
        folder (nothing was kept, so the next bake of ``out`` starts afresh instead of being
        told to resume one)."""
        if any(self.folder.glob("chunk_*.usdc")):
            return
        for name in ("plan.json", "manifest.usda"):
            with contextlib.suppress(OSError):
                (self.folder / name).unlink()

    def clip_path(self, index: int) -> Path:
        return self.folder / (_chunk_name(index, len(self.bounds)) + ".usdc")

    def chunk_times(self, index: int) -> np.ndarray:
        """(F_k,) times of clip layer ``index``: its own frames and the next chunk's first."""
        lo, hi = self.bounds[index]
        return self.times[lo:min(hi + 1, len(self.times))]

    def pending(self) -> list[int]:
        """Indices of the chunks to bake: all, or when resuming those that do not verify. Writes
        the plan and the manifest (and removes temporary files a killed run left)."""
        self.folder.mkdir(parents=True, exist_ok=True)
        _remove_files(self.folder, _TEMP)
        todo = [k for k in range(len(self.bounds))
                if not (self.resumed and verify_chunk(self.clip_path(k), self.key))]
        check_interrupted()
        _write_json(self.folder / "plan.json", self.plan)
        manifest = Sdf.Layer.CreateAnonymous(".usda")
        for target in self.targets.values():
            target.spec(manifest)
        with atomic_path(self.folder / "manifest.usda") as tmp:
            if not manifest.Export(str(tmp)):
                raise InputError(f"{self.folder / 'manifest.usda'}: USD could not write it")
        return todo

    def finish(self) -> Path:
        """Check every chunk is in place, then write the top level (atomically). Returns it."""
        for k in range(len(self.bounds)):  # in place, of this plan (not a late write of a
            record = _record_of(self.clip_path(k))  # stopped bake's remote worker)
            if not self.clip_path(k).is_file():
                raise InputError(f"{self.clip_path(k)}: missing (not written)")
            if record is None or record["plan"] != self.key:
                raise InputError(f"{self.clip_path(k)}: its record is missing or of another "
                                 "bake; rerun with ", Param("resume", True), " to redo it")
        layer, t = self.cache.layer, self.times
        with Sdf.ChangeBlock():
            for target in self.targets.values():
                spec = layer.GetAttributeAtPath(target.attr)
                if spec is not None and spec.HasDefaultValue():
                    spec.ClearDefaultValue()  # a default here would be stronger than the clips
            rel = f"./{self.folder.name}/"
            assets = Sdf.AssetPathArray([rel + self.clip_path(k).name
                                         for k in range(len(self.bounds))])
            active = Vt.Vec2dArray([(float(t[lo]), float(k))
                                    for k, (lo, _) in enumerate(self.bounds)])
            mapping = Vt.Vec2dArray(sorted({(float(t[0]),) * 2, (float(t[-1]),) * 2}))
            roots = sorted({str(Sdf.Path(x.attr).GetPrefixes()[0]) for x in self.targets.values()})
            for root in roots:
                layer.GetPrimAtPath(root).SetInfo("clips", {"default": {
                    "assetPaths": assets, "primPath": root, "active": active, "times": mapping,
                    "manifestAssetPath": Sdf.AssetPath(rel + "manifest.usda")}})
        self.cache.set_metadata(t.min(), t.max(), note=f"value-clip cache ({len(self.bounds)} "
                                f"clips in {self.folder.name}/)")
        claim = atomic_path(self.out, overwrite=self.overwrite)
        try:
            export_layer(layer, claim)
        except BaseException:
            claim.discard()
            raise
        claim.commit()
        _remove_files(self.folder, _TEMP)
        return self.out


def flatten(src: str | os.PathLike, out: str | os.PathLike, *, overwrite: bool = False) -> Path:
    """Write the composed stage ``src`` (a clip cache, or any stage) as one layer ``out``: every
    clip's samples become ordinary time samples, for tools that do not read value clips. The
    whole animation is held in memory while writing.

    Every clip layer the stage's ``clips`` metadata names must resolve, and one with a dqskin
    record beside it (``chunk_00000.json``) must match it (:func:`verify_chunk`) and its
    folder's plan: USD would skip a missing clip and hold the samples around it, and copy a
    damaged one (InputError, a ValueError, naming the layer; ``resume`` redoes it). That
    check reads each such layer once more. ``.usd`` output is crate. ``out``
    appears only when complete (exclusively unless ``overwrite``); ``src`` is never modified.
    Returns ``out``.
    """
    out = Path(out)
    if out.suffix.lower() not in (".usd", ".usdc", ".usda"):
        raise InputError(f"{out}: cannot write extension {out.suffix!r}; use .usd/.usdc/.usda")
    if not Path(src).is_file():
        raise InputError(f"{src}: no such file")
    if out.exists() and not overwrite:  # (checked again when it is claimed)
        raise output_exists(out, "overwrite")
    try:
        stage = open_stage(src, Usd.Stage.LoadAll)  # (clip layers included: no FIFO)
    except Tf.ErrorException as exc:
        raise InputError(f"{src}: cannot open as USD: {_tf_message(exc)}") from None
    if stage is None:
        raise InputError(f"{src}: cannot open the stage")
    try:
        _check_clips(stage, src)
        flat = stage.Flatten()  # opens every clip layer: only then are all the inputs known
    except Tf.ErrorException as exc:
        raise InputError(f"{src}: cannot flatten: {_tf_message(exc)}") from None
    for layer in stage.GetUsedLayers():
        real = layer.realPath and layer.realPath.split("[", 1)[0]
        if real and out.exists() and os.path.samefile(real, out):
            raise InputError(f"{out}: refusing to overwrite an input of {src}")
    claim = atomic_path(out, overwrite=overwrite)
    try:
        export_layer(flat, claim)
    except BaseException:
        claim.discard()
        raise
    claim.commit()
    return out


def _check_clips(stage: Usd.Stage, src: str | os.PathLike) -> None:
    """InputError (a ValueError) for a clip layer named in ``stage``'s ``clips`` metadata that
    does not resolve, or that has a dqskin record beside it (:func:`_record_of`) and does not
    match it or the plan of its folder (a clip of another bake). Each such layer is read in full."""
    seen: set[str] = set()
    plans: dict[Path, str | None] = {}
    for prim in stage.Traverse(Usd.TraverseInstanceProxies()):
        clips = Usd.ClipsAPI(prim)
        for clip_set in clips.GetClips() or {}:
            for asset in clips.ComputeClipAssetPaths(clip_set) or []:  # (templates expanded)
                where = asset.resolvedPath or asset.path
                if where in seen:
                    continue
                seen.add(where)
                if not asset.resolvedPath:
                    raise InputError(f"{src}: clip layer {asset.path} of {prim.GetPath()} is "
                                     "missing (for a dqskin clip bake, baking again with ",
                                     Param("resume", True), " redoes it)")
                path = Path(where)  # (a layer inside a package or elsewhere: no record)
                record = _record_of(path) if path.is_file() else None
                if record is None:
                    continue
                if path.parent not in plans:
                    plans[path.parent] = _recorded_in(path.parent, "key")
                plan = plans[path.parent] or record["plan"]
                if not verify_chunk(path, plan, record):
                    raise InputError(f"{path}: does not match its record {path.stem}.json "
                                     "(damaged, incomplete or of another bake; baking again "
                                     "with ", Param("resume", True), " redoes it)")
