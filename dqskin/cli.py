"""The ``dqskin`` command line: ``skin``, ``info``, ``compare``, ``flatten`` and ``demo``.

All argument parsing lives here; each command calls the library (:func:`dqskin.baking.bake`,
:func:`dqskin.report.compare.run_compare`). The process's promises, one place each:

* Exit status: 0 done; 2 bad input, a refused output or a limit
  (:class:`dqskin.errors.DqskinError`: one line ``dqskin: error: ...`` naming the file, prim,
  field or flag; no traceback), or a system error about a file (one line ``FILE: reason``:
  permission, no space, no such file); 70 for anything else, a bug in dqskin (one line
  ``dqskin: internal error (a bug): ...`` naming the file the traceback was written to); 130 on
  SIGINT (Ctrl-C) and 143 on SIGTERM (one line ``dqskin: interrupted``); 120 when a finished
  command's output could not be written (a full disk; one line ``dqskin: error: writing
  <stdout>: ...``); 141 without a message when the reader of stdout goes away (``dqskin info X
  | head``), as a tool ended by SIGPIPE.
* Signals: :func:`main` installs the handlers before anything else it does; the first SIGINT or
  SIGTERM raises :class:`Interrupted` in the main thread, so every ``with`` block unwinds and
  :mod:`dqskin.files.atomic` removes its temporary files (its commit and clean-up steps finish
  first; further signals during clean-up are ignored). An interrupted run leaves no output and no
  temporary file.
* Outputs: atomic, never over an existing file without ``--force`` nor over the input; without
  ``--force`` the name is claimed exclusively (:mod:`dqskin.files.atomic`), so of two runs
  writing the same output the one that finishes second fails.
* Exit: :func:`main`, as the process's entry point, ends the process itself once Python's exit
  handlers have run and the standard streams are flushed, skipping the interpreter's teardown of
  USD's, Warp's and Dask's native libraries (slow, and with nothing left to save).
* Output: only dqskin's own lines. Warp's start-up messages (including its CUDA-driver notice,
  printed by native code), library warnings and log records are silenced unless ``--verbose``;
  progress bars only on a terminal.
* Start-up: only what runs is loaded. This module imports nothing heavy at its top; the parser
  (:func:`build_parser`) reads its choices and defaults from light modules only (``errors``,
  ``options``, ``spaces``, ``times``, ``report.defaults``: no Warp, USD or Dask), so ``--help``
  and usage errors answer without them; each command imports what it needs inside its function.
  Warp is started quietly by :func:`_quiet_warp`: before the command (the default), or, for a
  command whose parser sets ``warp=False``, by the command itself: ``skin``, ``compare`` and
  ``rig`` once their refusals are answered (an existing output without ``--force``, bad option
  values, an output over the input: :func:`_load_input` starts it right before reading the
  input; their libraries' modules are imported after it too), ``info`` right before Warp's
  first use (only when its skinning check must skin), ``flatten`` never.
"""

import argparse
import math
import signal
import sys
from collections.abc import Callable, Sequence
from pathlib import Path
from types import FrameType
from typing import TYPE_CHECKING, Any, NoReturn

from .errors import DqskinError, InputError, Interrupted, Param
from .files.inputs import regular_file
from .terminal import printable

if TYPE_CHECKING:
    from .options import SkinOptions
    from .scene import Scene

# (nothing heavy above: main installs its signal handlers before importing anything else)

__all__ = ["EXIT_INPUT", "EXIT_INTERNAL", "Interrupted", "build_parser", "flag",
           "install_signal_handlers", "main"]

EXIT_INPUT = 2
EXIT_INTERNAL = 70  # os.EX_SOFTWARE: a bug in dqskin
SIGNALS = (signal.SIGINT, signal.SIGTERM)
_signalled: list[int] = []  # the signal numbers received while main runs (only the first one acts)
_own_process = False  # while main runs as the process's entry point (not from Python)


# The flag that sets an API parameter named in an error message (:class:`dqskin.errors.Param`),
# where it is not ``--`` + the name with ``-`` for ``_``; and the ``--no-...`` flag that sets one
# to False. The one place the command line's spelling of parameters lives.
FLAGS = {"overwrite": "--force", "times": "--frames"}
NEGATED = {"normals": "--no-normals", "velocities": "--no-velocities", "clips": "--no-clips"}


def flag(param: Param) -> str:
    """``param`` as typed on the command line: ``--force``, ``--no-clips``, ``--chunk 0``; ``no
    --method`` for None (the flag not given)."""
    import shlex
    name = FLAGS.get(param.name, "--" + param.name.replace("_", "-"))
    if not param.has_value or param.value is True:
        return name
    if param.value is False:
        return NEGATED.get(param.name, f"no {name}")
    if param.value is None:  # (the default: the flag not given)
        return f"no {name}"
    value = param.value
    text = format(value, "g") if isinstance(value, float) else str(value)
    if not text.isprintable():  # a newline or escape: one line, as bash's $'...' reads it
        escaped = text.encode("unicode_escape").decode("ascii").replace("'", "\\'")
        return f"{name} $'{escaped}'"
    return f"{name} {shlex.quote(text)}"


def _on_signal(signum: int, frame: FrameType | None) -> None:
    atomic = sys.modules.get("dqskin.files.atomic")
    if atomic is not None and not (hasattr(atomic, "finished") and hasattr(atomic, "interrupt")):
        atomic = None  # interrupted while it is being imported: nothing of it runs yet
    if _signalled or (atomic is not None and atomic.finished()):
        return  # the first signal interrupts; clean-up then runs to its end (or the output
        # is complete: the run succeeded)
    _signalled.append(signum)
    exc = Interrupted(signum)
    if atomic is not None:
        atomic.interrupt(exc)  # raises now, or when the current commit/clean-up step ends
        return
    raise exc


def install_signal_handlers() -> "dict[signal.Signals, Any] | None":
    """Route SIGINT and SIGTERM to :class:`Interrupted`; returns the previous handlers (None
    outside the main thread, where Python cannot set them)."""
    import threading
    if threading.current_thread() is not threading.main_thread():
        return None
    hook = sys.unraisablehook

    def unraisable(info: "sys.UnraisableHookArgs") -> None:
        # A signal landing in a finalizer (a Warp array's __del__) cannot raise there; the
        # interrupt is recorded and raised again at the next check, so say nothing now.
        if not isinstance(info.exc_value, Interrupted):
            hook(info)

    sys.unraisablehook = unraisable
    return {s: signal.signal(s, _on_signal) for s in SIGNALS}


def _quiet_libraries(verbose: bool, warp: bool = True) -> None:
    """Silence library chatter unless ``verbose``: Python warnings, log records and, with
    ``warp`` (a command that starts Warp: :func:`_quiet_warp`), Warp."""
    import logging
    import warnings
    if not verbose:
        warnings.simplefilter("ignore")
        logging.disable(logging.CRITICAL)
    if warp:
        _quiet_warp(verbose)


def _quiet_warp(verbose: bool) -> None:
    """Import and initialize Warp, silenced unless ``verbose`` (its banner, module-load timings,
    and the CUDA-driver notice its native init prints to fd 2). Every command that may start
    Warp calls it first (:func:`_run_command`, or the command itself where Warp is needed only
    sometimes, as ``info``): Warp's own start would print."""
    import warp as wp
    if not verbose:
        wp.config.log_level = wp.LOG_ERROR
    _init_warp(verbose)


def _init_warp(verbose: bool) -> None:
    """Warp's initialization (:func:`dqskin._warp.init_warp`, once, under its lock); without
    ``verbose`` what its native code writes to stderr is captured and shown only if it fails."""
    from ._warp import init_warp
    if verbose:
        init_warp()
        return
    import os
    import tempfile
    sys.stderr.flush()
    with tempfile.TemporaryFile() as capture:
        saved = os.dup(2)
        try:
            os.dup2(capture.fileno(), 2)
            try:
                init_warp()
            finally:
                os.dup2(saved, 2)
        except Exception:
            capture.seek(0)
            sys.stderr.write(capture.read().decode(errors="replace"))
            raise
        finally:
            os.close(saved)


def default_asset() -> Path:
    """The bundled humanoid rig (package data ``dqskin.assets``, made by tools/make_assets.py)."""
    from importlib.resources import files
    return Path(str(files("dqskin.assets") / "humanoid.usda"))  # (a folder: an installed package)


def _clip(text: str | None) -> str | int | None:
    return int(text) if isinstance(text, str) and text.isdigit() else text


def skin_options(args: argparse.Namespace) -> "SkinOptions":
    """The one :class:`dqskin.SkinOptions` of a command's parsed arguments (those it has:
    ``--method``, ``--sign-reference``, ``--interp``, ``--no-normals``, ``--no-velocities``,
    ``--device``, ``--space``, ``--cor-exact``; a bake's defaults, :meth:`SkinOptions.baking`,
    for the rest)."""
    from .options import CorOptions, SkinOptions
    given = {k: getattr(args, k) for k in ("method", "sign_reference", "interp", "normals",
                                           "velocities", "device", "space")
             if getattr(args, k, None) is not None}
    if getattr(args, "cor_exact", False):
        given["cor"] = CorOptions(cluster=None)
    return SkinOptions.baking(**given)


def cmd_skin(args: argparse.Namespace) -> int:
    import dataclasses

    from .baking import (
        BakeSettings,
        bake,
        check_clip_arguments,
        check_output,
        output_kind,
        workers_early,
    )
    from .times import frame_rate, select
    output_kind(args.out)
    inputs = _inputs(args)
    if "{" not in str(args.out):  # a per-frame pattern is checked frame by frame by bake
        # (an existing output refused here, before Warp and USD load; with --resume the bake
        # decides what an earlier one left)
        check_output(args.out, inputs, force=args.force or args.resume)
    if (args.skeleton is not None or args.weights is not None) and (
            args.workers is not None or args.scheduler or args.resume):
        raise InputError("--skeleton and --weights cannot be combined with --workers, "
                         "--scheduler or --resume: clip workers and the resume check read INPUT "
                         "from its file, without the new weights; write the rig first (dqskin "
                         "rig ... --out rig.usda) and bake that")
    options = skin_options(args)
    settings = BakeSettings(chunk=args.chunk, force=args.force, progress=True, clips=args.clips,
                            workers=args.workers, scheduler=args.scheduler, resume=args.resume,
                            inputs=tuple(inputs), prims=args.prims)
    check_clip_arguments(args.out, settings, options)  # before loading INPUT
    _checkpoint()
    with workers_early(settings):  # --workers: their start-up overlaps the load
        scene = _load_input(args, cache_out=args.out)
        if _own_process:  # what is loaded lives to the end: no full collection walks it again
            from .forkserver import freeze_heap
            freeze_heap()
        _checkpoint()
        sel = select(scene.times, scene.time_codes_per_second, args.frames, args.fps,
                     args.substeps, max_frames=args.max_frames, rate=frame_rate(scene),
                     hold=args.hold)
        settings = dataclasses.replace(settings, fps=sel.rate)
        said = bake(scene, args.out, sel.times, options=options, settings=settings)
    print("\n".join(printable(line) for line in said.splitlines()))
    return 0


def cmd_flatten(args: argparse.Namespace) -> int:
    from .writers.usd_clips import flatten
    src = regular_file(args.input)
    print(printable(f"wrote {flatten(src, args.out, overwrite=args.force)}"))
    return 0


def _rigging(args: argparse.Namespace) -> bool:
    """Whether ``--skeleton``, ``--weights`` or ``--scale`` were given."""
    return any(getattr(args, k, None) is not None
               for k in ("skeleton", "weights", "scale", "joints"))


def _inputs(args: argparse.Namespace) -> list[str]:
    """The files ``skin``/``compare``/``rig`` read: INPUT, ``--skeleton``, ``--weights FILE``
    (no output may replace one of them)."""
    weights = getattr(args, "weights", None)
    return [args.input] + [f for f in (getattr(args, "skeleton", None), weights,
                                       getattr(args, "joints", None))
                           if f is not None and f != "auto"]


def _load_input(args: argparse.Namespace, cache_out: str | None = None) -> "Scene":
    """The scene of ``skin``/``compare``/``rig``: the character file, or with ``--skeleton`` a
    plain mesh bound to a BVH (:func:`dqskin.rigging.rig_mesh`); ``--weights`` replaces the
    influences (:func:`dqskin.rigging.replace_weights`). ``cache_out``: the output ``skin``
    will write (named when a BVH alone has no mesh to skin)."""
    import warnings

    from . import readers
    if args.max_influences < 1:
        raise InputError(f"--max-influences {args.max_influences}: must be at least 1")
    if args.scale is not None and not (math.isfinite(args.scale) and args.scale > 0):
        raise InputError(f"--scale {args.scale:g}: must be a positive number")
    weights = args.weights
    if weights is not None and weights != "auto":
        weights = regular_file(weights)
    src = regular_file(args.input)
    if args.skeleton is not None:
        if readers.format_of(src) is not None and src.suffix.lower() != ".glb":
            raise InputError(f"{src}: --skeleton binds a plain mesh (.obj/.ply/.stl/.off/.glb) "
                             "to a BVH; a character file has its own skeleton (use --weights "
                             "auto to replace its weights)")
        joints = getattr(args, "joints", None)
        _quiet_warp(args.verbose)  # (every refusal above answered without it)
        from .rigging import FitWarning, rig_mesh
        with warnings.catch_warnings(record=True) as said:
            warnings.simplefilter("always", FitWarning)
            scene = rig_mesh(src, regular_file(args.skeleton), weights=weights or "auto",
                             scale=args.scale, as_is=getattr(args, "as_is", False),
                             joints=None if joints is None else regular_file(joints),
                             max_influences=args.max_influences,
                             max_vertices=args.max_vertices, max_input_gib=args.max_input_gib,
                             device=args.device)
        for w in said:
            if issubclass(w.category, FitWarning):
                print(printable(f"warning: {w.message}"), file=sys.stderr)
        return scene
    if args.scale is not None:
        raise InputError("--scale scales a --skeleton BVH to the mesh; it needs --skeleton")
    if getattr(args, "joints", None) is not None:
        raise InputError("--joints places the joints of a --skeleton BVH; it needs --skeleton")
    _quiet_warp(args.verbose)  # (every refusal above answered without it)
    scene = readers.load(src, clip=_clip(args.clip), max_input_gib=args.max_input_gib)
    if cache_out is not None and not scene.meshes and src.suffix.lower() == ".bvh":
        raise InputError(f"{src}: no mesh to skin (a BVH holds a skeleton and its motion); bind "
                         f"a mesh in its rest pose: dqskin skin MESH --skeleton {src.name} "
                         f"--out {cache_out}")
    if weights is not None:
        from .rigging import replace_weights
        asset = scene
        scene = replace_weights(scene, weights, max_influences=args.max_influences,
                                max_vertices=args.max_vertices,
                                max_input_gib=args.max_input_gib, device=args.device)
        _print_weight_difference(asset, scene, "automatic" if weights == "auto" else weights.name,
                                 args.device)
    return scene


def _print_weight_difference(asset: "Scene", scene: "Scene", label: str, device: str | None,
                             samples: int = 100) -> None:
    """One line per mesh: how far the new weights move the skinned points from the asset's own
    (LBS, at up to ``samples`` of the asset's times)."""
    import numpy as np

    from .rigging import skinned_difference
    t = np.unique(asset.times[np.linspace(0, len(asset.times) - 1,
                                          min(samples, len(asset.times))).round().astype(int)])
    for name, (mean, p95) in skinned_difference(asset, scene, t, device=device).items():
        print(printable(f"{label} weights vs the asset's on {name} (LBS, {len(t)} times): "
                        f"mean {mean:.3f}%, 95th percentile {p95:.3f}% of its height at the "
                        "worst time"))


def cmd_rig(args: argparse.Namespace) -> int:
    """``dqskin rig``: bind (or re-weight) and write a UsdSkel rig."""
    from .baking import check_output
    check_output(args.out, _inputs(args), args.force)
    from .writers.usd_rig import write_rig
    scene = _load_input(args)
    _checkpoint()
    print(printable(write_rig(scene, args.out, force=args.force)))
    return 0


def cmd_info(args: argparse.Namespace) -> int:
    import numpy as np

    from . import readers
    from .times import describe_range, frame_rate
    from .validation import scene_problems
    src = regular_file(args.input)
    if src.suffix.lower() in readers.LOADER_SUFFIXES["usd"]:
        from . import point_cache
        stage = point_cache.open_stage(src)  # (held: the loader below reuses its layers)
        if point_cache.is_point_cache(stage):
            print("\n".join(printable(line) for line in
                            point_cache.info_lines(point_cache.cache_info(stage))))
            return 0
    scene = readers.load(src, clip=_clip(args.clip), max_input_gib=args.max_input_gib)

    def say(line: str) -> None:  # every line holds names from the input: printed safely
        print(printable(line))

    say(f"{scene.path}")
    t = np.asarray(scene.times)
    tcps = scene.time_codes_per_second
    unit = "s" if tcps == 1.0 else f"time codes @ {tcps:g}/s"
    say(f"  time range: {describe_range(t, tcps, frame_rate(scene))}; {len(t)} samples "
        f"({t[0]:g} .. {t[-1]:g} {unit}); up axis {scene.up_axis}, "
        f"{scene.meters_per_unit:g} m/unit")
    if Path(scene.path).suffix.lower() == ".bvh":
        from .readers import bvh
        motion = bvh.read_bvh(scene.path, max_input_gib=args.max_input_gib)
        for line in bvh.summary_lines(motion, flag):
            say(f"  {line}")
    if scene.clips:
        say(f"  clips: {', '.join(scene.clips)} (loaded: {scene.clip})")
    problems = []
    for si, skel in enumerate(scene.skeletons):
        anim = scene.animations[si]
        say(f"  skeleton {si} {skel.name!r}: {skel.joint_count} joints, "
            f"{'animated' if anim is not None else 'rest pose only'}")
        children: dict[int, list[int]] = {j: [] for j in range(-1, skel.joint_count)}
        for j, p in enumerate(skel.parents):
            children[int(p)].append(j)
        stack = [(root, 0) for root in reversed(children[-1])]  # depth first, no recursion
        while stack:
            j, depth = stack.pop()
            say("    " + "  " * depth + skel.joint_names[j].split("/")[-1])
            stack.extend((c, depth + 1) for c in reversed(children[j]))
    for m in scene.meshes:
        w = np.asarray(m.joint_weights, np.float64)
        sums = w.sum(1)
        nnz = (w > 0).sum(1)
        say(f"  mesh {m.name!r}: {len(m.points)} points, {len(m.faces)} triangles, skeleton "
            f"{m.skeleton}, method {m.skinning_method}, "
            f"{m.joint_indices.shape[1]} influence slots")
        say(f"    influences per point: min {nnz.min()}, mean {nnz.mean():.2f}, max {nnz.max()}; "
            f"weight sums: min {sums.min():.4f}, max {sums.max():.4f}")
        if np.any(np.abs(sums - 1) > 1e-3):
            problems.append(f"{m.name}: {(np.abs(sums - 1) > 1e-3).sum()} points with weights not "
                            "summing to 1")
        if np.any(nnz == 0):
            problems.append(f"{m.name}: {(nnz == 0).sum()} points without influences")
    # what skin would refuse; Warp only if the points must be skinned to know
    problems += scene_problems(scene, device=args.device,
                               before_skinning=lambda: _quiet_warp(args.verbose))
    say("  problems: " + ("none" if not problems else ""))
    for p in problems:
        say(f"    - {p}")
    return 0


def cmd_demo(args: argparse.Namespace) -> int:
    from . import readers
    from .baking import bake
    from .report.compare import run_compare
    asset = regular_file(args.asset) if args.asset else default_asset()
    if not Path(asset).is_file():
        raise InputError(f"{asset}: demo asset not found")
    out_dir = Path(args.out)
    out_dir.mkdir(parents=True, exist_ok=True)
    print(f"dqskin demo: skinning {asset.name} with DQS")
    scene = readers.load(asset)
    options = skin_options(args)
    print(bake(scene, out_dir / "humanoid_dqs.usdc", options=options.replace(method="dqs"),
               force=True))
    report = out_dir / "report"
    print(f"dqskin demo: comparing LBS and DQS on {asset.name}")
    metrics = run_compare(scene, report, options=options, force=True)

    def worst(values: list[float | None], pick: Callable[[list[float]], float]) -> str:
        given = [v for v in values if v is not None]
        return f"{pick(given):.3f}" if given else "n/a"

    for name, per in metrics["meshes"].items():
        lbs, dqs = per["lbs"], per["dqs"]
        print(f"  {name}: min section LBS {worst(lbs['min_section_ratio'], min)} / DQS "
              f"{worst(dqs['min_section_ratio'], min)}; max bulge LBS "
              f"{worst(lbs['max_bulge_ratio'], max)} / DQS {worst(dqs['max_bulge_ratio'], max)}")
    print(f"report: {(report / 'report.html').resolve()}")
    return 0


def cmd_compare(args: argparse.Namespace) -> int:
    """``dqskin compare``: :func:`dqskin.report.compare.run_compare`, then a summary."""
    out = Path(args.out).resolve()
    for src in _inputs(args):  # the report replaces its folder whole
        p = Path(src).resolve()
        if p == out or out in p.parents:
            raise InputError(f"--out {args.out}: refusing to write the report over the input "
                             f"{src}")
    from .report.compare import RenderSettings, run_compare, summary_lines
    from .times import frame_rate, select
    scene = _load_input(args)  # (the limits of the command line apply to every input)
    source: "Scene | Path" = scene
    times = None
    if args.frames is not None:  # frames at the asset's frame rate, as for skin
        times = select(scene.times, scene.time_codes_per_second, args.frames,
                       max_frames=args.max_frames, rate=frame_rate(scene)).times
    result = run_compare(
        source, args.out, methods=[m.strip() for m in args.methods.split(",") if m.strip()],
        frames=times,
        options=skin_options(args), render=RenderSettings(
            views=tuple(v.strip() for v in args.views.split(",") if v.strip()),
            width=args.width, supersample=args.supersample, adaptive=not args.full_supersample,
            max_rays=args.max_rays, up_axis=args.up_axis),
        progress=not args.quiet, force=args.force,
        sweeps_dir=None if args.no_sweeps else "default", clip=_clip(args.clip),
        viewer_frames=args.viewer_frames)
    print(printable(f"wrote {Path(args.out) / 'report.html'} ({len(result['frames'])} frames "
                    f"× {len(result['methods'])} methods × {len(result['views'])} views, "
                    f"{result['timing_s']['total']:.1f} s)"))
    print("\n".join(map(printable, summary_lines(result))))
    return 0


def _add_sign_reference(parser: argparse.ArgumentParser) -> None:
    from .options import SIGN_REFERENCES, SkinOptions
    parser.add_argument("--sign-reference", choices=SIGN_REFERENCES,
                        default=SkinOptions.sign_reference,
                        help="DQS sign rule: largest_weight = UsdSkel's (default), running_sum = "
                        "Blender's Preserve Volume")


def _add_compare_arguments(parser: argparse.ArgumentParser) -> None:
    from .options import METHOD_NAMES
    from .report.defaults import MAX_RAYS, VIEWER_FRAMES, VIEWS
    from .times import MAX_FRAMES
    parser.add_argument("input", help="character file (.usd/.usda/.usdc/.usdz, .gltf/.glb, .fbx)")
    parser.add_argument("--out", required=True, help="output folder: report.html, metrics.json, "
                        "frames/*.png")
    parser.add_argument("--methods", default="lbs,dqs",
                        help=f"comma-separated from {', '.join(METHOD_NAMES)} (default: lbs,dqs)")
    parser.add_argument("--frames", help="START:END[:STEP] (END inclusive) or F1,F2,... in "
                        "frames at the asset's frame rate (USD: its time codes; glTF: seconds × "
                        "24; BVH: its frames); default: up to 10 evenly spaced samples")
    parser.add_argument("--views", default=",".join(VIEWS),
                        help=f"comma-separated from {', '.join(VIEWS)} (default: all)")
    parser.add_argument("--width", type=int, default=512, help="image size: about WIDTH² "
                        "pixels, shaped to each view (default: 512)")
    parser.add_argument("--supersample", type=int, default=2, help="anti-aliasing rays per pixel "
                        "along each axis (default: 2)")
    parser.add_argument("--max-rays", type=int, default=MAX_RAYS, help="refuse WIDTH × "
                        f"SUPERSAMPLE above this (default: {MAX_RAYS})")
    parser.add_argument("--max-frames", type=int, default=MAX_FRAMES, help="refuse --frames "
                        f"selecting more frames (default: {MAX_FRAMES})")
    parser.add_argument("--up-axis", choices=["Y", "Z"], help="skeleton-space up axis for the "
                        "cameras (default: the asset's)")
    parser.add_argument("--no-sweeps", action="store_true", help="leave out the twist/bend "
                        "sweeps on the procedural rigs")
    parser.add_argument("--full-supersample", action="store_true", help="cast SUPERSAMPLE² rays "
                        "for every pixel (default: only on edges, one ray elsewhere)")
    parser.add_argument("--viewer-frames", type=int, default=VIEWER_FRAMES, help="frames of the "
                        "animated viewer in report.html, evenly spaced over the clip plus the "
                        f"compared ones; 0: no viewer (default: {VIEWER_FRAMES})")
    parser.add_argument("--clip", help="glTF animation or FBX animation stack: name or index")
    _add_sign_reference(parser)
    parser.add_argument("--device", help="cpu or cuda (default: cuda when present)")
    parser.add_argument("--quiet", action="store_true", help="no progress bar")
    parser.add_argument("--force", action="store_true", help="overwrite an existing report")


def _add_rigging_arguments(parser: argparse.ArgumentParser) -> None:
    from .limits import MAX_RIG_VERTICES
    parser.add_argument("--skeleton", help="a .bvh: INPUT is then a plain mesh "
                        "(.obj/.ply/.stl/.off/.glb, +Y up) in any rest pose, size and place: the "
                        "BVH's skeleton is embedded in it and its motion retargeted (see --as-is)")
    parser.add_argument("--as-is", action="store_true", help="with --skeleton: the mesh is "
                        "modelled in the BVH's rest pose (every channel zero), space and unit: "
                        "bind it to the BVH's own skeleton and motion")
    parser.add_argument("--joints", metavar="FILE.json", help="with --skeleton: joint "
                        "positions in the mesh's space, {name: [x, y, z]}, overriding the "
                        "embedding")
    parser.add_argument("--weights", help="auto: bone-heat automatic weights (the default with "
                        "--skeleton; on a skinned glTF/USD input they replace the artist's), or "
                        "FILE.npz with joint_indices (V, K), joint_weights (V, K) and joint_names "
                        "(J,)")
    parser.add_argument("--scale", type=float, help="multiply the BVH's lengths by this to match "
                        "the mesh's unit (e.g. 0.0254: inches to metres)")
    parser.add_argument("--max-influences", type=int, default=8, help="influences per point of "
                        "automatic weights (default: 8)")
    parser.add_argument("--max-vertices", type=int, default=MAX_RIG_VERTICES, help="refuse "
                        "automatic weights on a mesh of more vertices (default: "
                        f"{MAX_RIG_VERTICES:,})")
    _add_input_limit(parser)


def _add_input_limit(parser: argparse.ArgumentParser) -> None:
    from .limits import MAX_INPUT_GIB
    parser.add_argument("--max-input-gib", type=float, default=MAX_INPUT_GIB, help="refuse an "
                        "input file asking for an array larger than this many GiB before its "
                        f"data is read (default: {MAX_INPUT_GIB:g})")


def build_parser() -> argparse.ArgumentParser:
    from .options import INTERPOLATIONS, METHOD_NAMES, SkinOptions
    from .spaces import SPACES
    from .times import MAX_FRAMES
    common = argparse.ArgumentParser(add_help=False)
    common.add_argument("--verbose", action="store_true", default=argparse.SUPPRESS,
                        help="show library warnings and Warp's messages")
    ap = argparse.ArgumentParser(prog="dqskin", description="Dual-quaternion and linear-blend "
                                 "skinning on NVIDIA Warp")
    ap.set_defaults(warp=True)  # Warp started before the command runs (_quiet_libraries), or
    # (warp=False) by the command itself when it needs it
    ap.add_argument("--verbose", action="store_true",  # (its own action: a subcommand's
                    help="show library warnings and Warp's messages")  # default stays SUPPRESS)
    sub = ap.add_subparsers(dest="command", required=True)
    s = sub.add_parser("skin", help="skin every frame and write a cache", parents=[common])
    s.add_argument("input")
    s.add_argument("--out", required=True, help=".usd/.usda/.usdc cache, .npz, or a per-frame "
                   "pattern like out/frame_{:04d}.obj (.obj/.ply/.glb with normals and UVs, "
                   ".stl/.off geometry only; a name without {} for one frame only)")
    s.add_argument("--method", choices=list(METHOD_NAMES), default=None,
                   help="default: what the asset asks for (LBS for glTF; an FBX skin's own); "
                   "cor = optimized centers of rotation (precomputed per mesh, cached in "
                   "~/.cache/dqskin)")
    s.add_argument("--cor-exact", action="store_true",
                   help="cor: exact centers even on meshes so large that the default clusters "
                   "their weights on a 1/256 grid (slower; see the documentation's Concepts: "
                   "Methods page)")
    _add_sign_reference(s)
    s.add_argument("--space", choices=list(SPACES), default=None,
                   help=".npz and per-frame files: the scene's world space (default: the points "
                   "a USD cache of the same bake shows, in stage units), each mesh's own local "
                   "space, or its skeleton's bind space; a USD cache holds local points under "
                   "the source's prims")
    s.add_argument("--frames", help="START:END[:STEP] (END inclusive) or F1,F2,... in frames "
                   "at the output frame rate (USD: its time codes; glTF: seconds × 24; BVH: "
                   "its frames; see --fps); default: every frame of the animation")
    s.add_argument("--fps", type=float, help="output frame rate: resample the animation at "
                   "this many frames per second (default: the file's own rate, 24 for glTF)")
    s.add_argument("--prims", help="which meshes to skin and write: comma-separated globs on "
                   "prim paths or glTF node names, ! or - to exclude (e.g. '/Root/Body*', "
                   "--prims='!/Root/Curves'); default: all. Meshes a per-frame format cannot "
                   "hold (no faces) are skipped with a line saying so")
    s.add_argument("--hold", action="store_true", help="allow --frames outside the "
                   "animation's range, holding its first and last poses (default: refused)")
    s.add_argument("--substeps", type=int, default=1,
                   help="samples per frame interval (motion-blur sub-frames)")
    s.add_argument("--interp", choices=INTERPOLATIONS, default=SkinOptions.interp,
                   help="joint interpolation between keys: trs = the asset's own (default); "
                   "sclerp, dlb, spline, catmull-rom interpolate dual quaternions")
    s.add_argument("--no-velocities", dest="velocities", action="store_false",
                   help="don't write per-point velocities (units/s) to USD caches")
    s.add_argument("--no-normals", dest="normals", action="store_false",
                   help="don't skin normals into USD caches (they keep their rest values) nor "
                   "write them to .obj/.ply/.glb files")
    s.add_argument("--clip", help="glTF animation or FBX animation stack: name or index")
    s.add_argument("--device", help="cpu or cuda (default: cuda when present)")
    s.add_argument("--chunk", type=int, help="frames per chunk (bounds memory; default 256, "
                   "fewer for a USD cache whose 256 frames exceed 64 MB) or per clip layer with "
                   "--clips (default 128, more for a small mesh: at least 32 MB of samples "
                   "per layer; with workers, shorter for four or more a worker and evened "
                   "out over them; with --resume, the earlier bake's)")
    s.add_argument("--clips", action=argparse.BooleanOptionalAction, default=None,
                   help="USD caches as value clips: OUT plus one layer per clip in OUT's .clips "
                   "folder (default: with --workers, --scheduler or --resume; else one layer)")
    s.add_argument("--workers", type=int, help="bake the clips on a local Dask cluster of "
                   "N worker processes (default: in this process)")
    s.add_argument("--scheduler", help="bake the clips on a running Dask cluster "
                   "(tcp://HOST:PORT; its workers must see INPUT and OUT at the same paths)")
    s.add_argument("--resume", action="store_true", help="complete an interrupted clip bake: "
                   "keep the clip layers that verify, bake the rest")
    s.add_argument("--max-frames", type=int, default=MAX_FRAMES, help="refuse --frames, --fps "
                   f"or --substeps selecting more frames (default: {MAX_FRAMES})")
    s.add_argument("--force", action="store_true", help="overwrite existing outputs")
    _add_rigging_arguments(s)
    s.set_defaults(run=cmd_skin, warp=False)  # (Warp once its refusals are answered)
    i = sub.add_parser("info", help="skeleton tree, meshes, influences, time range, problems; "
                       "for a USD point cache its prims, frames, attributes and bounds",
                       parents=[common])
    i.add_argument("input")
    i.add_argument("--clip")
    i.add_argument("--device", help="cpu or cuda for the skinning check (default: cuda when "
                   "present)")
    _add_input_limit(i)
    i.set_defaults(run=cmd_info, warp=False)  # (Warp only for the skinning check: cmd_info)
    c = sub.add_parser("compare", help="offscreen LBS-vs-DQS report: report.html, metrics.json, "
                       "frames/*.png", parents=[common])
    _add_compare_arguments(c)
    _add_rigging_arguments(c)
    c.set_defaults(run=cmd_compare, warp=False)  # (Warp once its refusals are answered)
    r = sub.add_parser("rig", help="bind a mesh to a BVH skeleton (or re-weight a character) "
                       "and write a UsdSkel rig", parents=[common])
    r.add_argument("input", help="mesh in the BVH's rest pose (with --skeleton), or a character")
    r.add_argument("--out", required=True, help=".usda/.usd/.usdc UsdSkel rig")
    _add_rigging_arguments(r)
    r.add_argument("--clip", help="glTF animation or FBX animation stack: name or index")
    r.add_argument("--device", help="cpu or cuda (default: cuda when present)")
    r.add_argument("--force", action="store_true", help="overwrite an existing output")
    r.set_defaults(run=cmd_rig, warp=False)  # (Warp once its refusal is answered)
    f = sub.add_parser("flatten", help="write a value-clip cache (or any stage) as one layer",
                       parents=[common])
    f.add_argument("input")
    f.add_argument("--out", required=True, help=".usd/.usdc/.usda")
    f.add_argument("--force", action="store_true", help="overwrite an existing output")
    f.set_defaults(run=cmd_flatten, warp=False)
    d = sub.add_parser("demo", help="run the main job on the bundled humanoid", parents=[common])
    d.add_argument("--asset", help="default: the bundled humanoid")
    d.add_argument("--out", default="out/demo")
    d.add_argument("--device")
    d.set_defaults(run=cmd_demo)
    return ap


def main(argv: Sequence[str] | None = None) -> int:
    """Run the command line; returns the exit status (see the module docstring).

    Called without ``argv`` (the process's entry point) it keeps its signal handlers until the
    process exits and, unless ``--verbose``, holds what native code (Warp, USD) writes to stderr,
    adding it to the traceback file if dqskin itself fails (a bug: :data:`EXIT_INTERNAL`); it
    then ends the process when the command returns
    (:func:`_exit`). With ``argv`` (from Python) it restores the previous handlers when it returns
    and leaves stderr alone.
    """
    code = _main(argv)
    if argv is None:
        _exit(code)
    return code


class _GuardedStdout:
    """``sys.stdout`` while :func:`main` runs as the process's entry point: a write that fails
    (a full disk, unbuffered or beyond the buffer) is recorded in ``error`` and the command goes
    on, so that it ends as a finished command whose output could not be written (:func:`_exit`:
    120), not as an error of the command; a reader that went away (``BrokenPipeError``) is
    raised as before. Everything else is the wrapped stream's."""

    def __init__(self, stream: Any) -> None:
        self.stream = stream
        self.error: OSError | None = None

    def _guard(self, call: Callable[[], Any], default: Any) -> Any:
        try:
            return call()
        except BrokenPipeError:
            raise
        except OSError as exc:
            if self.error is None:
                self.error = exc
            return default

    def write(self, text: str) -> int:
        return self._guard(lambda: self.stream.write(text), len(text))

    def flush(self) -> None:
        self._guard(self.stream.flush, None)

    def __getattr__(self, name: str) -> Any:
        return getattr(self.stream, name)


def _exit(code: int) -> NoReturn:
    """End the process with ``code`` once Python's exit handlers have run and the standard
    streams are flushed, without the interpreter's finalization (unloading USD's, Warp's and
    Dask's native libraries is slow): everything dqskin writes is complete and closed by then
    (outputs are renamed into place before a command returns). A
    signal from here on is ignored (the command has finished). Output that cannot be written
    (a full disk) makes a successful command exit 120, as Python's own exit does, with a message
    naming stdout; a reader that went away makes it exit 141 silently (:func:`_reader_gone`)."""
    import atexit
    import contextlib
    import os
    for s in SIGNALS:
        signal.signal(s, signal.SIG_IGN)
    atexit._run_exitfuncs()  # logging, weakref finalizers (temporary folders), ...
    failed, message = False, None
    for stream in (sys.stdout, sys.__stdout__, sys.stderr, sys.__stderr__):
        if stream is None:  # (no console: pythonw)
            continue
        try:
            stream.flush()
        except BrokenPipeError:  # the reader went away: nobody to tell
            if stream not in (sys.stdout, sys.__stdout__):
                failed = True
            elif code == 0:
                code = _reader_gone()
        except OSError as exc:
            failed = True
            message = f"dqskin: error: writing {getattr(stream, 'name', 'output')}: {exc}\n"
        except (AttributeError, ValueError):  # no stream, or a closed one
            pass
    guarded = getattr(sys.stdout, "error", None)  # a write that failed during the command
    if isinstance(guarded, OSError) and not failed:
        failed = True
        message = f"dqskin: error: writing {getattr(sys.stdout, 'name', 'output')}: {guarded}\n"
    if failed and code == 0:
        if message is not None:
            with contextlib.suppress(OSError):
                os.write(2, message.encode(errors="replace"))
        code = 120
    os._exit(code)


def _main(argv: Sequence[str] | None) -> int:
    previous = release = bug = None
    try:
        previous = install_signal_handlers()  # first: Ctrl-C in start-up is an interrupt too
        del _signalled[:]  # (a new run, when called from Python again)
        global _own_process
        _own_process = argv is None
        atomic = sys.modules.get("dqskin.files.atomic")
        if atomic is not None:
            atomic.reset_interrupt()
        if argv is None and "--verbose" not in sys.argv[1:]:
            release = _hold_native_stderr()
        if argv is None and sys.stdout is not None:
            sys.stdout = _GuardedStdout(sys.stdout)
        import logging
        import warnings
        with warnings.catch_warnings():
            disabled = logging.root.manager.disable
            try:
                return _run(argv)
            finally:
                logging.disable(disabled)
    except KeyboardInterrupt as exc:  # Interrupted, or SIGINT outside the main thread
        print("dqskin: interrupted" + _resume_advice(exc, argv), file=sys.stderr)
        return getattr(exc, "exit_code", 128 + signal.SIGINT)
    except Exception as exc:  # not a DqskinError nor a system error about a file: a bug
        bug = exc
    finally:
        native = release() if release is not None else ""
        if previous is not None and argv is not None:
            for s, h in previous.items():
                signal.signal(s, h)
    verbose = "--verbose" in (sys.argv[1:] if argv is None else argv)
    return _report_bug(bug, native, verbose)


def _resume_advice(exc: BaseException, argv: Sequence[str] | None) -> str:
    """For an interrupted clip bake that kept finished clips (the exception's ``resumable``,
    :func:`dqskin.distributed.bake_clips`): how many, and the command that completes it (this
    one with ``--resume`` in place of ``--force``)."""
    resumable = getattr(exc, "resumable", None)
    if not resumable:
        return ""
    import shlex
    kept, total, folder = resumable
    args = [a for a in (sys.argv[1:] if argv is None else argv) if a != "--force"]
    if "--resume" not in args:
        args.append("--resume")
    return (f"; {kept} of {total} clips are kept in {folder}; to complete the bake: "
            f"dqskin {shlex.join(args)}")


def _report_bug(exc, native="", verbose=False):
    """Write ``exc``'s traceback (and what native code wrote to stderr meanwhile, ``native``) to
    a new file in the temporary folder, say in one line that dqskin failed and where the
    traceback is, and return :data:`EXIT_INTERNAL`; with ``verbose`` the traceback is printed
    too. If the file cannot be written the traceback goes to stderr instead."""
    import os
    import tempfile
    import time
    import traceback
    text = "".join(traceback.format_exception(exc))
    report = (f"dqskin {_version()} internal error\ncommand: {sys.argv!r}\n\n{text}"
              + (f"\nnative stderr:\n{native}" if native else ""))
    stamp = time.strftime("%Y%m%d-%H%M%S")
    where = None
    try:
        fd, where = tempfile.mkstemp(prefix=f"dqskin-crash-{stamp}-{os.getpid()}-",
                                     suffix=".txt")  # O_EXCL, mode 0600
        with open(fd, "w", encoding="utf-8", errors="backslashreplace") as f:
            f.write(report)
    except OSError:
        where = None
    if verbose or where is None:
        sys.stderr.write(text)
    what = " ".join(str(exc).split())
    print(f"dqskin: internal error (a bug): {type(exc).__name__}"
          + (f": {what}" if what else "")
          + (f"; traceback written to {where}" if where else ""), file=sys.stderr)
    return EXIT_INTERNAL


def _version() -> str:
    from importlib.metadata import PackageNotFoundError, version
    try:
        return version("dqskin")
    except PackageNotFoundError:
        return "(not installed)"


def _checkpoint() -> None:
    """Raise :class:`Interrupted` if a signal came while a library swallowed the exception (USD
    runs Python module loads from C++ and reports their errors as warnings), unless the run's
    output was committed meanwhile (:func:`dqskin.files.atomic.finished`)."""
    atomic = sys.modules.get("dqskin.files.atomic")
    if _signalled and not (atomic is not None and atomic.finished()):
        raise Interrupted(_signalled[0])


def _hold_native_stderr() -> Callable[[], str] | None:
    """Point file descriptor 2 at a temporary file, ``sys.stderr`` staying on the real stderr;
    returns ``release()``, which restores it and returns what was written there (None when
    stderr cannot be redirected)."""
    import os
    import tempfile
    try:
        sys.stderr.flush()
        capture = tempfile.TemporaryFile()
        saved = os.dup(2)
    except (AttributeError, OSError, ValueError):
        return None
    stream = open(os.dup(saved), "w", buffering=1, errors="backslashreplace",
                  encoding=getattr(sys.stderr, "encoding", None) or "utf-8")
    os.dup2(capture.fileno(), 2)
    previous, sys.stderr = sys.stderr, stream

    def release() -> str:
        import contextlib
        with contextlib.suppress(OSError, ValueError):
            stream.flush()
        os.dup2(saved, 2)
        os.close(saved)
        sys.stderr = previous
        stream.close()
        capture.seek(0)
        text = capture.read().decode(errors="replace")
        capture.close()
        return text
    return release


def _run(argv: Sequence[str] | None) -> int:
    try:
        return _run_command(argv)
    finally:
        if "dqskin.forkserver" in sys.modules:  # one a --workers bake started: no process
            from .forkserver import stop_workers  # outlives the run
            stop_workers()


def _stdout_reader_gone() -> bool:
    """Whether stdout is a pipe whose reading end is closed (``poll`` reports an error on it):
    a broken pipe elsewhere (a socket, a child process) is an error like any other."""
    import os
    import select
    import stat
    try:
        fd = sys.stdout.fileno()
        if not stat.S_ISFIFO(os.fstat(fd).st_mode):
            return False
        poller = select.poll()
        poller.register(fd, select.POLLOUT)
        return any(ev & select.POLLERR for _, ev in poller.poll(0))
    except (AttributeError, OSError, ValueError):
        return False


def _reader_gone(redirect: bool = True) -> int:
    """The reader of stdout went away (``dqskin info X | head``): no message, the status of a
    process ended by SIGPIPE, as ``cat`` and ``grep`` end; with ``redirect`` (the process's own
    run, not a call from Python) stdout's descriptor is pointed at the null device, so what is
    still buffered goes nowhere."""
    import os
    if redirect:
        try:
            null = os.open(os.devnull, os.O_WRONLY)
            os.dup2(null, sys.stdout.fileno())
            os.close(null)
        except (AttributeError, OSError, ValueError):
            pass
    return 128 + signal.SIGPIPE


def _run_command(argv: Sequence[str] | None) -> int:
    try:
        args = build_parser().parse_args(argv)  # imports NumPy: an interrupt may land in there
        _quiet_libraries(args.verbose, warp=args.warp)
        _checkpoint()
        code = args.run(args)
    except (DqskinError, OSError) as exc:
        _checkpoint()  # an error caused by an interrupt some library turned into another type
        if isinstance(exc, BrokenPipeError) and _stdout_reader_gone():
            return _reader_gone(redirect=argv is None)
        if isinstance(exc, DqskinError):
            msg = exc.message(flag)
        elif exc.strerror:  # the system about a file: "[Errno 13] ...: 'x'" → "x: ..."
            where = " -> ".join(str(f) for f in (exc.filename, exc.filename2) if f is not None)
            msg = f"{where}: {exc.strerror}" if where else exc.strerror
        elif exc.errno is not None:  # a system error reworded to name its file (files.atomic)
            msg = str(exc)
        else:  # an OSError that did not come from the system: a bug
            raise
        print(f"dqskin: error: {printable(msg)}", file=sys.stderr)
        code = EXIT_INPUT
    except Exception:
        _checkpoint()  # e.g. NumPy's ImportError when Ctrl-C lands inside its C-level import
        raise
    _checkpoint()  # nothing was committed after a swallowed interrupt (files.atomic)
    return code


if __name__ == "__main__":
    sys.exit(main())
