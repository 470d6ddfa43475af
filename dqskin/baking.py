"""Bake a skinned animation to files: the library behind ``dqskin skin``.

:func:`bake` skins a scene chunk by chunk (:meth:`dqskin.Scene.skin_chunks`, so memory stays
bounded) with one :class:`dqskin.SkinOptions` and hands each chunk to the writer the output's
suffix selects: a USD point cache
(:mod:`dqskin.writers.usd_cache`) or value clips (:mod:`dqskin.writers.usd_clips`, chunks baked
in parallel by :mod:`dqskin.distributed`), one ``.npz`` (:mod:`dqskin.writers.npz`) or one mesh
file per frame (:mod:`dqskin.writers.mesh_files`). Every output is written atomically
(:mod:`dqskin.files.atomic`) and checked first (:mod:`dqskin.validation`).
"""

import contextlib
import dataclasses
import numbers
import os
import re
from collections.abc import Iterable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any, NamedTuple

import numpy as np
import numpy.typing as npt

from .errors import InputError, LimitError, OutputExistsError, Param, output_exists
from .files.atomic import atomic_path, check_interrupted, check_parent
from .forkserver import MAX_WORKERS_PER_CORE, max_workers
from .options import SkinOptions, is_numpy_bool, split_changes
from .progress import progress_bar
from .readers import format_of
from .scene import Scene
from .validation import check_skinned
from .writers import CACHE_EXTENSIONS, mesh_files, npz

if TYPE_CHECKING:  # (the skinning engine: imported when a bake runs, not before its checks)
    from .pipeline import SkinnedFrames

__all__ = ["OUTPUT_SUFFIXES", "USDA_MAX_BYTES", "BakeSettings", "bake", "check_clip_arguments",
           "check_output", "output_kind", "sample_bytes", "workers_early"]

OUTPUT_SUFFIXES = CACHE_EXTENSIONS + npz.SUFFIXES + mesh_files.SUFFIXES
"""Suffixes :func:`bake` writes (mesh files take a per-frame pattern like ``f_{:04d}.obj``)."""


USDA_MAX_BYTES = 512 << 20
"""Most bytes of samples (:func:`sample_bytes`) a single-layer ``.usda`` cache takes: a text
layer holds every sample in memory until it is saved. Beyond it the bake is refused before
skinning (LimitError): a ``.usdc``/``.usd`` layer streams its samples to its file and takes any
size; value clips (``clips=True``) split them into layers."""

def sample_bytes(scene: Scene, frames: int, normals: bool = True, velocities: bool = True) -> int:
    """Bytes of point, normal and velocity samples a USD cache of ``frames`` frames holds."""
    from .writers import usd_cache
    return usd_cache.frame_bytes(scene, normals, velocities) * int(frames)


def output_kind(out: str | Path) -> str:
    """"usd", "npz" or "frames" for an output path; InputError (a ValueError) for anything
    else."""
    suffix = Path(str(out)).suffix.lower()
    if suffix in CACHE_EXTENSIONS:
        return "usd"
    if suffix in npz.SUFFIXES:
        return "npz"
    if suffix in mesh_files.SUFFIXES:
        return "frames"
    raise InputError(Param("out", out), ": unsupported output type; use "
                     f"{'/'.join(CACHE_EXTENSIONS)}, {'/'.join(npz.SUFFIXES)}, or a "
                     "per-frame pattern like out/frame_{:04d}.obj "
                     f"({' '.join(mesh_files.SUFFIXES)})")


def check_output(out: str | Path, inputs: list, force: bool) -> Path:
    """``out`` as a Path; InputError (a ValueError) if it is one of ``inputs``,
    OutputExistsError (a FileExistsError) if it exists and not ``force``, NotADirectoryError if
    a folder above it is a file."""
    out = Path(out)
    for src in inputs:
        if out.resolve() == Path(src).resolve():
            raise InputError(f"{out}: refusing to overwrite the input")
    check_parent(out)
    if out.exists() and not force:
        raise output_exists(out)
    return out


def _plural(n, word, plural=None):
    return f"{n} {word if n == 1 else plural or word + 's'}"


@dataclass(frozen=True, kw_only=True)
class BakeSettings:
    """How :func:`dqskin.bake` writes, apart from what is skinned (:class:`dqskin.SkinOptions`).

    Attributes
    ----------
    chunk : int or None
        Frames skinned at a time (default :data:`~dqskin.writers.usd_cache.CHUNK_FRAMES`, 256,
        fewer for a USD cache when 256 frames of its samples exceed
        :data:`~dqskin.writers.usd_cache.CHUNK_BYTES`); with clips, frames per clip layer
        (default :func:`dqskin.writers.usd_clips.clip_frames`: 128, more for a mesh whose 128
        frames hold under 32 MB of samples; on a ``scheduler``'s workers, or ``workers``
        started without the two clips first, shorter for four or more a task slot and evened
        out over them, so possibly fewer than 128; with ``resume``, the earlier bake's).
    force : bool
        Overwrite existing outputs (never the input); the last writer wins. In a clip folder
        only the files dqskin made are replaced; another tool's file where the bake writes is
        refused (InputError).
    progress : bool
        A tqdm bar over frames (over clips with clips) on stderr (for three chunks or more, and
        only when stderr is a terminal).
    clips : bool or None
        USD output as value clips (:mod:`dqskin.writers.usd_clips`): a small top-level ``out``
        and one crate layer per clip in ``out``'s ``.clips`` folder. None: clips when
        ``workers``, ``scheduler`` or ``resume`` ask for them, else one layer (a ``.usda`` one
        of at most :data:`USDA_MAX_BYTES` of samples).
    workers : int or None
        Bake the clips on a local Dask cluster of this many worker processes
        (:mod:`dqskin.distributed`), at most :func:`~dqskin.forkserver.max_workers`
        (LimitError). None: in this
        process.
    scheduler : str or None
        ``tcp://HOST:PORT`` of a running Dask scheduler to bake the clips on instead (other
        protocols are refused); its
        workers read ``scene.path`` from the file (in-memory changes to the scene are not seen)
        and write to ``out``'s folder, so both must be at the same paths for them.
    resume : bool
        Keep the clip layers of an earlier, interrupted bake of the same input and settings
        that verify against their checksums; bake the rest.
    inputs : tuple of paths
        Other files the scene was read from (a mesh, a BVH, a weights file): like
        ``scene.path``, no output may replace them.
    fps : float or None
        Output frame rate (:func:`dqskin.times.frame_rate`; default the scene's own): the
        frame numbers of per-frame files are ``times`` in frames at this rate, and a USD cache
        of a scene that is not a USD stage has these frame numbers as time codes and this rate
        as ``timeCodesPerSecond`` and ``framesPerSecond``.
    prims : str or None
        Which meshes are skinned and written (:func:`dqskin.selection.select_meshes`:
        comma-separated globs, ``!`` excluding); None: all. A USD cache deactivates the skinned
        prims left out; value clips hold them all (refused).
    """

    chunk: int | None = None
    force: bool = False
    progress: bool = False
    clips: bool | None = None
    workers: int | None = None
    scheduler: str | None = None
    resume: bool = False
    inputs: tuple = ()
    fps: float | None = None
    prims: str | None = None

    def __post_init__(self) -> None:
        for name in ("chunk", "workers"):
            v = getattr(self, name)
            if v is not None and (isinstance(v, bool) or not isinstance(v, numbers.Integral)):
                raise InputError(Param(name, v), ": expected a whole number or None")
            if v is not None and v < 1:
                raise InputError(Param(name, v), ": must be at least 1")
            object.__setattr__(self, name, None if v is None else int(v))
        for name in ("force", "progress", "resume", "clips"):
            v = getattr(self, name)
            if name == "clips" and v is None:
                continue
            if not isinstance(v, bool) and not is_numpy_bool(v):
                raise InputError(Param(name, v), ": expected True or False"
                                 + (" or None" if name == "clips" else ""))
            object.__setattr__(self, name, bool(v))
        address: object = self.scheduler  # (whatever the caller passed)
        if address is not None and (not isinstance(address, str) or
                                    not _TCP_ADDRESS.fullmatch(address)):
            raise InputError(Param("scheduler", self.scheduler), ": expected tcp://HOST:PORT "
                             "(a Dask scheduler reached over plain TCP)")
        if self.workers is not None and self.workers > max_workers():
            raise LimitError(Param("workers", self.workers), f": more than the limit of "
                             f"{max_workers()} local worker processes ({MAX_WORKERS_PER_CORE} "
                             "per CPU core; each holds the asset); ask for fewer, or raise the "
                             "limit with the environment variable DQSKIN_MAX_WORKERS")
        given: object = self.inputs  # (whatever the caller passed)
        paths = () if isinstance(given, (str, Path)) or not isinstance(given, Iterable) \
            else tuple(given)
        if not paths and given or not all(isinstance(p, (str, os.PathLike)) for p in paths):
            raise InputError(Param("inputs", given), ": expected a sequence of paths")
        object.__setattr__(self, "inputs", paths)
        if self.fps is not None:
            from .times import check_fps
            object.__setattr__(self, "fps", check_fps(self.fps))

    @property
    def distributed(self) -> bool:
        """Whether ``workers``, ``scheduler`` or ``resume`` ask for a clip bake."""
        return self.workers is not None or bool(self.scheduler) or self.resume


_TCP_ADDRESS = re.compile(r"tcp://(\[[0-9A-Fa-f:.]+\]|[^\s/:\[\]@]+):\d{1,5}/?")


def check_clip_arguments(out: str | Path, settings: BakeSettings,
                         options: SkinOptions | None = None) -> None:
    """Raise InputError, naming the parameters, for what :func:`bake` refuses together, before
    anything is loaded (each field alone is checked by :class:`BakeSettings` and
    :class:`~dqskin.options.SkinOptions`): clips or their options (``workers``, ``scheduler``,
    ``resume``) with a non-USD ``out``, those options with ``clips=False``, ``workers`` with
    ``scheduler``, ``resume`` with ``force``, a USD cache in skeleton space (its points sit
    under the source's prims, whose transforms take them to the world: "local" and "world" make
    the same cache), and clips of an ``out`` whose path USD cannot name in clip metadata
    (:func:`~dqskin.writers.usd_clips.check_clip_name`: a backslash, a newline)."""
    workers, scheduler, resume = settings.workers, settings.scheduler, settings.resume
    if options is not None and options.space == "skeleton" and output_kind(out) == "usd":
        raise InputError(Param("space", options.space), ": a USD point cache holds each prim's "
                         "local points, placed in the world by its prims; write .npz or "
                         "per-frame files for skeleton space")
    asked = settings.distributed
    if output_kind(out) != "usd" and (settings.clips or asked):
        raise InputError(Param("out", out), ": value clips, ", Param("workers"), ", ",
                         Param("scheduler"), " and ", Param("resume", True),
                         " are for USD caches (.usd/.usdc/.usda)")
    if resume and settings.force:
        raise InputError(Param("resume", True), " and ", Param("force", True), ": give one (",
                         Param("resume", True), " completes the earlier bake, ",
                         Param("force", True), " starts over)")
    if workers is not None and scheduler:
        raise InputError(Param("workers"), " and ", Param("scheduler"), ": give one (",
                         Param("scheduler"), " bakes on the workers of that cluster; ",
                         Param("workers"), " starts a cluster of its own)")
    if settings.clips is False and asked:
        raise InputError(Param("workers"), ", ", Param("scheduler"), " and ",
                         Param("resume", True), " need value clips (not ", Param("clips", False),
                         ")")
    if settings.clips or asked:
        from .writers.usd_clips import check_clip_name
        check_clip_name(out)


def bake(scene: Scene | str | Path, out: str | Path, times: npt.ArrayLike | None = None, *,
         options: SkinOptions | None = None, settings: BakeSettings | None = None,
         **changes: Any) -> str:
    """Skin ``scene`` at ``times`` and write ``out``.

    Every chunk's joint transforms are checked as they are sampled
    (:meth:`dqskin.Scene.local_transforms`) and every skinned chunk before it is written
    (:func:`dqskin.validation.check_skinned`: no NaN or infinite result in any format); a refusal
    leaves nothing behind, because the output appears only when complete
    (:mod:`dqskin.files.atomic`); without ``force`` its name is claimed exclusively, so of two
    runs writing the same file the one finishing second fails.

    Parameters
    ----------
    scene : dqskin.Scene, str or Path
        A loaded scene, or a file to load (:func:`dqskin.load`).
    out : str or Path
        ``.usd/.usda/.usdc`` (a point cache with points, extent, and normals and velocities as
        asked: of the source stage for a USD input, else of a UsdSkel rig of the scene with
        frame numbers as time codes), ``.npz`` (points and faces), or a per-frame pattern
        ``dir/f_{:04d}.obj`` (``.obj .ply .stl .off .glb``; all meshes in one file; a name
        without ``{}`` only for one frame; ``.obj/.ply/.glb`` also get skinned normals, UVs and
        the base-colour material, see :mod:`dqskin.writers.mesh_files`). Per-frame files are
        committed together. Points are in ``options.space``: world by default (the points a
        USD cache of the same bake shows through its prims' local-to-world).
    times : (F,) float, optional
        Asset times (``scene.times`` unit); default ``scene.times``. Per-frame files are
        numbered, and a USD cache of a non-USD scene timed, in frames at ``settings.fps``.
    options : dqskin.SkinOptions, optional
        What is skinned (default :meth:`SkinOptions.baking`: normals and velocities on, world
        space; they are written into USD caches, normals into ``.obj/.ply/.glb`` files). The
        method and sign rule also skin the rigidly bound prims of a USD cache.
    settings : BakeSettings, optional
        How it is written (chunks, clips, workers, ``force``, ...).
    **changes
        Fields of either replacing those given (``method="dqs"``, ``force=True``, ...).

    Returns
    -------
    str
        A one-line summary of what was written.

    Raises
    ------
    InputError
        Bad input or settings (a ValueError), naming the file or parameter; LimitError beyond a
        limit (``workers``, a ``.usda`` of more than :data:`USDA_MAX_BYTES` of samples).
    OutputExistsError
        ``out`` exists (without ``force``), or another bake of it runs.
    KeyboardInterrupt
        Interrupted; a clip bake that kept finished clips sets the exception's ``resumable`` to
        ``(kept, clips, folder)`` (``resume=True`` completes it).
    """
    skin_changes, bake_changes = split_changes("bake", changes, SkinOptions, BakeSettings)
    opts = SkinOptions.build(SkinOptions.baking() if options is None else options,
                             **skin_changes)
    if not isinstance(settings, BakeSettings | None):
        raise InputError(Param("settings", settings), ": expected a BakeSettings or None")
    settings = dataclasses.replace(BakeSettings() if settings is None else settings,
                                   **bake_changes)
    kind = output_kind(out)
    check_clip_arguments(out, settings, opts)  # before loading
    with workers_early(settings, loading=not isinstance(scene, Scene)):
        if not isinstance(scene, Scene):
            from .readers import load
            scene = load(scene)
        t = scene.times if times is None else np.atleast_1d(np.asarray(times, dtype=np.float64))
        from .selection import select_meshes
        scene, dropped = select_meshes(scene, settings.prims)
        job = _Job(scene, out, t, opts, settings, tuple(dropped))
        return {"usd": _bake_usd, "npz": _bake_npz, "frames": _bake_frames}[kind](job)


HEAD_START_CORES = 3
"""Free cores (:func:`dqskin.distributed.free_cores`) from which :func:`workers_early` starts
the workers' forkserver while the source loads: its imports then take a core of their own,
beside the two that the bake's skinning and writer threads keep busy; on fewer it would slow
every bake that ends in this process (a short shot), so the forkserver starts only once the
first clip says the workers may pay."""


@contextlib.contextmanager
def workers_early(settings: BakeSettings, loading: bool = True) -> Iterator[None]:
    """The block that loads a bake's source (``loading``) and bakes it: with
    ``settings.workers`` (a LocalCluster of the bake's own, no ``scheduler``), the workers'
    forkserver starts importing in the background first
    (:func:`dqskin.forkserver.prestart_workers`), so that the worker start-up overlaps the load;
    the clip bake then uses it or stops it once it has measured whether the workers pay
    (:mod:`dqskin.distributed`). An exception in the block (a load or a check that failed)
    stops it before it is raised. Nothing without ``workers`` or ``loading``, nor where the
    forkserver's imports would slow the bake here (:func:`dqskin.distributed.free_cores`:
    fewer than :data:`HEAD_START_CORES` cores free)."""
    if settings.workers is None or settings.scheduler or not loading:
        yield
        return
    from . import forkserver
    from .distributed import free_cores
    if settings.workers <= 1 or free_cores()[1] < HEAD_START_CORES:  # no head start
        yield
        return
    try:
        try:
            forkserver.prestart_workers()
        except Exception:  # only a head start: the cluster says why it cannot start
            pass
        yield
    except BaseException:  # an interrupt during the start too
        forkserver.stop_workers()
        raise



class _Job(NamedTuple):
    """One :func:`bake`: what it reads, skins and writes."""

    scene: Scene
    out: str | Path
    times: np.ndarray
    options: SkinOptions
    settings: BakeSettings
    dropped: tuple[str, ...] = ()  # meshes left out by settings.prims

    @property
    def sources(self) -> list[str | Path]:
        return [self.scene.path, *self.settings.inputs]

    def counts(self, frames: int | None = None) -> str:
        n = len(self.scene.meshes)
        return (f"{_plural(n, 'mesh', 'meshes')} × "
                f"{_plural(len(self.times) if frames is None else frames, 'frame')}")

    def chunks(self, chunk, options):
        """:meth:`Scene.skin_chunks` of ``chunk`` frames with ``options``, with a progress bar
        over frames (only on a terminal; tqdm is imported only then)."""
        times = self.times
        bar = progress_bar(enabled=self.settings.progress and len(times) > 2 * chunk,
                           total=len(times), unit="frame", desc="skinning")
        try:
            for sl, res in self.scene.skin_chunks(times, chunk, options=options):
                check_interrupted()  # in case a library swallowed it
                yield sl, res
                bar.update(sl.stop - sl.start)
        finally:
            bar.close()


def _bake_usd(job: _Job) -> str:
    """A USD point cache: value clips or one layer; a scene that is not a USD stage through a
    rig of it (:func:`_bake_usd_scene`)."""
    opts = job.options.replace(space="local")  # (the prims above place the points)
    job = job._replace(options=opts)
    scene, out, t, _, s, dropped = job
    method = opts.method or "asset method"
    if _format(scene.path) != "usd":
        frames = _bake_usd_scene(job)
        return (f"wrote {out}: {job.counts(frames)} ({method}"
                f"{', velocities' if opts.velocities else ''})")
    # a USD cache holds each time once (np.unique would import numpy.ma)
    counts = job.counts(int(np.count_nonzero(np.diff(np.sort(t)))) + 1)
    method = opts.method or "asset method"
    clips = s.distributed if s.clips is None else s.clips
    if not clips and Path(out).suffix.lower() == ".usda":
        need = sample_bytes(scene, len(t), opts.normals, opts.velocities)
        if need > USDA_MAX_BYTES:
            raise LimitError(Param("out", out), f": {need / (1 << 20):,.0f} MiB of samples, more "
                             f"than the {USDA_MAX_BYTES >> 20} MiB a .usda layer takes (a text "
                             "layer is held in memory whole); write .usdc or .usd (one layer of "
                             "any size), or value clips with ", Param("clips", True))
    if clips and dropped:
        raise InputError(Param("prims", s.prims), ": value clips hold every skinned prim of "
                         "the source; bake one layer (", Param("clips", False), ") to leave "
                         "prims out")
    if clips:
        from .distributed import bake_clips
        done = bake_clips(scene, out, t, opts, s)
        kept = f", {done['kept']} kept from the earlier run" if done["kept"] else ""
        kept += f"; {done['chose']}" if done.get("chose") else ""  # (one line)
        return (f"wrote {out}: {counts} ({method}{', velocities' if opts.velocities else ''}) "
                f"as {_plural(done['clips'], 'clip')} in {done['folder']}{kept}")
    wrote_velocities = _bake_usd_layer(job)
    return f"wrote {out}: {counts} ({method}{', velocities' if wrote_velocities else ''})"


def _bake_usd_scene(job: _Job) -> int:
    """A single-layer USD point cache of a scene read from any other format (glTF, a mesh bound
    to a BVH, ...): the cache is a UsdSkel rig of the scene (:func:`~.writers.usd_rig.rig_stage`,
    its meshes, topology, UVs and normals), unbound, with the skinned samples of the scene
    itself in world space (the rig's placement groups cleared); time codes are the frame
    numbers at the output rate (:attr:`BakeSettings.fps`). Returns the number of frames
    written."""
    import tempfile

    from pxr import Sdf, UsdGeom

    from .times import frame_rate
    from .writers import usd_cache
    from .writers.usd_rig import rig_stage
    scene, out, t, opts, s, _ = job
    if s.clips or s.distributed:
        raise InputError(Param("out", out), ": value clips (", Param("clips", True), ", ",
                         Param("workers"), ", ", Param("scheduler"), ", ", Param("resume", True),
                         f") are baked from a USD stage and {scene.path} is not one; bake one "
                         "layer, or write it as a UsdSkel rig first "
                         "(dqskin.writers.usd_rig.write_rig) and bake that")
    check_output(out, job.sources, s.force)
    rate = frame_rate(scene, s.fps)
    codes = t * rate / float(scene.time_codes_per_second)
    whole = np.round(codes)
    codes = np.where(np.abs(codes - whole) <= 1e-6, whole, codes)
    if len(np.unique(codes)) != len(codes) or np.any(np.diff(codes) <= 0):
        raise InputError(Param("times"), ": a USD cache needs increasing times")
    stage, paths = rig_stage(scene, t, codes, rate)
    opts = opts.replace(space="world")
    for path in paths.values():  # the points are in the world: nothing above them moves
        for above in Sdf.Path(path).GetParentPath().GetPrefixes():
            prim = stage.GetPrimAtPath(above)
            if prim.IsA(UsdGeom.Xformable):
                UsdGeom.Xformable(prim).ClearXformOpOrder()
    with_normals = {p for p in paths.values()
                    if stage.GetPrimAtPath(p).GetAttribute("normals").HasAuthoredValue()}
    named = dataclasses.replace(
        scene, times=codes, time_codes_per_second=rate, frame_rate=None, _skinners={},
        meshes=[dataclasses.replace(m, name=paths[m.name], normals=m.normals
                                    if paths[m.name] in with_normals else None)
                for m in scene.meshes])

    from .pipeline import SkinnedFrames

    def renamed(res: SkinnedFrames, sl: slice) -> SkinnedFrames:
        check_skinned(scene.path, res)
        return SkinnedFrames(
            codes[sl], {paths[k]: v for k, v in res.points.items()},
            {paths[k]: v for k, v in res.normals.items() if paths[k] in with_normals},
            {paths[k]: v for k, v in res.velocities.items()})

    with tempfile.TemporaryDirectory(prefix="dqskin-rig-") as folder:
        rig = Path(folder) / "rig.usdc"
        stage.GetRootLayer().Export(str(rig))
        with usd_cache.UsdCacheWriter(named, out, opts, source_path=rig,
                                      overwrite=s.force) as writer:
            writer.cache.src = os.fspath(scene.path)  # (what the cache says it was made of)
            writer.write_chunks((renamed(res, sl) for sl, res in
                                 job.chunks(s.chunk or usd_cache.chunk_frames(scene, opts),
                                            opts)), checked=True)
    return len(t)


def _bake_usd_layer(job: _Job) -> bool:
    """A single-layer USD cache (replacing a clip bake of ``out`` with ``force``); whether it
    holds velocities."""
    scene, out, t, opts, s, dropped = job
    src = scene.path
    check_output(out, job.sources, s.force)
    from .writers import usd_cache
    # SHOT.clips/ of a dqskin clip bake beside SHOT.usd: locked, and replaced with force (no
    # folder is made otherwise: the bake writes one file)
    folder = usd_cache.clips_folder(out)
    clips = False
    if folder.is_dir():
        from .writers import clip_lock, usd_clips
        clips = usd_clips.our_plan(folder) is not None
    wrote_velocities = False

    def check(res: "SkinnedFrames") -> None:
        nonlocal wrote_velocities
        check_skinned(src, res)
        wrote_velocities |= bool(res.velocities)

    size = s.chunk or usd_cache.chunk_frames(scene, opts)
    with clip_lock.bake_lock(out) if clips else contextlib.nullcontext():
        replaces = clips and usd_clips.holds_clip_bake(out)
        with usd_cache.UsdCacheWriter(scene, out, opts, overwrite=s.force, final=True,
                                      dropped=dropped, expected_bytes=sample_bytes(
                                          scene, len(t), opts.normals, opts.velocities)) as writer:
            if replaces and not s.force:  # (an unfinished one: out itself does not exist)
                raise OutputExistsError(f"{usd_cache.clips_folder(out)}: holds a clip bake "
                                        f"of {Path(out).name}; complete it with ",
                                        Param("resume", True), ", or replace it with a "
                                        "single layer with ", Param("force", True))
            if replaces:  # its files are removed below
                usd_clips.check_outside(out, usd_clips.input_files(
                    writer.cache.stage, src, s.inputs), src)
            writer.write_chunks((res for _, res in job.chunks(size, opts)), check, checked=True)
        if replaces:
            usd_clips.remove_clip_bake(out)  # nothing reads it now
    return wrote_velocities


def _memory_bytes() -> int:
    """Physical memory of this machine in bytes (1 TiB when it cannot be told)."""
    try:
        return os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")
    except (AttributeError, OSError, ValueError):
        return 1 << 40


def _bake_npz(job: _Job) -> str:
    """One ``.npz`` of every mesh's points (held in memory: refused beyond half of it), with
    the frame numbers, rate, space, up axis and unit (:func:`dqskin.writers.npz.save_npz`)."""
    scene, out, t, opts, s, _ = job
    check_output(out, job.sources, s.force)
    from .writers.usd_cache import CHUNK_FRAMES
    names = [m.name for m in scene.meshes]
    need = 12 * len(t) * sum(len(m.points) for m in scene.meshes)
    if need > _memory_bytes() // 2:
        raise LimitError(Param("out", out), f": {len(t):,} frames of "
                         f"{sum(len(m.points) for m in scene.meshes):,} points need "
                         f"{need / 2**30:.1f} GiB in memory, more than half of this machine's; "
                         "write a USD cache or per-frame files, or select fewer frames")
    from .times import frame_rate
    rate = frame_rate(scene, s.fps)
    with atomic_path(out, overwrite=s.force, final=True) as tmp:  # claimed for the whole run
        pts = {m.name: np.empty((len(t), len(m.points), 3), np.float32) for m in scene.meshes}
        for sl, res in job.chunks(s.chunk or CHUNK_FRAMES,
                                  opts.replace(normals=False, velocities=False)):
            check_skinned(scene.path, res)
            for name in names:
                pts[name][sl] = res.points[name]
        npz.save_npz(tmp, t, names, [pts[n] for n in names], [m.faces for m in scene.meshes],
                     info=dict(frames=t * rate / float(scene.time_codes_per_second), fps=rate,
                               space=opts.space, up_axis=scene.up_axis,
                               meters_per_unit=float(scene.meters_per_unit)))
    return f"wrote {out}: {job.counts()}"


def _to_gltf(scene: Scene) -> np.ndarray | None:
    """(4, 4) scene units and up axis → glTF's metres and +Y up (None: the identity)."""
    m = np.eye(4) * float(scene.meters_per_unit)
    m[3, 3] = 1.0
    if scene.up_axis == "Z":  # (x, y, z) → (x, z, -y)
        m = m @ np.array([[1, 0, 0, 0], [0, 0, 1, 0], [0, -1, 0, 0], [0, 0, 0, 1]], float)
    return None if np.array_equal(m, np.eye(4)) else m


def _bake_frames(job: _Job) -> str:
    """One mesh file per frame (all meshes in each), committed together."""
    scene, out, t, opts, s, _ = job
    src = scene.path
    from .readers.materials import base_colors
    from .times import frame_numbers, frame_rate
    from .writers.usd_cache import CHUNK_FRAMES
    numbers = frame_numbers(t, scene.time_codes_per_second, frame_rate(scene, s.fps))
    paths = mesh_files.frame_paths(str(out), numbers)
    for p in paths:
        check_output(p, job.sources, s.force)
    gltf_input = _format(src) == "gltf"
    suffix = Path(str(out)).suffix.lower()
    layout = mesh_files.MeshLayout(
        scene.meshes, suffix, normals=opts.normals,
        uv_top_left=gltf_input, uv_interpolation=_uv_interpolation(src))
    if len(layout.meshes) < len(scene.meshes):  # skin only what the files hold
        job = job._replace(scene=dataclasses.replace(scene, meshes=layout.meshes))
    colors = base_colors(scene) if suffix in (".obj", ".glb") and layout.uvs is not None else {}
    groups = [(v, f, colors.get(m.name), m.name)
              for m, (v, f) in zip(layout.meshes, layout.ranges)]
    comment = (f"dqskin: {opts.space} space, +{scene.up_axis} up, "
               f"{float(scene.meters_per_unit):g} m per unit")
    with mesh_files.FrameWriter(str(out), layout.faces, layout.uvs, overwrite=s.force,
                                groups=groups, to_gltf=_to_gltf(scene),
                                comment=comment) as writer:
        for sl, res in job.chunks(s.chunk or CHUNK_FRAMES,
                                  opts.replace(normals=layout.normals, velocities=False)):
            check_skinned(src, res)
            points, nrm = layout.frames(res.points, res.normals)
            writer.write(numbers[sl], points, nrm)
    extras = [w for w, on in (("normals", layout.normals), ("UVs", layout.uvs is not None),
                              ("materials", any(colors.values()))) if on]
    mtl = writer.material_path()
    span = f"{paths[0]}" if len(paths) == 1 else f"{paths[0]} … {paths[-1]}"
    return "\n".join(layout.skipped + [
        f"wrote {_plural(len(paths), 'file')} {span}: {job.counts()}"
        + (f" ({', '.join(extras)})" if extras else "")
        + (f"; materials in {mtl}" if mtl is not None else "")])


def _uv_interpolation(path):
    """How the UVs of the input's meshes map to them, where their counts leave it ambiguous: a
    USD stage's ``primvars:st`` interpolation; FBX UVs are per face corner."""
    fmt = _format(path)
    if fmt == "fbx":
        return lambda name: "faceVarying"
    return _usd_uv_interpolation(path) if fmt == "usd" else None


def _format(path: str | Path) -> str | None:
    """The name of the reader module of ``path`` ("usd", "gltf", "fbx") or None: only that
    reader is imported."""
    fmt = format_of(path)
    return None if fmt is None else fmt.__name__.rpartition(".")[2]


def _usd_uv_interpolation(path):
    """``mesh name → interpolation of its primvars:st`` from the USD stage at ``path``, opened
    on first use (only asked when UV counts leave the mapping ambiguous)."""
    stage: list[Any] = []

    def lookup(name: str) -> str | None:
        from pxr import Usd, UsdGeom
        if not stage:
            stage.append(Usd.Stage.Open(str(path)))
        prim = stage[0].GetPrimAtPath(name) if stage[0] else None
        pv = UsdGeom.PrimvarsAPI(prim).GetPrimvar("st") if prim else None
        return str(pv.GetInterpolation()) if pv else None
    return lookup

