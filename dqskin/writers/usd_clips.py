"""USD value clips: a long bake as one crate layer per clip of frames, read as one animation.

For ``--out SHOT.usd`` (any of ``.usd/.usdc/.usda``) a clip bake writes::

    SHOT.usd                     top level: the source flattened and unbound, as the single-layer
                                 cache (:class:`~.usd_cache.CacheLayer`), without the samples;
                                 ``clips`` metadata on each root prim above a skinned prim; the
                                 size and checksum of every file below (:data:`LISTING`)
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
one layer for tools that do not read clips, once every file the top level lists verifies.
A bake holds the folder exclusively, a flatten shared (:mod:`.clip_lock`); ``force``
replaces only the files dqskin made there (:func:`made_by_dqskin`).
"""

import contextlib
import dataclasses
import errno
import hashlib
import json
import os
import re
import shutil
from collections.abc import Callable, Iterable
from pathlib import Path
from types import TracebackType
from typing import IO, Any, Literal

import numpy as np
import numpy.typing as npt
import xxhash
from pxr import Sdf, Tf, Usd, Vt

from ..errors import InputError, OutputExistsError, Param, output_exists
from ..files.atomic import atomic_path, check_interrupted, named_error
from ..files.crate import BOOTSTRAP, CrateSamples, Hasher
from ..files.inputs import open_input, regular_file
from ..options import CorOptions, SkinOptions
from ..readers.usd import _tf_message
from ..readers.usd_layers import open_stage
from ..scene import Scene
from .clip_lock import reading_lock
from .usd_cache import (
    CLIPS_FOLDER_SUFFIX,
    CacheLayer,
    _source_files,
    clips_folder,
    export_layer,
    frame_bytes,
    layer_file,
    stage_files,
)

__all__ = ["CHECKSUM", "CLIP_BYTES", "CLIP_CHUNK", "CLIPS_FOLDER_SUFFIX", "LISTING",
           "MAX_JSON_BYTES", "ClipBake", "ClipLayer", "check_clip_name",
           "check_outside", "chunk_bounds", "clip_frames", "clips_folder", "commit_clip",
           "flatten", "file_checksum", "file_states", "holds_clip_bake", "input_files",
           "made_by_dqskin", "our_plan", "read_json", "recorded_chunk",
           "remove_clip_bake", "verify_chunk", "write_clip"]


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


MAX_JSON_BYTES = 16 << 20
"""Largest ``plan.json`` or clip record read (a plan of a million clips is a few hundred KB)."""


def read_json(path: str | os.PathLike) -> Any:
    """The JSON document in ``path``; InputError (a ValueError) naming it when it is not JSON,
    nested too deeply to read, over :data:`MAX_JSON_BYTES`, or not a regular file (never a
    FIFO: :func:`~dqskin.files.inputs.open_input`); OSError when it cannot be read."""
    with open_input(path) as fh:
        data = fh.read(MAX_JSON_BYTES + 1)
    if len(data) > MAX_JSON_BYTES:
        raise InputError(f"{path}: over {MAX_JSON_BYTES >> 20} MB; not a dqskin file")
    try:
        return json.loads(data)
    except RecursionError:
        raise InputError(f"{path}: JSON nested too deeply; not a dqskin file") from None
    except ValueError as exc:
        raise InputError(f"{path}: not JSON ({exc})") from None


def _plan_key(plan: dict[str, Any]) -> str:
    """The key of a plan: SHA-256 of its canonical JSON without ``key``, ``out`` and
    ``manifest`` (the output's name and the manifest's checksum are not part of what is
    baked)."""
    body = {k: v for k, v in plan.items() if k not in ("key", "out", "manifest")}
    return hashlib.sha256(json.dumps(body, sort_keys=True).encode()).hexdigest()


def our_plan(folder: str | os.PathLike) -> dict[str, Any] | None:
    """The plan of the dqskin clip bake in ``folder`` (its ``plan.json``: this format, and a key
    that is the hash of its content), or None: no plan, or another tool's (or an unreadable)
    file."""
    try:
        plan = read_json(Path(folder) / "plan.json")
    except (OSError, ValueError):
        return None
    try:
        if isinstance(plan, dict) and plan.get("format") == _FORMAT and \
                plan.get("key") == _plan_key(plan):
            return plan
    except (TypeError, ValueError):  # (not serializable as it was written: not ours)
        pass
    return None


def _recorded(out: str | os.PathLike, key: str) -> Any:
    """``key`` of the plan of the earlier dqskin bake in ``out``'s clip folder (:func:`our_plan`),
    None without one."""
    return _recorded_in(clips_folder(out), key)


def _recorded_in(folder: str | os.PathLike, key: str) -> Any:
    plan = our_plan(folder)
    return None if plan is None else plan.get(key)


def input_files(stage: Usd.Stage, src: str | os.PathLike,
                inputs: Iterable[str | os.PathLike] = ()) -> list[str]:
    """Every file a bake of ``src`` reads: the layers of its ``stage`` and ``inputs`` (the
    command's other files: ``--weights``, ``--skeleton``)."""
    return [*_source_files(stage, src), *map(str, inputs)]


def file_states(files: Iterable[str | os.PathLike]) -> list[list[Any]]:
    """``[[path, bytes, mtime_ns], ...]`` of ``files`` (absolute, sorted; None for a missing
    one): what a plan records of every file a bake reads, so that ``resume`` refuses to go on
    after any of them changed (a sublayer edited between two runs would give one cache of two
    animations)."""
    states = []
    for f in sorted({str(Path(f).resolve()) for f in files}):
        try:
            st = os.stat(f)
            states.append([f, st.st_size, st.st_mtime_ns])
        except OSError:
            states.append([f, None, None])
    return states


def _foreign(path: Path) -> InputError:
    """The refusal of a file in a clip folder that dqskin did not make, at a name a clip bake
    writes (with ``force`` too: it replaces only what dqskin made)."""
    why = "not made by dqskin (no dqskin record of it)"
    if path.suffix == ".json":
        try:
            read_json(path)
        except InputError as exc:  # (nested too deeply, not JSON: say so)
            why = str(exc).removeprefix(f"{path}: ")
        except OSError:
            pass
    return InputError(f"{path}: {why}, where this clip bake writes; move it out of "
                      f"{path.parent.name}/, or bake to another output")


_UNSAFE_NAME = re.compile(r"[\\\x00-\x1f\x7f]")


def check_clip_name(out: str | os.PathLike) -> None:
    """InputError (a ValueError) when USD could not name the clip layers of ``out`` in its
    metadata: a backslash (read as a folder separator) or a control character (a newline, a tab:
    not allowed in an asset path) in its folder path or name, or a name that is not UTF-8."""
    path = os.path.abspath(os.fspath(out))
    bad = _UNSAFE_NAME.search(path)
    try:
        path.encode("utf-8")
    except UnicodeEncodeError:
        bad = bad or re.search(r"[\udc80-\udcff]", path)
    if bad:
        raise InputError(Param("out", os.fspath(out)), f": {bad.group()!r} in the path; USD "
                         "cannot name value clips there (asset paths hold no backslash and no "
                         "control character); choose another name")


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
    """Whether ``out``'s clip folder holds a dqskin clip bake of ``out`` (:func:`our_plan`, naming
    it)."""
    return _recorded(out, "out") == Path(out).name


def remove_clip_bake(out: str | os.PathLike) -> None:
    """Remove the clip bake of ``out`` that a single layer written there replaced: the files
    dqskin made in its clip folder (:func:`made_by_dqskin`; others stay, the folder too)."""
    _remove_ours(clips_folder(out))


def made_by_dqskin(path: str | os.PathLike, plan: dict[str, Any] | None = None) -> bool:
    """Whether the file ``path`` in a clip folder is one a dqskin clip bake wrote there:
    ``plan.json`` that is a dqskin plan (:func:`our_plan`), ``manifest.usda`` beside one (of
    the checksum it records), a clip layer with its dqskin record (:func:`_record_of`, of its
    size) or such a record. ``plan``: the folder's plan if already read. (Anything else there,
    another tool's ``plan.json`` or ``chunk_00001.usdc`` included, is not dqskin's to remove or
    replace.)"""
    path = Path(path)
    if plan is None:
        plan = our_plan(path.parent)
    try:
        if path.name == "plan.json":
            return plan is not None
        if path.name == "manifest.usda":
            m = None if plan is None else plan.get("manifest")
            return plan is not None and (m is None or _matches(path, m))
        if _CHUNK.match(path.name) and path.suffix == ".usdc":
            record = _record_of(path)
            return record is not None and record.get("bytes") == path.stat().st_size
        if _CHUNK.match(path.name) and path.suffix == ".json":
            return _record_of(path.with_suffix(".usdc")) is not None
    except OSError:
        return False
    return False


_CHUNK = re.compile(r"^chunk_\d+\.(usdc|json)$")


def _matches(path: Path, record: Any) -> bool:
    """Whether ``path`` has the size and checksum of ``record`` (``{"bytes": .., ALGORITHM: ..}``
    with an algorithm of :data:`_HASHES`)."""
    if not isinstance(record, dict):
        return False
    algorithm = next((a for a in _HASHES if isinstance(record.get(a), str)), None)
    try:
        return (algorithm is not None and path.is_file()
                and path.stat().st_size == record.get("bytes")
                and file_checksum(path, algorithm) == record[algorithm])
    except OSError:
        return False


def _remove_ours(folder: Path) -> None:
    """Remove the files dqskin made in ``folder`` (:func:`made_by_dqskin`) and its temporary
    folders (:mod:`.atomic`); the plan last, so an interrupted removal can be done again."""
    plan = our_plan(folder)
    files = sorted((p for p in folder.iterdir() if _OURS.match(p.name) and not _TEMP.match(p.name)
                    and p.is_file() and made_by_dqskin(p, plan)),
                   key=lambda p: p.name == "plan.json")
    _remove_temporaries(folder)
    for p in files:
        with contextlib.suppress(OSError):
            p.unlink()


def _remove_temporaries(folder: Path) -> None:
    """Remove ``folder``'s temporary folders of clip bakes (:mod:`.atomic`)."""
    for p in folder.iterdir():
        if _TEMP.match(p.name) and p.is_dir() and not p.is_symlink():
            shutil.rmtree(p, ignore_errors=True)


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
    (``claim``, an :class:`~.atomic.atomic_path` beside ``path``), written past the page cache
    unless ``direct`` is False (:func:`dqskin.files.direct.pays` decides for a bake).

    :meth:`finish` completes the file, sets :attr:`digest` (its checksum) and returns the claim
    for :func:`commit_clip`;
    :meth:`discard` (or leaving the ``with`` block on an exception) removes it."""

    digest: str | None = None

    def __init__(self, path: str | os.PathLike, time_codes_per_second: float, *,
                 direct: bool = True) -> None:
        self.claim = atomic_path(Path(path), overwrite=True)
        try:
            # hashed as it is written (never read back), so it may go past the page cache
            self._hasher = _HASHES[CHECKSUM]()
            self.samples = CrateSamples(self.claim.open(), time_codes_per_second,
                                        hasher=self._hasher, direct=direct)
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
        if isinstance(exc, OSError):  # (a full disk: naming the layer)
            named = named_error(self.claim.path, exc)
            if named is not exc:
                raise named from None
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
        record = read_json(Path(path).with_suffix(".json"))
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
        check_clip_name(out)
        read = input_files(self.cache.stage, self.cache.src, inputs)
        check_outside(out, read, self.cache.src)
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
                "attributes": sorted(t.attr for t in self.targets.values()),
                "layers": file_states(f for f in read if not _same_path(f, src))}
        manifest = Sdf.Layer.CreateAnonymous(".usda")
        for target in self.targets.values():
            target.spec(manifest)
        self.manifest = manifest.ExportToString().encode()
        self.key = _plan_key(plan)
        # (the name and the manifest's checksum: not in the key)
        self.plan = dict(plan, key=self.key, out=self.out.name, manifest={
            "bytes": len(self.manifest), "xxh3_128": xxhash.xxh3_128_hexdigest(self.manifest)})
        self.resumed = self._check_existing(force, resume)
        self.overwrite = force or self.resumed

    def _check_existing(self, force: bool, resume: bool) -> bool:
        """True when resuming a bake of this plan; clears an earlier bake when ``force``."""
        plan_file = self.folder / "plan.json"
        if self.folder.exists() and not self.folder.is_dir():
            raise NotADirectoryError(errno.ENOTDIR, "exists and is not a folder", str(self.folder))
        if self.folder.is_dir():  # before anything is removed: a bake would fail on it midway
            layers = [self.clip_path(k) for k in range(len(self.bounds))]
            plan = our_plan(self.folder)
            for p in [plan_file, self.folder / "manifest.usda", *layers,
                      *(q.with_suffix(".json") for q in layers)]:
                if p.exists() and not p.is_file():  # (a link to a file is one)
                    raise InputError(f"{p}: not a file, where this clip bake writes one; move it "
                                     f"out of {self.folder.name}/")
                if p.exists() and not made_by_dqskin(p, plan):  # --force never replaces it
                    raise _foreign(p)
        earlier = plan_file.exists()
        self._check_owner(self.out)
        if earlier and resume and not force:
            if _recorded(self.out, "key") != self.key:
                raise InputError(f"{self.folder}: an earlier bake ", *self._differs(),
                                 "; rerun it with those, or use ", Param("force", True),
                                 " to start over")
            return True
        if not force:
            self.check_free(self.out)
            self._claim(plan_file)
        elif self.folder.is_dir():
            if earlier and self.out.is_file():  # it reads the clips about to be replaced: an
                self.out.unlink()  # interrupted --force left it showing a mix of two bakes
            _remove_ours(self.folder)
        return False

    def _differs(self) -> list[str | Param]:
        """What the earlier bake's plan has that this one's does not, in words (the options as
        :class:`Param`: the command line spells them as typed)."""
        try:
            return self._compare_plans(our_plan(self.folder))
        except (TypeError, AttributeError, KeyError, ValueError):  # a plan.json edited by hand
            return ["with other settings"]

    def _compare_plans(self, old: dict[str, Any] | None) -> list[str | Param]:
        if old is None:
            return ["of another format (or with an unreadable plan.json)"]
        new = self.plan
        if old.get("source") != new["source"]:
            return [f"of another input ({old.get('source')})"]
        if (old.get("source_bytes"), old.get("source_mtime_ns")) != \
                (new["source_bytes"], new["source_mtime_ns"]):
            return ["of this input before it changed (its size or modification time)"]
        if old.get("layers") != new["layers"]:
            was = {e[0]: e[1:] for e in old.get("layers") or []}  # path → [bytes, mtime]
            now = {e[0]: e[1:] for e in new["layers"]}
            changed = [p for p, st in now.items() if was.get(p) != st] + sorted(set(was) - set(now))
            return [f"of this input before {changed[0] if changed else 'a layer it reads'} "
                    "changed (its size or modification time)"]
        said: list[list[str | Param]] = []
        if any(old.get(k) != new[k] for k in ("frames", "first", "last", "times_sha256")):
            said.append([f"of {old.get('frames')} frames from {old.get('first'):g} to "
                         f"{old.get('last'):g} (now {new['frames']} from {new['first']:g} to "
                         f"{new['last']:g}: other times selected)"])
        if old.get("chunk") != new["chunk"]:
            said.append(["with ", Param("chunk", old.get("chunk")), " (now ",
                         Param("chunk", new["chunk"]), ")"])
        # (a plan leaves out the settings that are at their defaults)
        opts = {**_PLAN_DEFAULTS, **new["options"]}
        was = {**_PLAN_DEFAULTS, **(old.get("options") or {})}
        for k in sorted(set(opts) | set(was)):
            if opts.get(k) == was.get(k):
                continue
            if all(v is None or isinstance(v, (bool, int, float, str))
                   for v in (opts.get(k), was.get(k))):
                said.append(["with ", Param(k, was.get(k)), " (now ", Param(k, opts.get(k)), ")"])
            else:
                said.append([f"with other {k} settings"])
        if not said and old.get("attributes") != new["attributes"]:
            said.append(["of other attributes"])
        if not said:
            return ["with other settings"]
        return [part for i, parts in enumerate(said) for part in ([", "] if i else []) + parts]

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
            if our_plan(folder) is None:
                raise _foreign(folder / "plan.json")
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

    def _verified(self, index: int) -> bool:
        """Whether clip layer ``index`` of an earlier run of this plan matches its record
        (:func:`verify_chunk`), and the record is of this clip's frames (not a neighbour's
        copied over it)."""
        path = self.clip_path(index)
        record = _record_of(path)
        t = self.chunk_times(index)
        return (record is not None and record.get("frames") == len(t)
                and record.get("first") == float(t[0]) and record.get("last") == float(t[-1])
                and verify_chunk(path, self.key, record))

    def kept(self) -> int:
        """How many clip layers of this plan are in place (each with its record): what a
        ``resume`` would keep, unless one is damaged."""
        return sum(1 for k in range(len(self.bounds))
                   if self.clip_path(k).is_file()
                   and (_record_of(self.clip_path(k)) or {}).get("plan") == self.key)

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
        _remove_temporaries(self.folder)
        todo = [k for k in range(len(self.bounds)) if not (self.resumed and self._verified(k))]
        check_interrupted()
        _write_json(self.folder / "plan.json", self.plan)
        with atomic_path(self.folder / "manifest.usda") as tmp:
            tmp.write_bytes(self.manifest)
        return todo

    def finish(self) -> Path:
        """Check every chunk is in place, then write the top level (atomically), recording the
        size and checksum of every clip layer and of the manifest in its ``customLayerData``
        (:data:`LISTING`: what :func:`flatten` verifies). Returns it."""
        listed = {}
        for k in range(len(self.bounds)):  # in place, of this plan (not a late write of a
            record = _record_of(self.clip_path(k))  # stopped bake's remote worker)
            if not self.clip_path(k).is_file():
                raise InputError(f"{self.clip_path(k)}: missing (not written)")
            if record is None or record["plan"] != self.key:
                raise InputError(f"{self.clip_path(k)}: its record is missing or of another "
                                 "bake; rerun with ", Param("resume", True), " to redo it")
            algorithm = next(a for a in _HASHES if a in record)
            listed[self.clip_path(k).name] = {"bytes": record["bytes"],
                                              algorithm: record[algorithm]}
        layer, t = self.cache.layer, self.times
        data = dict(layer.customLayerData)
        data[LISTING] = {"format": _FORMAT, "plan": self.key, "folder": self.folder.name,
                         "manifest": self.plan["manifest"], "layers": listed}
        layer.customLayerData = data
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
        claim.commit(final=True)
        _remove_temporaries(self.folder)
        return self.out


LISTING = "dqskinClips"
"""The key of a clip cache's top-level ``customLayerData`` that lists what it reads: ``format``,
``plan`` (its key), ``folder`` (the clip folder's name, beside the top level), ``manifest`` and
``layers`` (clip layer name → its record): ``{"bytes": size, ALGORITHM: checksum}``
(:data:`CHECKSUM`, or an older algorithm of a layer kept from an earlier bake)."""


def flatten(src: str | os.PathLike, out: str | os.PathLike, *, overwrite: bool = False) -> Path:
    """Write the composed stage ``src`` (a clip cache, or any stage) as one layer ``out``: every
    clip's samples become ordinary time samples, for tools that do not read value clips. The
    whole animation is held in memory while writing.

    Every clip layer the stage's ``clips`` metadata names must resolve. A dqskin clip cache
    lists the size and checksum of each of its clip layers and of its manifest (:data:`LISTING`):
    each must be in place and match (a missing, damaged, swapped or emptied file, or one of
    another bake, is refused; USD would skip a missing clip and hold the samples around it,
    copy a damaged one, and read no animation through a wrong manifest). Clips of a cache
    without that list that have a dqskin record beside them (``chunk_00000.json``) must match it
    (:func:`verify_chunk`) and its folder's plan; in a folder of a dqskin plan, every clip must
    have one. Any failure is an InputError (a ValueError) naming the file (``resume`` redoes a
    clip). That check reads each such layer once more. While it reads, ``src``'s clip folder
    is held (:func:`~.clip_lock.reading_lock`): a bake of ``src`` running is refused, and none
    starts.
    ``.usd`` output is crate. ``out`` appears only when complete (exclusively unless
    ``overwrite``); ``src`` is never modified. Returns ``out``.
    """
    out = Path(out)
    if out.suffix.lower() not in (".usd", ".usdc", ".usda"):
        raise InputError(f"{out}: cannot write extension {out.suffix!r}; use .usd/.usdc/.usda")
    regular_file(src)
    if out.exists() and not overwrite:  # (checked again when it is claimed)
        raise output_exists(out, "overwrite")
    folder = clips_folder(src)
    with reading_lock(folder, src) if folder.is_dir() else contextlib.nullcontext():
        return _flatten(src, out, overwrite)


def _flatten(src: str | os.PathLike, out: Path, overwrite: bool) -> Path:
    """:func:`flatten` once ``src``'s clip folder is held."""
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
    for real in stage_files(stage):
        if out.exists() and os.path.exists(real) and os.path.samefile(real, out):
            raise InputError(f"{out}: refusing to overwrite an input of {src}")
    if LISTING in flat.customLayerData:  # (its clips are in the samples now)
        flat.customLayerData = {k: v for k, v in flat.customLayerData.items() if k != LISTING}
    claim = atomic_path(out, overwrite=overwrite)
    try:
        export_layer(flat, claim)
    except BaseException:
        claim.discard()
        raise
    claim.commit(final=True)
    return out


def _check_clips(stage: Usd.Stage, src: str | os.PathLike) -> None:
    """InputError (a ValueError) for a clip layer named in ``stage``'s ``clips`` metadata that
    does not resolve, or that has a dqskin record beside it (:func:`_record_of`) and does not
    match it or the plan of its folder (a clip of another bake). Each such layer is read in full."""
    listed = _check_listing(stage, src)
    seen: set[str] = set()
    plans: dict[Path, dict[str, Any] | None] = {}
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
                if listed is not None:
                    manifest = clips.GetClipManifestAssetPath(clip_set)
                    if manifest is None or not manifest.resolvedPath or Path(os.path.realpath(
                            manifest.resolvedPath)) != listed[0] / "manifest.usda":
                        raise InputError(f"{src}: the clips of {prim.GetPath()} name another "
                                         f"manifest than {listed[0] / 'manifest.usda'} "
                                         f"({manifest.path if manifest else 'none'})")
                    path = Path(os.path.realpath(where))
                    if path.parent != listed[0] or path.name not in listed[1]:
                        raise InputError(f"{src}: clip layer {asset.path} of {prim.GetPath()} "
                                         f"is not one of the clips its list ({LISTING}) names")
                    continue  # (verified)
                if path.parent not in plans:
                    plans[path.parent] = our_plan(path.parent)
                    _check_manifest(path.parent, plans[path.parent])
                record = _record_of(path) if path.is_file() else None
                if record is None:
                    if plans[path.parent] is not None:
                        raise InputError(f"{path}: its dqskin record {path.stem}.json is missing "
                                         "or unreadable (baking again with ",
                                         Param("resume", True), " redoes it)")
                    continue
                plan = (plans[path.parent] or {}).get("key") or record["plan"]
                if not verify_chunk(path, plan, record):
                    raise InputError(f"{path}: does not match its record {path.stem}.json "
                                     "(damaged, incomplete or of another bake; baking again "
                                     "with ", Param("resume", True), " redoes it)")


def _check_listing(stage: Usd.Stage, src: str | os.PathLike) -> tuple[Path, set[str]] | None:
    """Verify the files a dqskin clip cache lists (:data:`LISTING`): its manifest and every
    clip layer in place, of the recorded size and checksum (each read in full); InputError (a
    ValueError) naming the first that is not. Returns the clip folder and the names of its
    layers, or None for a stage without that list."""
    root = stage.GetRootLayer()
    data = root.customLayerData.get(LISTING)
    if data is None:
        return None
    where = layer_file(root)
    try:
        if not where or not isinstance(data, dict) or data.get("format") != _FORMAT:
            raise TypeError
        folder = Path(os.path.realpath(Path(where).parent / str(data["folder"])))
        layers = dict(data["layers"])
        manifest = data["manifest"]
    except (TypeError, KeyError, ValueError):
        raise InputError(f"{src}: its list of clip files ({LISTING}) is damaged; bake it "
                         "again") from None
    if not _matches(folder / "manifest.usda", manifest):
        raise InputError(f"{folder / 'manifest.usda'}: missing, damaged or not the manifest "
                         f"{Path(src).name} was written with (its size and checksum differ "
                         "from its list); bake it again (", Param("resume", True),
                         " keeps the clips that verify)")
    for name in sorted(layers):
        path = folder / name
        if not _matches(path, layers[name]):
            raise InputError(f"{path}: missing, damaged or not the clip layer "
                             f"{Path(src).name} was written with (its size and checksum "
                             "differ from its list); baking again with ",
                             Param("resume", True), " redoes it")
    return folder, set(layers)


def _check_manifest(folder: Path, plan: dict[str, Any] | None) -> None:
    """InputError (a ValueError) when the folder of a dqskin plan that records its manifest's
    checksum has no such manifest."""
    if plan is not None and plan.get("manifest") is not None and \
            not _matches(folder / "manifest.usda", plan["manifest"]):
        raise InputError(f"{folder / 'manifest.usda'}: missing, damaged or not the manifest of "
                         f"the bake in {folder.name}/ (its size and checksum differ from "
                         "plan.json); bake it again")
