"""The ``dqskin`` command line: ``skin``, ``info``, ``compare`` and ``demo``.

Errors in the input print one line naming the file, prim or field and exit with status 2; no
traceback. Existing outputs are never overwritten without ``--force``; outputs are atomic.
"""

import argparse
import sys
from pathlib import Path

import numpy as np

from .motion import INTERPOLATIONS

__all__ = ["main"]

EXIT_INPUT = 2
ASSETS = Path(__file__).resolve().parents[1] / "assets"


class CliError(Exception):
    """An error reported as one line, exit status 2."""


def parse_frames(text, default_step=1.0):
    """``START:END[:STEP]`` → (start, end, step) floats (END inclusive)."""
    parts = text.split(":")
    try:
        if len(parts) not in (2, 3):
            raise ValueError
        start, end = float(parts[0]), float(parts[1])
        step = float(parts[2]) if len(parts) == 3 else default_step
    except ValueError:
        raise CliError(f"--frames {text!r}: expected START:END[:STEP]") from None
    if step <= 0 or end < start:
        raise CliError(f"--frames {text!r}: need END >= START and STEP > 0")
    return start, end, step


def select_times(scene, frames=None, fps=None, substeps=1):
    """Sample times: the asset's own, an explicit ``--frames`` range, or ``--fps`` resampling
    (which also sets the default STEP of ``--frames``); ``substeps`` more samples evenly inside
    each interval (motion-blur sub-frames)."""
    t = np.asarray(scene.times, np.float64)
    if fps is not None and fps <= 0:
        raise CliError(f"--fps {fps}: must be positive")
    step = 1.0 if fps is None else scene.time_codes_per_second / fps
    if frames is not None:
        start, end, step = parse_frames(frames, step)
        t = np.arange(start, end + step * 1e-6, step)
    elif fps is not None:
        t = np.arange(t[0], t[-1] + step * 1e-6, step)
    if t.size == 0:
        raise CliError(f"{scene.path}: no frames selected")
    if substeps < 1:
        raise CliError(f"--substeps {substeps}: must be at least 1")
    if substeps > 1 and t.size > 1:
        u = np.arange(substeps) / substeps
        t = np.append((t[:-1, None] + np.diff(t)[:, None] * u).ravel(), t[-1])
    return t


def frame_numbers(scene, times):
    """Integer frame numbers for file names: USD time codes; for glTF (seconds) the sample rate's
    frames (24 fps, or finer when the samples are). A CliError when two frames would still share
    a name."""
    from .io import GLTF_SUFFIXES
    t = np.asarray(times, dtype=np.float64)
    gltf = Path(scene.path).suffix.lower() in GLTF_SUFFIXES
    rate = 1.0
    if gltf:
        step = np.diff(t).min() if t.size > 1 else 1.0
        rate = max(24.0, float(np.round(1.0 / step)) if step > 0 else 24.0)
    numbers = np.round(t * rate).astype(int)
    if len(set(numbers.tolist())) != len(numbers):
        raise CliError(f"--out: {len(numbers)} frames map to {len(set(numbers.tolist()))} file "
                       "names (sub-frame times); write .npz"
                       + ("" if gltf else " or .usd/.usdc") + " instead")
    return numbers


def chunk_velocities(scene, times, method, interp, device):
    """Per-mesh velocities (units per second) for one chunk; "blend" mixes LBS and DQS."""
    from .motion import scene_velocities
    if method != "blend":
        return scene_velocities(scene, times, method, interp, device=device)
    lbs = scene_velocities(scene, times, "lbs", interp, device=device)
    dqs = scene_velocities(scene, times, "dqs", interp, device=device)
    return {m.name: (lbs[m.name] * (1 - m.blend_or_default()[:, None])
                     + dqs[m.name] * m.blend_or_default()[:, None]) for m in scene.meshes}


def skin_chunks(scene, times, method, device, chunk, normals, progress=True, interp="trs",
                velocities=False):
    """Yield ``(slice, points, normals, velocities)`` per chunk of frames, so memory stays bounded.

    The next chunk is skinned on a worker thread while the caller writes the current one (Warp
    launches and NumPy release the GIL, so the two overlap).
    """
    from concurrent.futures import ThreadPoolExecutor

    from tqdm import tqdm

    def compute(sl):
        res = scene.skin(times[sl], method, device=device, normals=normals, interp=interp)
        pts, nrm = res if normals else (res, {})
        vel = chunk_velocities(scene, times[sl], method, interp, device) if velocities else {}
        return sl, pts, nrm, vel

    slices = [slice(lo, min(lo + chunk, len(times))) for lo in range(0, len(times), chunk)]
    bar = tqdm(total=len(times), unit="frame", disable=not progress or len(slices) < 3,
               desc="skinning", file=sys.stderr)
    with ThreadPoolExecutor(max_workers=1, thread_name_prefix="dqskin-skin") as ex:
        fut = ex.submit(compute, slices[0])
        for k, sl in enumerate(slices):
            res = fut.result()
            if k + 1 < len(slices):
                fut = ex.submit(compute, slices[k + 1])
            yield res
            bar.update(sl.stop - sl.start)
    bar.close()


def check_output(out, inputs, force):
    out = Path(out)
    for src in inputs:
        if out.resolve() == Path(src).resolve():
            raise CliError(f"{out}: refusing to overwrite the input")
    if out.exists() and not force:
        raise CliError(f"{out}: exists (use --force to overwrite)")
    return out


def cmd_skin(args):
    from . import io
    if args.chunk < 1:
        raise CliError(f"--chunk {args.chunk}: must be at least 1")
    scene = io.load(args.input, clip=args.clip)
    times = select_times(scene, args.frames, args.fps, args.substeps)
    out = str(args.out)
    suffix = Path(out).suffix.lower()
    names = [m.name for m in scene.meshes]
    F = len(times)
    if suffix in (".usd", ".usda", ".usdc"):
        if Path(args.input).suffix.lower() not in io.USD_SUFFIXES:
            raise CliError(f"--out {out}: a USD point cache copies the input stage, so it needs a "
                           "USD input; for glTF write .npz or per-frame .obj/.ply/.glb files")
        check_output(out, [args.input], args.force)
        from .usd_cache import UsdCacheWriter
        wrote_velocities = False
        with UsdCacheWriter(scene, out, source_path=args.input, method=args.method,
                            device=args.device, interp=args.interp) as writer:
            for sl, p, n, v in skin_chunks(scene, times, args.method, args.device, args.chunk,
                                           args.normals, interp=args.interp,
                                           velocities=args.velocities):
                writer.write(times[sl], p, n, v)
                wrote_velocities |= bool(v)
        print(f"wrote {out}: {len(names)} meshes × {F} frames ({args.method or 'asset method'}"
              f"{', velocities' if wrote_velocities else ''})")
    elif suffix == ".npz":
        check_output(out, [args.input], args.force)
        pts = {n: np.empty((F, len(scene.mesh(n).points), 3), np.float32) for n in names}
        for sl, p, _, _ in skin_chunks(scene, times, args.method, args.device, args.chunk, False,
                                       interp=args.interp):
            for name in names:
                pts[name][sl] = p[name]
        with io.atomic_path(out) as tmp:
            with open(tmp, "wb") as fh:
                np.savez(fh, times=times, names=np.array(names),
                         **{f"points_{i}": pts[n] for i, n in enumerate(names)},
                         **{f"faces_{i}": scene.mesh(n).faces for i, n in enumerate(names)})
        print(f"wrote {out}: {len(names)} meshes × {F} frames")
    elif suffix in io.MESH_SUFFIXES:
        numbers = frame_numbers(scene, times)
        paths = io.frame_paths(out, numbers)
        for p in paths:
            check_output(p, [args.input], args.force)
        faces, offset = [], 0
        for m in scene.meshes:
            faces.append(m.faces + offset)
            offset += len(m.points)
        faces = np.concatenate(faces)
        for sl, p, _, _ in skin_chunks(scene, times, args.method, args.device, args.chunk, False,
                                       interp=args.interp):
            stacked = np.concatenate([p[n] for n in names], axis=1)
            io.write_frames(out, numbers[sl], stacked, faces, force=args.force)
        print(f"wrote {len(paths)} files {paths[0]} … {paths[-1]}")
    else:
        raise CliError(f"--out {out}: unsupported output type; use .usd/.usda/.usdc, .npz, or a "
                       "per-frame pattern like out/frame_{:04d}.obj (.obj .ply .stl .off .glb)")
    return 0


def cmd_info(args):
    from . import io
    scene = io.load(args.input, clip=args.clip)
    print(f"{scene.path}")
    t = np.asarray(scene.times)
    unit = "s" if scene.time_codes_per_second == 1.0 else f"time codes @ {scene.time_codes_per_second:g}/s"
    print(f"  time range: {t[0]:g} .. {t[-1]:g} ({len(t)} samples, {unit}); up axis {scene.up_axis}, "
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
              f"{m.skeleton}, method {m.skinning_method}, {m.joint_indices.shape[1]} influence slots")
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
    asset = Path(args.asset)
    if not asset.is_file():
        raise CliError(f"{asset}: demo asset not found (run from a source checkout, or pass --asset)")
    out_dir = Path(args.out)
    out_dir.mkdir(parents=True, exist_ok=True)
    cache = out_dir / "humanoid_dqs.usdc"
    print(f"dqskin demo: skinning {asset.name} with DQS")
    cmd_skin(build_parser().parse_args(["skin", str(asset), "--out", str(cache), "--method", "dqs",
                                        "--force"] + (["--device", args.device] if args.device
                                                      else [])))
    from .compare import run_compare
    report = out_dir / "report"
    print(f"dqskin demo: comparing LBS and DQS on {asset.name}")
    metrics = run_compare(asset, report, device=args.device, force=True)
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


def build_parser():
    ap = argparse.ArgumentParser(prog="dqskin", description="Dual-quaternion and linear-blend "
                                 "skinning on NVIDIA Warp")
    sub = ap.add_subparsers(dest="command", required=True)
    s = sub.add_parser("skin", help="skin every frame and write a cache")
    s.add_argument("input")
    s.add_argument("--out", required=True, help=".usd/.usda/.usdc cache, .npz, or a per-frame "
                   "pattern like out/frame_{:04d}.obj")
    s.add_argument("--method", choices=["dqs", "lbs", "blend"], default=None,
                   help="default: what the asset asks for (LBS for glTF)")
    s.add_argument("--frames", help="START:END[:STEP] in the asset's time unit (USD time codes, "
                   "glTF seconds), END inclusive")
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
    from .compare import add_compare_arguments, cmd_compare
    c = sub.add_parser("compare", help="offscreen LBS-vs-DQS report: report.html, metrics.json, "
                       "frames/*.png")
    add_compare_arguments(c)
    c.set_defaults(run=cmd_compare)
    d = sub.add_parser("demo", help="run the main job on the bundled humanoid")
    d.add_argument("--asset", default=str(ASSETS / "humanoid.usda"))
    d.add_argument("--out", default="out/demo")
    d.add_argument("--device")
    d.set_defaults(run=cmd_demo)
    return ap


def main(argv=None):
    import warp as wp
    wp.config.quiet = True
    wp.config.log_level = wp.LOG_ERROR  # no init banner or per-module load timings on stdout
    args = build_parser().parse_args(argv)
    if getattr(args, "clip", None) is not None and args.clip.isdigit():
        args.clip = int(args.clip)
    try:
        return args.run(args)
    except (CliError, ValueError, FileExistsError, KeyError, OSError) as exc:
        msg = exc.args[0] if isinstance(exc, KeyError) and exc.args else exc
        print(f"dqskin: error: {msg}", file=sys.stderr)
        return EXIT_INPUT


if __name__ == "__main__":
    sys.exit(main())
