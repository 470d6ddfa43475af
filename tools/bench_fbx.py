"""FBX benchmark: loading and skinning the largest shared FBX file against ufbx's own evaluation
loop, and where the time goes.

    python tools/bench_fbx.py [--file NAME] [--frames 1000] [--repeat 3]

``NAME`` (default ``maya_slime_7500_ascii.fbx``, the largest of ../shared/assets/ufbx/data) is
loaded with :func:`dqskin.load` (best of ``--repeat``), split into the FBX reader's process
(Python start-up and imports, ufbx's parse, reading meshes and clusters, evaluating every whole
frame of the stack) and building the :class:`~dqskin.Scene`; then every skinned mesh is skinned
at ``--frames`` times spread over the stack (one :meth:`dqskin.Scene.skin` call, world space,
the asset's method): the first call, where the reader's process evaluates the times between
frames, and again (those evaluations kept), best of ``--repeat``; and compared with ufbx's
loop over the same times, ``ufbx.evaluate_scene(scene, anim, t, evaluate_skinning=True)`` per
time (run in a process of its own, as the bindings require; ufbx's parse timed apart). Prints
one table and writes nothing.
"""

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
DATA = ROOT.parent / "shared" / "assets" / "ufbx" / "data"


def ufbx_loop(path: str, seconds: list[float]) -> None:
    """(In its own process) ufbx's parse and its evaluate-with-skinning loop; prints JSON."""
    import ufbx
    keep = []
    t0 = time.perf_counter()
    scene = ufbx.load_file(path, evaluate_skinning=True)
    t1 = time.perf_counter()
    stacks = scene.anim_stacks
    stack = stacks[0]
    anim = stack.anim
    keep += [scene, stacks, stack, anim]
    t2 = time.perf_counter()
    for t in seconds:
        ev = ufbx.evaluate_scene(scene, anim, t, evaluate_skinning=True)
        meshes = ev.meshes
        for i in range(len(meshes)):
            m = meshes[i]
            pos = m.skinned_position
            values = np.array(memoryview(pos.values))  # the skinned points, as a user takes them
            keep += [ev, meshes, m, pos, values]
    t3 = time.perf_counter()
    print(json.dumps({"parse": t1 - t0, "loop": t3 - t2}), flush=True)
    os._exit(0)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--file", default="maya_slime_7500_ascii.fbx")
    ap.add_argument("--frames", type=int, default=1000)
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--ufbx-loop", nargs="+", help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.ufbx_loop:
        ufbx_loop(args.ufbx_loop[0], [float(x) for x in args.ufbx_loop[1:]])
    import dqskin
    from dqskin.readers import fbx

    path = DATA / args.file
    rows = []
    best_load = best_extract = np.inf
    timing = {}
    for _ in range(args.repeat):
        t0 = time.perf_counter()
        meta, _ = fbx._extract(path, None)
        t1 = time.perf_counter()
        scene = dqskin.load(path)
        t2 = time.perf_counter()
        if t1 - t0 < best_extract:
            best_extract, timing = t1 - t0, meta["timing_s"]
        best_load = min(best_load, t2 - t1)
    inside = sum(timing.values())
    frames = len(scene.times)
    rows += [("dqskin.load (total)", best_load, ""),
             ("  reader process: Python start-up, exchange", best_extract - inside, ""),
             ("  reader process: import ufbx", timing["import"], ""),
             ("  reader process: ufbx parse", timing["load"], ""),
             ("  reader process: meshes and clusters", timing["meshes"], ""),
             ("  reader process: evaluate whole frames", timing["frames"],
              f"{frames} frames, {1e3 * timing['frames'] / frames:.2f} ms each"),
             ("  build the Scene", best_load - best_extract, "")]
    t = np.linspace(scene.times[0], scene.times[-1], args.frames)
    best_first = best_skin = np.inf
    for _ in range(args.repeat):
        scene = dqskin.load(path)
        scene.skin(scene.times[:2], space="world")  # warm-up: kernels, uploads
        t0 = time.perf_counter()
        scene.skin(t, space="world")
        best_first = min(best_first, time.perf_counter() - t0)
        t0 = time.perf_counter()
        res = scene.skin(t, space="world")
        best_skin = min(best_skin, time.perf_counter() - t0)
    vertices = sum(p.shape[1] for p in res.points.values())
    rows.append((f"dqskin Scene.skin, {args.frames} times, first call", best_first,
                 f"{1e6 * best_first / args.frames:.1f} µs a time (ufbx evaluates the times "
                 "between frames)"))
    rows.append((f"dqskin Scene.skin, {args.frames} times, again", best_skin,
                 f"{1e6 * best_skin / args.frames:.1f} µs a time, {vertices} vertices"))
    seconds = [repr(float(x)) for x in t]
    best_loop, parse = np.inf, np.inf
    for _ in range(args.repeat):
        done = subprocess.run([sys.executable, __file__, "--ufbx-loop", str(path), *seconds],
                              capture_output=True, text=True, check=True)
        r = json.loads(done.stdout.strip().splitlines()[-1])
        best_loop, parse = min(best_loop, r["loop"]), min(parse, r["parse"])
    rows += [("ufbx load_file (evaluate_skinning)", parse, ""),
             (f"ufbx evaluate_scene + skinning, {args.frames} times", best_loop,
              f"{1e6 * best_loop / args.frames:.1f} µs a time")]
    print(f"{path.name}: {frames} frames at {scene.frame_rate:g} fps, "
          f"{len(scene.meshes)} meshes, {sum(s.joint_count for s in scene.skeletons)} joints; "
          f"best of {args.repeat}")
    width = max(len(r[0]) for r in rows)
    for name, seconds_, note in rows:
        print(f"  {name:<{width}}  {1e3 * seconds_:9.2f} ms  {note}")


if __name__ == "__main__":
    main()
