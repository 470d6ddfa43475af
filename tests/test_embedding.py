"""Skeleton embedding, retargeting and fits that explain themselves (issue 31).

Oracles: the artists' joint positions (CesiumMan, RiggedFigure, greenman), MakeHuman's own joint
markers (base_joints.json), the capture's FK written from the BVH text (tests/test_bvh.py), and
the rest mesh's own floor.
"""

import json
import re
import sys
from pathlib import Path

import numpy as np
import pytest
import trimesh
from test_bvh import oracle

from dqskin import readers
from dqskin.cli import main
from dqskin.embedding import embed_skeleton, embedding_errors
from dqskin.readers import bvh
from dqskin.readers.mesh import load_mesh

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tools"))
from bench_embedding import MAKEHUMAN_MARKERS, character, displaced, reposed  # noqa: E402

FRAMES = 40


def world_transforms(parents, local):
    """(F, J, 4, 4) world transforms of (F, J, 4, 4) local ones, float64: ``Wⱼ = Wₚ·Lⱼ``."""
    world = np.array(local, np.float64)
    for j, p in enumerate(parents):
        if p >= 0:
            world[:, j] = world[:, p] @ world[:, j]
    return world


def _short_capture(src, folder, frames=FRAMES, step=6):
    """Every ``step``-th frame of a capture, ``frames`` of them, as a new BVH."""
    lines = Path(src).read_text().splitlines()
    at = lines.index("MOTION")
    body = lines[at + 3:][::step][:frames]
    out = folder / "walk.bvh"
    out.write_text("\n".join(lines[:at + 1] + [f"Frames: {len(body)}", lines[at + 2]] + body)
                   + "\n")
    return out


@pytest.mark.parametrize("path, up, pose, mean_max, worst_max", [
    ("khronos-gltf/CesiumMan/CesiumMan.glb", 2, False, 2.0, 3.5),
    ("khronos-gltf/CesiumMan/CesiumMan.glb", 2, True, 2.5, 4.5),
    ("usd-wg/RiggedFigure/RiggedFigure.usdz", 2, False, 3.0, 4.5),
    ("raylib-gltf/greenman.glb", 1, False, 3.0, 3.5),  # a blob: arm stubs, foot bumps
])
def test_embedding_finds_the_artists_joints(shared_assets, path, up, pose, mean_max, worst_max):
    """The character's own skeleton, shrunk and moved off the mesh (and re-posed: every joint
    turned by 5–10°), embedded from scratch: every joint against the artist's, in % of the
    mesh's height."""
    pts, faces, skel, used = character(shared_assets / path)
    guess = displaced(reposed(skel) if pose else skel, up=up)
    assert np.abs(guess.bind_transforms[used, :3, 3] - skel.bind_transforms[used, :3, 3]
                  ).max() > 0.5 * np.ptp(pts[:, up]), "the guess is nowhere near the answer"
    got = embed_skeleton((pts, faces), guess, deforming=used, up=up)
    assert got.joint_names == skel.joint_names
    np.testing.assert_array_equal(got.parents, skel.parents)
    mean, worst, _ = embedding_errors(got.bind_transforms[used, :3, 3],
                                      skel.bind_transforms[used, :3, 3], np.ptp(pts[:, up]))
    assert mean <= mean_max and worst <= worst_max, (mean, worst)


def test_embedding_tells_left_from_right_whatever_the_guess_pose(shared_assets):
    """CesiumMan's own skeleton re-posed by 10–20° per joint (the legs crossing over in the
    guess: seeds 1–3): each limb still goes to its own side's extremity (the sides of two
    limbs branching from one joint), every joint against the artist's."""
    pts, faces, skel, used = character(shared_assets / "khronos-gltf/CesiumMan/CesiumMan.glb")
    for seed in (1, 2, 3):
        guess = displaced(reposed(skel, 20.0, seed), up=2)
        got = embed_skeleton((pts, faces), guess, deforming=used, up=2)
        mean, worst, _ = embedding_errors(got.bind_transforms[used, :3, 3],
                                          skel.bind_transforms[used, :3, 3], np.ptp(pts[:, 2]))
        assert mean <= 2.5 and worst <= 5.0, (seed, mean, worst)


def test_embedding_a_capsule_body_with_arms_touching_the_thighs(shared_assets):
    """The CMU skeleton, displaced, embedded back into a body of capsules around its own bones
    (I-pose: the forearms' capsules touch the thighs'; separate parts, joined each to its
    nearest): the hands and feet go to their own extremities, every joint against the
    skeleton's own."""
    from test_autoweights import capsule_body
    motion = bvh.read_bvh(shared_assets / "cmu-mocap" / "scaled_131_02.bvh")
    skel = motion.skeleton()
    pts, faces = capsule_body(skel, motion.end_sites, radius=0.25)
    got = embed_skeleton((pts, faces), displaced(skel), end_sites=motion.end_sites)
    mean, worst, per = embedding_errors(got.bind_transforms[:, :3, 3],
                                        skel.bind_transforms[:, :3, 3], np.ptp(pts[:, 1]))
    assert mean <= 4.0 and worst <= 10.0, (mean, worst, per)


def test_embedding_a_capture_skeleton_in_makehuman(shared_assets):
    """The CMU skeleton (I-pose, metres) in MakeHuman's A-pose body (decimetres), against the
    body's own joint markers; a joints file overrides any joint."""
    folder = shared_assets / "bodies" / "makehuman"
    pts, faces = load_mesh(folder / "base_body.obj")
    markers = json.loads((folder / "base_joints.json").read_text())["joints"]
    motion = bvh.read_bvh(shared_assets / "cmu-mocap" / "scaled_131_02.bvh")
    skel = motion.skeleton()
    got = embed_skeleton((pts, faces), skel, end_sites=motion.end_sites)
    idx = [skel.joint_names.index(n) for n in MAKEHUMAN_MARKERS]
    truth = np.array([markers[v] for v in MAKEHUMAN_MARKERS.values()])
    mean, worst, per = embedding_errors(got.bind_transforms[idx, :3, 3], truth,
                                        np.ptp(pts[:, 1]))
    assert mean <= 3.2 and worst <= 7.0, (mean, worst, per)
    # the elbows bend out of the capture's straight-down arms into the body's A-pose
    for side in "LR":
        e = skel.joint_names.index(("Left" if side == "L" else "Right") + "Elbow")
        s = skel.parents[e]
        d = got.bind_transforms[e, :3, 3] - got.bind_transforms[s, :3, 3]
        angle = np.degrees(np.arctan2(-d[1], abs(d[0])))
        assert 30 < angle < 65, angle  # MakeHuman: 50° below horizontal
    over = embed_skeleton((pts, faces), skel, end_sites=motion.end_sites,
                          joints={"LeftElbow": markers["l-elbow"]})
    np.testing.assert_allclose(over.bind_transforms[skel.joint_names.index("LeftElbow"), :3, 3],
                               markers["l-elbow"])


@pytest.fixture(scope="module")
def walk(shared_assets, tmp_path_factory):
    """MakeHuman's body rigged to a short CMU walk with the two documented commands."""
    folder = tmp_path_factory.mktemp("walk")
    capture = _short_capture(shared_assets / "cmu-mocap" / "scaled_131_02.bvh", folder)
    body = shared_assets / "bodies" / "makehuman" / "base_body.obj"
    rig, out = folder / "body_rig.usda", folder / "walk.npz"
    assert main(["rig", str(body), "--skeleton", str(capture), "--out", str(rig)]) == 0
    assert main(["skin", str(rig), "--method", "dqs", "--out", str(out)]) == 0
    with np.load(out) as z:
        points = z[[k for k in z.files if k.startswith("points")][0]].astype(np.float64)
    return capture, body, rig, points


def test_retargeted_bones_follow_the_capture(walk):
    """Every bone of a single-child joint points where the capture's does, at every frame
    (the capture's FK from the BVH text), although the body rests in an A-pose."""
    capture, body, rig, _ = walk
    names, parents, rot, pos, F = oracle(capture)
    scene = readers.load(rig)
    skel = scene.skeletons[0]
    order = [skel.joint_names.index(n) if n in skel.joint_names else
             [k for k, m in enumerate(skel.joint_names) if m.split("/")[-1] == n][0]
             for n in names]
    local = skel.animation.local_transforms(scene.times)
    world = world_transforms(skel.parents, local)[:, order]
    parents = np.asarray(parents)
    checked = 0
    for j, p in enumerate(parents):
        if p < 0 or np.sum(parents == p) != 1:
            continue
        dc = pos[:, j] - pos[:, p]
        de = world[:, j, :3, 3] - world[:, p, :3, 3]
        if np.linalg.norm(dc, axis=1).min() < 1e-6 or np.linalg.norm(de, axis=1).min() < 1e-6:
            continue
        cos = np.einsum("fk,fk->f", dc, de) / np.linalg.norm(dc, axis=1) \
            / np.linalg.norm(de, axis=1)
        assert np.degrees(np.arccos(np.clip(cos, -1, 1))).max() < 2.0, names[j]
        checked += 1
    assert checked >= 15


def _capture_feet(capture):
    """From the capture's FK (the BVH text): per frame, the lowest foot joint's height above the
    capture's floor level (its median) in % of the capture's height, and each foot's
    contact frames (that foot at the floor level, within 1%)."""
    names, parents, rot, pos, F = oracle(capture)
    motion = bvh.read_bvh(capture)
    rest = motion.rest_world()
    ends = [(rest[j] @ np.append(o, 1.0))[1] for j, o in motion.end_sites]
    height = np.ptp(np.concatenate([rest[:, 1, 3], ends]))
    feet = {side: [names.index(side + j) for j in ("Ankle", "Toe")] for side in ("Left", "Right")}
    y = pos[:, feet["Left"] + feet["Right"], 1].min(1)
    level = np.median(y)
    contact = {side: np.abs(pos[:, f, 1].min(1) - level) / height * 100 <= 1.0
               for side, f in feet.items()}
    return (y - level) / height * 100, contact, names, pos


def test_retargeted_walk_stands_on_the_floor(walk):
    """Whenever the capture's lowest foot joint is at its floor level (within 1% of its height),
    the skinned body's lowest point is at the rest mesh's floor within 1% of the body's height;
    at every frame it is as far from the floor as the capture's feet are from theirs, within 1%
    (where the capture's feet dip below its floor, the body's follow); the feet slide no more
    than the capture's (toe paths while in contact, per leg length); the body moves with the
    capture."""
    capture, body, rig, points = walk
    rest, _ = load_mesh(body)
    floor, height = rest[:, 1].min(), np.ptp(rest[:, 1])
    low = (points[..., 1].min(1) - floor) / height * 100
    dev, contact, names, pos = _capture_feet(capture)
    down = np.abs(dev) <= 1.0
    assert down.mean() > 0.5
    assert np.abs(low[down]).max() <= 1.0, low[down]
    assert np.abs(low - dev).max() <= 1.0, np.c_[low, dev]
    scene = readers.load(rig)
    skel = scene.skeletons[0]
    short = [n.split("/")[-1] for n in skel.joint_names]
    world = world_transforms(skel.parents, skel.animation.local_transforms(scene.times))

    def leg(p, side):
        j = [side + n for n in ("Hip", "Knee", "Ankle")]
        return sum(np.linalg.norm(p[names.index(a) if p is pos[0] else short.index(a)]
                                  - p[names.index(b) if p is pos[0] else short.index(b)])
                   for a, b in zip(j, j[1:]))

    for side in ("Left", "Right"):
        both = contact[side][1:] & contact[side][:-1]
        toe_c = pos[:, names.index(side + "Toe"), :][:, [0, 2]]
        toe_e = world[:, short.index(side + "Toe"), :3, 3][:, [0, 2]]
        slide_c = np.linalg.norm(np.diff(toe_c, axis=0), axis=1)[both].sum() / leg(pos[0], side)
        slide_e = (np.linalg.norm(np.diff(toe_e, axis=0), axis=1)[both].sum()
                   / leg(world[0, :, :3, 3], side))
        assert slide_e <= 1.1 * slide_c + 1e-9, (side, slide_e, slide_c)
    travel_c = np.linalg.norm(pos[-1, 0, [0, 2]] - pos[0, 0, [0, 2]])
    travel_e = np.linalg.norm(world[-1, 0, [0, 2], 3] - world[0, 0, [0, 2], 3])
    assert travel_c > 0.05 and travel_e > 0.5 * travel_c * height / 1.37


def test_feet_on_the_floor_over_the_whole_capture(shared_assets):
    """Every frame of the full capture (1,248) on MakeHuman's body: whenever the capture's
    lowest foot joint is at its floor level (within 1% of its height; its FK from the BVH text),
    the skinned body's lowest point (linear blend of the feet's rest points, float64, from the
    rig's weights) is within 1% of the body's height of the rest mesh's floor, and at every frame
    it is as far above the floor as the capture's feet are above theirs; the toes slide no more
    than the capture's."""
    import warnings

    from dqskin.rigging import FitWarning, rig_mesh
    capture = shared_assets / "cmu-mocap" / "scaled_131_02.bvh"
    body = shared_assets / "bodies" / "makehuman" / "base_body.obj"
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", FitWarning)
        scene = rig_mesh(body, capture)
    (m,), skel = scene.meshes, scene.skeletons[0]
    rest = np.asarray(m.points, np.float64)
    floor, height = rest[:, 1].min(), np.ptp(rest[:, 1])
    feet = np.nonzero(rest[:, 1] < floor + 0.15 * height)[0]
    world = world_transforms(skel.parents, skel.animation.local_transforms(scene.times))
    skin = world[:, :, :3] @ np.linalg.inv(skel.bind_transforms)  # (F, J, 3, 4)
    idx, w = np.asarray(m.joint_indices)[feet], np.asarray(m.joint_weights, np.float64)[feet]
    p = np.append(rest[feet], np.ones((len(feet), 1)), axis=1)
    y = sum(w[:, k] * np.einsum("fvl,vl->fv", skin[:, idx[:, k], 1], p)
            for k in range(idx.shape[1]))
    low = (y.min(1) - floor) / height * 100
    dev, contact, names, pos = _capture_feet(capture)
    assert len(low) == len(dev) == 1248
    down = np.abs(dev) <= 1.0
    assert down.mean() > 0.8
    assert np.abs(low[down]).max() <= 1.0, np.abs(low[down]).max()
    assert np.abs(low - dev).max() <= 0.1, np.abs(low - dev).max()
    short = [n.split("/")[-1] for n in skel.joint_names]
    for side in ("Left", "Right"):
        both = contact[side][1:] & contact[side][:-1]
        legs = [side + n for n in ("Hip", "Knee", "Ankle")]
        leg_c = sum(np.linalg.norm(pos[0, names.index(a)] - pos[0, names.index(b)])
                    for a, b in zip(legs, legs[1:]))
        leg_e = sum(np.linalg.norm(world[0, short.index(a), :3, 3]
                                   - world[0, short.index(b), :3, 3])
                    for a, b in zip(legs, legs[1:]))
        toe_c = pos[:, names.index(side + "Toe")][:, [0, 2]]
        toe_e = world[:, short.index(side + "Toe"), [0, 2], 3]
        slide_c = np.linalg.norm(np.diff(toe_c, axis=0), axis=1)[both].sum() / leg_c
        slide_e = np.linalg.norm(np.diff(toe_e, axis=0), axis=1)[both].sum() / leg_e
        assert slide_e <= 1.1 * slide_c, (side, slide_e, slide_c)


def test_refusal_offset_works_as_printed(tmp_path, capsys, shared_assets):
    """--as-is: a mesh far from the skeleton is refused with the offset to add to its points;
    adding it as printed makes the rig."""
    from test_autoweights import capsule_body
    capture = _short_capture(shared_assets / "cmu-mocap" / "scaled_131_02.bvh", tmp_path,
                             frames=3)
    motion = bvh.read_bvh(capture)
    pts, faces = capsule_body(motion.skeleton(), motion.end_sites, count=(6, 6))
    far = pts + [3.0, 120.0, -7.0]
    trimesh.Trimesh(far, faces, process=False).export(tmp_path / "far.obj")
    argv = ["rig", str(tmp_path / "far.obj"), "--skeleton", str(capture), "--as-is", "--out",
            str(tmp_path / "rig.usda")]
    assert main(argv) == 2
    err = capsys.readouterr().err
    offset = np.array(json.loads(re.search(r"add (\[[^\]]*\])", err).group(1)))
    # bounding-box centres: back where it was within 2% of the height
    assert np.abs(offset - [-3.0, -120.0, 7.0]).max() < 0.02 * np.ptp(pts[:, 1]), offset
    trimesh.Trimesh(far + offset, faces, process=False).export(tmp_path / "far.obj")
    assert main(argv) == 0, capsys.readouterr().err


def test_bad_fit_says_so_in_one_line(tmp_path, capsys, shared_assets):
    """--as-is: a mesh that binds but hangs below its skeleton's feet is rigged with one line
    saying so, with the figure."""
    from test_autoweights import capsule_body
    capture = _short_capture(shared_assets / "cmu-mocap" / "scaled_131_02.bvh", tmp_path,
                             frames=3)
    motion = bvh.read_bvh(capture)
    pts, faces = capsule_body(motion.skeleton(), motion.end_sites, count=(6, 6))
    low = pts - [0.0, 0.25 * np.ptp(pts[:, 1]), 0.0]
    trimesh.Trimesh(low, faces, process=False).export(tmp_path / "low.obj")
    assert main(["rig", str(tmp_path / "low.obj"), "--skeleton", str(capture), "--as-is",
                 "--out", str(tmp_path / "rig.usda")]) == 0
    lines = [x for x in capsys.readouterr().err.splitlines() if x.startswith("warning:")]
    assert any(re.search(r"feet are \d+\.\d% of the height above", x) for x in lines), lines


def test_joints_file_is_checked_and_named(tmp_path, capsys, shared_assets):
    """--joints FILE.json: unreadable files, wrong shapes and unknown joints are refused naming
    the file or the joint, before any weights; it needs --skeleton and cannot go with --as-is."""
    capture = _short_capture(shared_assets / "cmu-mocap" / "scaled_131_02.bvh", tmp_path,
                             frames=3)
    body = shared_assets / "bodies" / "makehuman" / "base_body.obj"
    cases = [("{not json", "cannot read joints"), ('{"LeftElbow": [1, 2]}', "expected"),
             ('{"joints": {"Elbow": [1, 2, 3]}}', "'Elbow' is not a joint")]
    for text, message in cases:
        path = tmp_path / "j.json"
        path.write_text(text)
        assert main(["rig", str(body), "--skeleton", str(capture), "--joints", str(path),
                     "--out", str(tmp_path / "r.usda")]) == 2
        err = capsys.readouterr().err
        assert message in err and "Traceback" not in err, (text, err)
    for extra, message in ((["--as-is"], "--as-is"), ([], "needs --skeleton")):
        argv = ["rig", str(body), "--joints", str(path), "--out", str(tmp_path / "r.usda")]
        if extra:
            argv[2:2] = ["--skeleton", str(capture), *extra]
        assert main(argv) == 2
        assert message in capsys.readouterr().err
    assert not (tmp_path / "r.usda").exists()


def test_api_and_info_embed_by_default(shared_assets):
    """rig_mesh embeds by default, as ``dqskin rig`` does (the whole-capture test above relies on
    it: MakeHuman's body is 12× the capture's size); ``as_is=True`` is ``--as-is``, refused with
    ``joints``; ``dqskin info X.bvh`` says so with the command line's flags."""
    import inspect

    from dqskin.cli import flag
    from dqskin.errors import InputError
    from dqskin.rigging import rig_mesh
    assert inspect.signature(rig_mesh).parameters["as_is"].default is False
    capture = shared_assets / "cmu-mocap" / "scaled_131_02.bvh"
    with pytest.raises(InputError, match=r"joints places .* as_is=True binds"):
        rig_mesh(shared_assets / "bodies" / "makehuman" / "base_body.obj", capture,
                 as_is=True, joints={"LeftElbow": [0, 0, 0]})
    line = bvh.summary_lines(bvh.read_bvh(capture), flag)[-1]
    assert "any size and pose is fitted by embedding" in line and "with --as-is a mesh must be" \
        in line and line.endswith("--scale"), line


def test_retargeted_rig_bakes_the_same_in_usdskel(walk):
    """UsdSkel.BakeSkinning of the written rig (bind rotations carrying the A-pose) equals
    dqskin's skinning of it, and has the body's arms down like the capture's."""
    from pxr import Gf, Sdf, Usd, UsdGeom, UsdSkel
    capture, body, rig, _ = walk
    stage = Usd.Stage.Open(Sdf.Layer.OpenAsAnonymous(str(rig)))
    assert UsdSkel.BakeSkinning(stage.Traverse(), Gf.Interval(0, 3))
    (prim,) = [p for p in stage.Traverse() if p.IsA(UsdGeom.Mesh)]
    attr = UsdGeom.Mesh(prim).GetPointsAttr()
    ref = np.stack([np.asarray(attr.Get(float(t)), np.float64) for t in range(4)])
    got = readers.load(rig).skin(np.arange(4.0), method="lbs", space="local")
    np.testing.assert_allclose(got.points[str(prim.GetPath())], ref,
                               atol=2e-5 * np.abs(ref).max())
    rest, _ = load_mesh(body)  # the A-pose's arms (9.9 dm apart) hang down as the capture's
    assert np.ptp(ref[0][:, 0]) < 0.7 * np.ptp(rest[:, 0]), np.ptp(ref[0][:, 0])


def test_scale_refusal_works_as_printed_over_a_given_scale(tmp_path, capsys, shared_assets):
    """--as-is with a wrong --scale: the suggested --scale replaces it and fits."""
    from test_autoweights import capsule_body
    capture = _short_capture(shared_assets / "cmu-mocap" / "scaled_131_02.bvh", tmp_path,
                             frames=3)
    motion = bvh.read_bvh(capture)
    pts, faces = capsule_body(motion.skeleton(), motion.end_sites, count=(6, 6))
    trimesh.Trimesh(pts * 10.0, faces, process=False).export(tmp_path / "dm.obj")  # decimetres
    argv = ["rig", str(tmp_path / "dm.obj"), "--skeleton", str(capture), "--as-is", "--out",
            str(tmp_path / "rig.usda"), "--scale"]
    assert main(argv + ["100"]) == 2
    suggested = re.search(r"--scale ([0-9.]+)", capsys.readouterr().err).group(1)
    assert float(suggested) == pytest.approx(10.0, rel=0.05)
    assert main(argv + [suggested]) == 0, capsys.readouterr().err
