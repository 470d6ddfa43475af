"""Skeleton-embedding accuracy against the truth (issue 31).

    python tools/bench_embedding.py [--quiet]

Artists' characters (CesiumMan, RiggedFigure, greenman; glTF and USD): the character's own
skeleton, shrunk to 60% and moved off the mesh by twice its height (so that nothing of its
placement is kept) and optionally re-posed (every joint turned by a random 5–10°, or 10–20° over
10 seeds), is embedded into the character's bind-pose mesh by
:func:`dqskin.embedding.embed_skeleton`, and the deforming joints are compared with the artist's:
distance in % of the mesh's vertical height, mean and worst, and every joint.

A body of capsules around the CMU skeleton's bones (the tests' ``capsule_body``; I-pose, the arms
touching the thighs): the skeleton, displaced, embedded back, against its own joints.

MakeHuman's base body (../shared/assets/bodies/makehuman/base_body.obj, A-pose, decimetres) with
the CMU capture's skeleton (scaled_131_02.bvh, I-pose, metres): the embedded joints against
MakeHuman's own joint markers (base_joints.json), matched by :data:`MAKEHUMAN_MARKERS`.
"""

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
SHARED = ROOT.parent / "shared" / "assets"

CHARACTERS = [("CesiumMan", "khronos-gltf/CesiumMan/CesiumMan.glb", 2),
              ("CesiumMan", "usd-wg/CesiumMan/CesiumMan.usdz", 2),
              ("RiggedFigure", "khronos-gltf/RiggedFigure/RiggedFigure.glb", 2),
              ("RiggedFigure", "usd-wg/RiggedFigure/RiggedFigure.usdz", 2),
              ("greenman", "raylib-gltf/greenman.glb", 1)]
"""(name, file under ../shared/assets, up axis of its skeleton space)."""

SEEDS = 10
"""Random poses of the guess per character for the 10–20° rows."""

MAKEHUMAN_MARKERS = {
    "Hips": "pelvis", "LeftHip": "l-upper-leg", "LeftKnee": "l-knee", "LeftAnkle": "l-ankle",
    "RightHip": "r-upper-leg", "RightKnee": "r-knee", "RightAnkle": "r-ankle",
    "LeftCollar": "l-clavicle", "LeftShoulder": "l-shoulder", "LeftElbow": "l-elbow",
    "LeftWrist": "l-hand", "RightCollar": "r-clavicle", "RightShoulder": "r-shoulder",
    "RightElbow": "r-elbow", "RightWrist": "r-hand", "Neck": "neck", "Head": "head",
}
"""CMU joint → MakeHuman marker (hm08 joint-* cubes)."""


def character(path):
    """(points (V, 3) in skeleton space, faces, skeleton, deforming joints) of a character's
    first mesh; ``path`` under ../shared/assets (or absolute)."""
    from dqskin import readers
    scene = readers.load(SHARED / path)
    m = scene.meshes[0]
    skel = scene.skeletons[m.skeleton]
    g = m.geom_bind_transform
    pts = np.asarray(m.points, np.float64) @ g[:3, :3].T + g[:3, 3]
    used = np.unique(np.asarray(m.joint_indices)[np.asarray(m.joint_weights) > 0])
    return pts, np.asarray(m.faces), skel, used


def displaced(skel, factor=0.6, up=1):
    """The skeleton shrunk by ``factor`` about its root and moved off by twice its height."""
    from dqskin import Skeleton
    bind = skel.bind_transforms.copy()
    x = bind[:, :3, 3]
    h = float(np.ptp(x, axis=0).max())
    shift = np.zeros(3)
    shift[(up + 1) % 3] = 2 * h
    bind[:, :3, 3] = (x - x[0]) * factor + x[0] + shift
    return Skeleton(skel.joint_names, skel.parents, bind, name=skel.name)


def reposed(skel, degrees=10.0, seed=0):
    """The skeleton with every joint's local rotation turned by a random rotation of up to
    ``degrees`` (fixed ``seed``): another pose, the same bones."""
    from scipy.spatial.transform import Rotation

    from dqskin import Skeleton
    from dqskin.retarget import world_transforms
    bind = skel.bind_transforms
    local = bind.copy()
    has = skel.parents >= 0
    local[has] = np.linalg.inv(bind[skel.parents[has]]) @ bind[has]
    rng = np.random.default_rng(seed)
    axes = rng.normal(size=(len(local), 3))
    angles = np.radians(degrees) * rng.uniform(0.5, 1.0, len(local))  # half to all of it
    turn = Rotation.from_rotvec(axes / np.linalg.norm(axes, axis=1)[:, None]
                                * angles[:, None]).as_matrix()
    local[:, :3, :3] = local[:, :3, :3] @ turn
    world = world_transforms(skel.parents, local[None])[0]
    return Skeleton(skel.joint_names, skel.parents, world, name=skel.name)


def run_character(name, path, up, pose=False, degrees=10.0, seed=0):
    from dqskin.embedding import embed_skeleton, embedding_errors
    pts, faces, skel, used = character(path)
    guess = displaced(reposed(skel, degrees, seed) if pose else skel, up=up)
    t0 = time.perf_counter()
    got = embed_skeleton((pts, faces), guess, deforming=used, up=up)
    dt = time.perf_counter() - t0
    height = float(np.ptp(pts[:, up]))
    mean, worst, per = embedding_errors(got.bind_transforms[used, :3, 3],
                                        skel.bind_transforms[used, :3, 3], height)
    return mean, worst, {skel.joint_names[j].split("/")[-1]: d for j, d in zip(used, per)}, dt


def run_capsules(radius):
    """The CMU skeleton embedded in a body of capsules around its own bones (I-pose: the arms
    hang against the thighs, touching them), against the skeleton's joints."""
    sys.path.insert(0, str(ROOT / "tests"))
    from test_autoweights import capsule_body

    from dqskin.embedding import embed_skeleton, embedding_errors
    from dqskin.readers import bvh
    motion = bvh.read_bvh(SHARED / "cmu-mocap" / "scaled_131_02.bvh")
    skel = motion.skeleton()
    pts, faces = capsule_body(skel, motion.end_sites, radius=radius)
    t0 = time.perf_counter()
    got = embed_skeleton((pts, faces), displaced(skel), end_sites=motion.end_sites)
    dt = time.perf_counter() - t0
    mean, worst, per = embedding_errors(got.bind_transforms[:, :3, 3],
                                        skel.bind_transforms[:, :3, 3], float(np.ptp(pts[:, 1])))
    return mean, worst, dict(zip(skel.joint_names, per)), dt


def run_makehuman():
    from dqskin.embedding import embed_skeleton, embedding_errors
    from dqskin.readers import bvh
    from dqskin.readers.mesh import load_mesh
    folder = SHARED / "bodies" / "makehuman"
    pts, faces = load_mesh(folder / "base_body.obj")
    markers = json.loads((folder / "base_joints.json").read_text())["joints"]
    motion = bvh.read_bvh(SHARED / "cmu-mocap" / "scaled_131_02.bvh")
    skel = motion.skeleton()
    t0 = time.perf_counter()
    got = embed_skeleton((pts, faces), skel, end_sites=motion.end_sites)
    dt = time.perf_counter() - t0
    names = [n for n in MAKEHUMAN_MARKERS if n in skel.joint_names]
    idx = [skel.joint_names.index(n) for n in names]
    truth = np.array([markers[MAKEHUMAN_MARKERS[n]] for n in names])
    height = float(np.ptp(np.asarray(pts)[:, 1]))
    mean, worst, per = embedding_errors(got.bind_transforms[idx, :3, 3], truth, height)
    return mean, worst, dict(zip(names, per)), dt


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--quiet", action="store_true", help="only the summary lines")
    args = ap.parse_args(argv)
    import warp as wp
    wp.config.quiet = True
    rows = [(f"{n} ({Path(p).suffix[1:]})", *run_character(n, p, up)) for n, p, up in CHARACTERS]
    rows += [(f"{n} ({Path(p).suffix[1:]}), guess re-posed", *run_character(n, p, up, True))
             for n, p, up in CHARACTERS if p.endswith(".glb")]
    rows.append(("MakeHuman + CMU skeleton vs markers", *run_makehuman()))
    rows += [(f"capsule body around the CMU skeleton, radius {r:g} of each bone, arms touching "
              "the thighs", *run_capsules(r)) for r in (0.18, 0.25)]
    for label, mean, worst, per, dt in rows:
        print(f"{label}: mean {mean:.2f}%, worst {worst:.2f}% of height ({len(per)} joints, "
              f"{dt:.2f} s)")
        if not args.quiet:
            print("   " + ", ".join(f"{k} {v:.1f}" for k, v in per.items()))
    for n, p, up in CHARACTERS:
        if p.endswith(".glb") and n != "greenman":
            runs = [run_character(n, p, up, True, 20.0, seed) for seed in range(SEEDS)]
            means = [r[0] for r in runs]
            print(f"{n} ({Path(p).suffix[1:]}), guess re-posed by 10-20° per joint, {SEEDS} "
                  f"seeds: mean {np.mean(means):.2f}%, median {np.median(means):.2f}%, "
                  f"worst seed {max(means):.2f}% (worst joint {max(r[1] for r in runs):.2f}%)")
            if not args.quiet:
                print("   seed means: " + ", ".join(f"{m:.2f}" for m in means))
    sys.stdout.flush()


if __name__ == "__main__":
    main()
