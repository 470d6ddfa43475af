"""The ``dqskin`` command line: ``skin``, ``info``, ``compare`` and ``demo``.

All argument parsing lives here; each command calls the library (:func:`dqskin.baking.bake`,
:func:`dqskin.report.compare.run_compare`). Errors in the input print one line naming the file,
prim or field and exit with status 2; no traceback. Existing outputs are never overwritten without
``--force``; outputs are atomic.
"""

import argparse
import sys
from importlib.resources import files
from pathlib import Path

import numpy as np

from .animation import INTERPOLATIONS
from .skinning import METHODS

__all__ = ["build_parser", "main"]

EXIT_INPUT = 2


def default_asset():
    """The bundled humanoid rig (package data ``dqskin.assets``, made by tools/make_assets.py)."""
    return files("dqskin.assets") / "humanoid.usda"


def _clip(text):
    return int(text) if isinstance(text, str) and text.isdigit() else text


def cmd_skin(args):
    from . import formats
    from .baking import bake, output_kind
    from .times import select_times
    output_kind(args.out)
    scene = formats.load(args.input, clip=_clip(args.clip))
    times = select_times(scene.times, scene.time_codes_per_second, args.frames, args.fps,
                         args.substeps)
    print(bake(scene, args.out, times, method=args.method, interp=args.interp,
               device=args.device, chunk=args.chunk, normals=args.normals,
               velocities=args.velocities, force=args.force, progress=True))
    return 0


def cmd_info(args):
    from . import formats
    scene = formats.load(args.input, clip=_clip(args.clip))
    print(f"{scene.path}")
    t = np.asarray(scene.times)
    tcps = scene.time_codes_per_second
    unit = "s" if tcps == 1.0 else f"time codes @ {tcps:g}/s"
    print(f"  time range: {t[0]:g} .. {t[-1]:g} ({len(t)} samples, {unit}); "
          f"up axis {scene.up_axis}, "
          f"{scene.meters_per_unit:g} m/unit")
    if scene.clips:
        print(f"  clips: {', '.join(scene.clips)} (loaded: {scene.clip})")
    problems = []
    for si, skel in enumerate(scene.skeletons):
        anim = scene.animations[si]
        print(f"  skeleton {si} {skel.name!r}: {skel.joint_count} joints, "
              f"{'animated' if anim is not None else 'rest pose only'}")
        children = {j: [] for j in range(-1, skel.joint_count)}
        for j, p in enumerate(skel.parents):
            children[int(p)].append(j)

        def tree(j, depth):
            print("    " + "  " * depth + skel.joint_names[j].split("/")[-1])
            for c in children[j]:
                tree(c, depth + 1)
        for root in children[-1]:
            tree(root, 0)
    for m in scene.meshes:
        w = np.asarray(m.joint_weights, np.float64)
        sums = w.sum(1)
        nnz = (w > 0).sum(1)
        print(f"  mesh {m.name!r}: {len(m.points)} points, {len(m.faces)} triangles, skeleton "
              f"{m.skeleton}, method {m.skinning_method}, "
              f"{m.joint_indices.shape[1]} influence slots")
        print(f"    influences per point: min {nnz.min()}, mean {nnz.mean():.2f}, max {nnz.max()}; "
              f"weight sums: min {sums.min():.4f}, max {sums.max():.4f}")
        if np.any(np.abs(sums - 1) > 1e-3):
            problems.append(f"{m.name}: {(np.abs(sums - 1) > 1e-3).sum()} points with weights not "
                            "summing to 1")
        if np.any(nnz == 0):
            problems.append(f"{m.name}: {(nnz == 0).sum()} points without influences")
    print("  problems: " + ("none" if not problems else ""))
    for p in problems:
        print(f"    - {p}")
    return 0


def cmd_demo(args):
    from . import formats
    from .baking import bake
    from .report.compare import run_compare
    asset = Path(args.asset) if args.asset else default_asset()
    if not asset.is_file():
        raise ValueError(f"{asset}: demo asset not found")
    out_dir = Path(args.out)
    out_dir.mkdir(parents=True, exist_ok=True)
    print(f"dqskin demo: skinning {asset.name} with DQS")
    scene = formats.load(asset)
    print(bake(scene, out_dir / "humanoid_dqs.usdc", method="dqs", device=args.device,
               force=True))
    report = out_dir / "report"
    print(f"dqskin demo: comparing LBS and DQS on {asset.name}")
    metrics = run_compare(scene, report, device=args.device, force=True)

    def worst(values, pick):
        values = [v for v in values if v is not None]
        return f"{pick(values):.3f}" if values else "n/a"

    for name, per in metrics["meshes"].items():
        lbs, dqs = per["lbs"], per["dqs"]
        print(f"  {name}: min section LBS {worst(lbs['min_section_ratio'], min)} / DQS "
              f"{worst(dqs['min_section_ratio'], min)}; max bulge LBS "
              f"{worst(lbs['max_bulge_ratio'], max)} / DQS {worst(dqs['max_bulge_ratio'], max)}")
    print(f"report: {(report / 'report.html').resolve()}")
    return 0


def cmd_compare(args):
    """``dqskin compare``: :func:`dqskin.report.compare.run_compare`, then a summary."""
    from .report.compare import run_compare, summary_lines
    from .times import parse_frames
    result = run_compare(
        args.input, args.out, methods=[m.strip() for m in args.methods.split(",") if m.strip()],
        frames=None if args.frames is None else parse_frames(args.frames),
        views=[v.strip() for v in args.views.split(",") if v.strip()], device=args.device,
        width=args.width, supersample=args.supersample, progress=not args.quiet,
        force=args.force, sweeps_dir=None if args.no_sweeps else "default",
        up_axis=args.up_axis, clip=_clip(args.clip))
    print(f"wrote {Path(args.out) / 'report.html'} ({len(result['frames'])} frames × "
          f"{len(result['methods'])} methods × {len(result['views'])} views, "
          f"{result['timing_s']['total']:.1f} s)")
    print("\n".join(summary_lines(result)))
    return 0


def _add_compare_arguments(parser):
    from .report.render import VIEWS
    parser.add_argument("input", help="character file (.usd/.usda/.usdc/.usdz, .gltf/.glb)")
    parser.add_argument("--out", required=True, help="output folder: report.html, metrics.json, "
                        "frames/*.png")
    parser.add_argument("--methods", default="lbs,dqs",
                        help=f"comma-separated from {', '.join(METHODS)} (default: lbs,dqs)")
    parser.add_argument("--frames", help="START:END[:STEP] (END inclusive) or T1,T2,... in the "
                        "asset's time unit; default: up to 10 evenly spaced samples")
    parser.add_argument("--views", default=",".join(VIEWS),
                        help=f"comma-separated from {', '.join(VIEWS)} (default: all)")
    parser.add_argument("--width", type=int, default=512, help="image size: about WIDTH² "
                        "pixels, shaped to each view (default: 512)")
    parser.add_argument("--supersample", type=int, default=2, help="anti-aliasing rays per pixel "
                        "along each axis (default: 2)")
    parser.add_argument("--up-axis", choices=["Y", "Z"], help="skeleton-space up axis for the "
                        "cameras (default: the asset's)")
    parser.add_argument("--no-sweeps", action="store_true", help="leave out the twist/bend "
                        "sweeps on the procedural rigs")
    parser.add_argument("--clip", help="glTF animation name or index")
    parser.add_argument("--device", help="cpu or cuda (default: cuda when present)")
    parser.add_argument("--quiet", action="store_true", help="no progress bar")
    parser.add_argument("--force", action="store_true", help="overwrite an existing report")


def build_parser():
    ap = argparse.ArgumentParser(prog="dqskin", description="Dual-quaternion and linear-blend "
                                 "skinning on NVIDIA Warp")
    sub = ap.add_subparsers(dest="command", required=True)
    s = sub.add_parser("skin", help="skin every frame and write a cache")
    s.add_argument("input")
    s.add_argument("--out", required=True, help=".usd/.usda/.usdc cache, .npz, or a per-frame "
                   "pattern like out/frame_{:04d}.obj")
    s.add_argument("--method", choices=list(METHODS), default=None,
                   help="default: what the asset asks for (LBS for glTF)")
    s.add_argument("--frames", help="START:END[:STEP] (END inclusive) or T1,T2,... in the "
                   "asset's time unit (USD time codes, glTF seconds)")
    s.add_argument("--fps", type=float, help="resample the clip at this many frames per second "
                   "(also the default STEP of --frames)")
    s.add_argument("--substeps", type=int, default=1,
                   help="samples per frame interval (motion-blur sub-frames)")
    s.add_argument("--interp", choices=INTERPOLATIONS, default="trs",
                   help="joint interpolation between keys: trs = the asset's own (default); "
                   "sclerp, dlb, spline, catmull-rom interpolate dual quaternions")
    s.add_argument("--no-velocities", dest="velocities", action="store_false",
                   help="don't write per-point velocities (units/s) to USD caches")
    s.add_argument("--no-normals", dest="normals", action="store_false",
                   help="don't skin normals into USD caches (they keep their rest values)")
    s.add_argument("--clip", help="glTF animation name or index")
    s.add_argument("--device", help="cpu or cuda (default: cuda when present)")
    s.add_argument("--chunk", type=int, default=256, help="frames per chunk (bounds memory)")
    s.add_argument("--force", action="store_true", help="overwrite existing outputs")
    s.set_defaults(run=cmd_skin)
    i = sub.add_parser("info", help="skeleton tree, meshes, influences, time range, problems")
    i.add_argument("input")
    i.add_argument("--clip")
    i.set_defaults(run=cmd_info)
    c = sub.add_parser("compare", help="offscreen LBS-vs-DQS report: report.html, metrics.json, "
                       "frames/*.png")
    _add_compare_arguments(c)
    c.set_defaults(run=cmd_compare)
    d = sub.add_parser("demo", help="run the main job on the bundled humanoid")
    d.add_argument("--asset", help="default: the bundled humanoid")
    d.add_argument("--out", default="out/demo")
    d.add_argument("--device")
    d.set_defaults(run=cmd_demo)
    return ap


def main(argv=None):
    import warp as wp
    wp.config.quiet = True
    wp.config.log_level = wp.LOG_ERROR  # no init banner or per-module load timings on stdout
    args = build_parser().parse_args(argv)
    try:
        return args.run(args)
    except (ValueError, FileExistsError, KeyError, OSError) as exc:
        msg = exc.args[0] if isinstance(exc, KeyError) and exc.args else exc
        print(f"dqskin: error: {msg}", file=sys.stderr)
        return EXIT_INPUT


if __name__ == "__main__":
    sys.exit(main())
