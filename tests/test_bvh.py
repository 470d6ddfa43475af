"""BVH motion capture against an FK written here from the format: its own parser (a regex over
the text) and scipy's intrinsic Euler rotations, float64; on the shared CMU captures and on
generated files covering every rotation-channel order."""

import itertools
import re

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from dqskin.cli import main
from dqskin.readers import bvh, load

ORDERS = ["".join(p) for p in itertools.permutations("XYZ")]


def oracle(path):
    """Joint world rotations and positions of every frame, from the text alone: ``world =
    parent · [R(channels, intrinsic, in file order) | offset + positions]``."""
    text = open(path).read()
    head, motion = re.split(r"^\s*MOTION\s*$", text, flags=re.M)
    names, parents, offsets, chans, stack, last = [], [], [], [], [], None
    for m in re.finditer(r"(ROOT|JOINT)\s+(\S+)|End Site|OFFSET\s+(\S+)\s+(\S+)\s+(\S+)|"
                         r"CHANNELS\s+\d+((?:\s+[XYZ](?:position|rotation))*)|([{}])", head):
        if m.group(1):
            names.append(m.group(2))
            parents.append(stack[-1] if stack else -1)
            chans.append([])
            last = "joint"
        elif m.group(0) == "End Site":
            last = "site"
        elif m.group(3) and stack[-1] is not None and len(offsets) < len(names):
            offsets.append([float(m.group(k)) for k in (3, 4, 5)])
        elif m.group(6) is not None:
            chans[-1] = m.group(6).split()
        elif m.group(7) == "{":
            stack.append(len(names) - 1 if last == "joint" else None)
        elif m.group(7) == "}":
            stack.pop()
    rows = [r.split() for r in motion.strip().splitlines()[2:] if r.strip()]
    values = np.array(rows, dtype=np.float64)
    F, J = values.shape[0], len(names)
    rot, pos = np.zeros((F, J, 3, 3)), np.zeros((F, J, 3))
    col = 0
    for j in range(J):
        p = np.asarray(offsets[j]) + np.zeros((F, 3))
        order, angles = "", []
        for c in chans[j]:
            if c.endswith("position"):
                p[:, "XYZ".index(c[0])] += values[:, col]
            else:
                order += c[0]
                angles.append(values[:, col])
            col += 1
        r = (Rotation.from_euler(order, np.stack(angles, 1), degrees=True).as_matrix()
             if order else np.tile(np.eye(3), (F, 1, 1)))
        q = parents[j]
        if q < 0:
            rot[:, j], pos[:, j] = r, p
        else:
            rot[:, j] = rot[:, q] @ r
            pos[:, j] = pos[:, q] + np.einsum("fij,fj->fi", rot[:, q], p)
    return names, parents, rot, pos, values.shape[0]


def check_against_oracle(path, frames):
    names, parents, rot, pos, F = oracle(path)
    scene = load(path)
    skel = scene.skeletons[0]
    assert skel.joint_names == names
    assert list(skel.parents) == parents
    assert len(scene.times) == F
    world = skel.forward_kinematics(scene.local_transforms(frames))
    scale = 1.0 + np.abs(pos).max()
    np.testing.assert_allclose(world[..., :3, 3], pos[frames], atol=2e-5 * scale)
    np.testing.assert_allclose(world[..., :3, :3], rot[frames], atol=2e-5)
    # the bind pose is every channel at zero: joints at their summed offsets, unrotated
    offsets = _offsets(path)
    zero = np.zeros((len(names), 3))
    for j, p in enumerate(parents):
        zero[j] = offsets[j] + (zero[p] if p >= 0 else 0)
    np.testing.assert_allclose(skel.bind_transforms[:, :3, 3], zero, atol=1e-9)
    np.testing.assert_allclose(skel.bind_transforms[:, :3, :3], np.tile(np.eye(3), (len(names),
                                                                                   1, 1)))


def _offsets(path):
    """(J, 3) joint OFFSETs in declaration order, from the text (End Sites skipped)."""
    head = open(path).read().split("MOTION")[0]
    found = re.findall(r"(?:ROOT|JOINT)\s+\S+\s*\{\s*OFFSET\s+(\S+)\s+(\S+)\s+(\S+)", head)
    return np.array(found, dtype=np.float64)


@pytest.mark.parametrize("name", ["131_01.bvh", "scaled_131_02.bvh"])
def test_cmu_captures_match_independent_fk(shared_assets, name):
    path = shared_assets / "cmu-mocap" / name
    m = bvh.read_bvh(path)
    assert {"Zrotation Yrotation Xrotation", "Zrotation Xrotation Yrotation"} <= {
        " ".join(c) for c in m.channels}, "the captures mix channel orders"
    frames = np.array([0, 1, m.frame_count // 2, m.frame_count - 1])
    check_against_oracle(path, frames)
    scene = load(path)
    assert scene.time_codes_per_second == round(1 / m.frame_time)  # 0.0083333 s: 120 fps


def _write_generated(path, seed, frames=5, position_everywhere=False, positions_last=False):
    """A chain-and-branch skeleton whose joints use every rotation order (and position channels
    on the root, or on every joint; written before the rotations, or after them)."""
    rng = np.random.default_rng(seed)
    lines, channels = ["HIERARCHY"], []

    def joint(kind, name, depth, order, children):
        pad = "\t" * depth
        lines.append(f"{pad}{kind} {name}")
        lines.append(pad + "{")
        off = rng.uniform(-2, 2, 3)
        lines.append(f"{pad}\tOFFSET {off[0]:.6f} {off[1]:.6f} {off[2]:.6f}")
        pos = ([f"{a}position" for a in "XYZ"] if kind == "ROOT" or position_everywhere
               else [])
        rot = [f"{a}rotation" for a in order]
        ch = rot + pos if positions_last else pos + rot
        channels.extend(ch)
        lines.append(f"{pad}\tCHANNELS {len(ch)} {' '.join(ch)}")
        for child in children:
            child(depth + 1)
        if not children:
            lines.append(f"{pad}\tEnd Site")
            lines.append(pad + "\t{")
            lines.append(f"{pad}\t\tOFFSET 0.0 1.0 0.0")
            lines.append(pad + "\t}")
        lines.append(pad + "}")

    def chain(k, depth):
        if k == len(ORDERS):
            return
        joint("JOINT", f"j{k}", depth, ORDERS[k],
              [lambda d: chain(k + 1, d)] + ([lambda d: joint("JOINT", f"side{k}", d,
                                                               ORDERS[-1 - k], [])]
                                             if k % 2 else []))

    joint("ROOT", "root", 0, "ZXY", [lambda d: chain(0, d)])
    values = rng.uniform(-180, 180, (frames, len(channels)))
    lines += ["MOTION", f"Frames: {frames}", "Frame Time: 0.04"]
    lines += [" ".join(f"{v:.5f}" for v in row) for row in values]
    path.write_text("\n".join(lines) + "\n")
    return path


@pytest.mark.parametrize("everywhere,last", [(False, False), (True, False), (True, True)])
def test_generated_every_rotation_order(tmp_path, everywhere, last):
    """Position channels written after the rotations still add to the offset (not rotated by
    the joint's own rotation): ``T(offset + positions) · R``."""
    path = _write_generated(tmp_path / "gen.bvh", seed=3 + everywhere,
                            position_everywhere=everywhere, positions_last=last)
    m = bvh.read_bvh(path)
    assert {"".join(c[0] for c in ch if c.endswith("rotation")) for ch in m.channels} >= set(
        ORDERS)
    check_against_oracle(path, np.arange(5))
    assert m.end_sites and all(np.allclose(o, [0, 1, 0]) for _, o in m.end_sites)


def test_hand_built_motion_uses_its_channels():
    """A BvhMotion built in code (no parser) reads its values column by column."""
    m = bvh.BvhMotion("hand.bvh", ["root", "arm"], np.array([-1, 0], np.int32),
                      np.array([[0.0, 0, 0], [1.0, 0, 0]]),
                      [("Xposition", "Yposition", "Zposition", "Zrotation"), ("Xrotation",)],
                      [], 0.1, np.array([[1.0, 2.0, 3.0, 90.0, 90.0]]))
    loc = m.local_transforms()[0]
    np.testing.assert_allclose(loc[0, :3, 3], [1, 2, 3])
    np.testing.assert_allclose(loc[0, :3, :3], Rotation.from_euler("z", 90, degrees=True)
                               .as_matrix(), atol=1e-12)
    np.testing.assert_allclose(loc[1, :3, :3], Rotation.from_euler("x", 90, degrees=True)
                               .as_matrix(), atol=1e-12)
    with pytest.raises(ValueError, match="hand.bvh.*one column per channel"):
        bvh.BvhMotion("hand.bvh", ["root"], np.array([-1]), np.zeros((1, 3)), [("Xrotation",)],
                      [], 0.1, np.zeros((1, 2)))


def test_between_frames_slerp_and_lerp(tmp_path):
    path = _write_generated(tmp_path / "gen.bvh", seed=5, frames=2)
    scene = load(path)
    loc = scene.local_transforms([0.0, 0.25, 1.0])
    np.testing.assert_allclose(loc[1, :, :3, 3], 0.75 * loc[0, :, :3, 3] + 0.25 * loc[2, :, :3, 3],
                               atol=1e-9)
    r0, r1 = Rotation.from_matrix(loc[0, :, :3, :3]), Rotation.from_matrix(loc[2, :, :3, :3])
    rel = (r0.inv() * r1).as_rotvec()
    expect = (r0 * Rotation.from_rotvec(0.25 * rel)).as_matrix()
    np.testing.assert_allclose(loc[1, :, :3, :3], expect, atol=1e-9)


def test_scaled_scales_lengths_only(tmp_path):
    path = _write_generated(tmp_path / "gen.bvh", seed=7, position_everywhere=True,
                            positions_last=True)
    m = bvh.read_bvh(path)
    s = bvh.scaled(m, 2.5)
    a, b = m.local_transforms(), s.local_transforms()
    np.testing.assert_allclose(b[..., :3, :3], a[..., :3, :3])
    np.testing.assert_allclose(b[..., :3, 3], 2.5 * a[..., :3, 3])
    with pytest.raises(ValueError, match=r"^scale=0\.0: must be a positive"):
        bvh.scaled(m, 0)


MALFORMED = [
    ("HELLO\n", "not a BVH file"),
    ("HIERARCHY\nROOT a\n{\nOFFSET 0 0 0\nCHANNELS 1 Xrotation\n}\n", "no MOTION"),
    ("HIERARCHY\nROOT a\n{\nOFFSET 0 0 0\nCHANNELS 1 Wrotation\n}\nMOTION\nFrames: 1\n"
     "Frame Time: 0.1\n0\n", "line 5: joint 'a': unknown channel 'Wrotation'"),
    ("HIERARCHY\nROOT a\n{\nOFFSET 0 zero 0\n}\nMOTION\nFrames: 1\nFrame Time: 0.1\n\n",
     "line 4: expected a number for OFFSET"),
    ("HIERARCHY\nROOT a\n{\nOFFSET 0 0 0\nCHANNELS 2 Xrotation Yrotation\n}\nMOTION\nFrames: 2\n"
     "Frame Time: 0.1\n1 2\n3\n", "line 11: frame 1 has 1 values, expected 2"),
    ("HIERARCHY\nROOT a\n{\nOFFSET 0 0 0\nCHANNELS 1 Xrotation\n}\nMOTION\nFrames: 3\n"
     "Frame Time: 0.1\n1\n2\n", "Frames: 3 but only 2 frame lines"),
    ("HIERARCHY\nROOT a\n{\nOFFSET 0 0 0\nCHANNELS 1 Xrotation\n}\nMOTION\nFrames: 1\n"
     "Frame Time: 0\n1\n", "Frame Time: '0': expected seconds per frame, at least 1e-06"),
    ("HIERARCHY\nROOT a\n{\nOFFSET 0 0 0\nCHANNELS 1 Xrotation\n}\nMOTION\nFrame Time: 0.1\n",
     "expected 'Frames: N'"),
    ("HIERARCHY\nROOT a\n{\nOFFSET 0 0 0\nCHANNELS 1 Xrotation\nJOINT a\n{\nOFFSET 0 0 0\n}\n}\n"
     "MOTION\nFrames: 1\nFrame Time: 0.1\n1\n", "duplicate joint name 'a'"),
    ("HIERARCHY\nROOT a\n{\nOFFSET 0 0 0\nCHANNELS 1 Xrotation\n", "no MOTION"),
    ("HIERARCHY\nROOT a\n{\nOFFSET 0 0 0\nCHANNELS 1 Xrotation\nMOTION\nFrames: 1\n"
     "Frame Time: 0.1\n1\n", "unexpected end of file"),
    ("HIERARCHY\nROOT a\n{\nOFFSET 0 0 0\nCHANNELS 1 Xrotation\n}\nMOTION\nFrames: 1\n"
     "Frame Time: 0.1\nnan\n", "not finite"),
]


@pytest.mark.parametrize("text,message", MALFORMED)
def test_malformed_files_name_file_and_line(tmp_path, text, message):
    path = tmp_path / "bad.bvh"
    path.write_text(text)
    with pytest.raises(ValueError, match=re.escape(message)) as err:
        bvh.read_bvh(path)
    assert str(path) in str(err.value)


def test_cli_info_and_error(tmp_path, capsys):
    path = _write_generated(tmp_path / "gen.bvh", seed=1)
    assert main(["info", str(path)]) == 0
    out = capsys.readouterr().out
    assert "7 samples" not in out and "5 samples" in out and "time codes @ 25/s" in out
    assert "j5" in out and "side3" in out and "problems: none" in out
    assert "End Sites, 5 frames of 0.04 s" in out and "rotation orders" in out
    assert "XYZ ×" in out and "ZYX ×" in out and "rest skeleton:" in out
    assert "--scale" in out  # the command line's spelling of the rig's scale
    bad = tmp_path / "bad.bvh"
    bad.write_text(MALFORMED[2][0])
    assert main(["info", str(bad)]) == 2
    assert "unknown channel" in capsys.readouterr().err


def test_summary_names_the_scale_parameter_as_the_caller_spells_it(tmp_path):
    """The size line names rig_mesh's ``scale`` (from Python) or the CLI's ``--scale`` flag."""
    from dqskin.cli import flag
    motion = bvh.read_bvh(_write_generated(tmp_path / "gen.bvh", seed=1))
    assert bvh.summary_lines(motion)[-1].endswith("or be matched with scale")
    assert bvh.summary_lines(motion, flag)[-1].endswith("or be matched with --scale")


def test_seeded_corruptions_give_value_errors_only(shared_assets, tmp_path):
    """Truncations, dropped, swapped and garbled words of a real capture: each either loads or
    raises ValueError naming the file, never another exception."""
    text = (shared_assets / "cmu-mocap" / "131_01.bvh").read_text()
    lines = text.splitlines()
    at = lines.index("MOTION")
    base = lines[:at + 1] + ["Frames: 3", lines[at + 2]] + lines[at + 3:at + 6]
    words = "\n".join(base).split(" ")
    rng = np.random.default_rng(14)
    path = tmp_path / "fuzz.bvh"
    outcomes = {"loaded": 0, "refused": 0}
    for trial in range(60):
        w = list(words)
        for _ in range(rng.integers(1, 4)):
            i = int(rng.integers(len(w)))
            kind = rng.integers(4)
            if kind == 0:
                w = w[:i]
            elif kind == 1:
                del w[i]
            elif kind == 2:
                w[i] = rng.choice(["nan", "{", "}", "JOINT", "-", "1e999", "CHANNELS", "ROOT"])
            else:
                w.insert(i, w[int(rng.integers(len(w)))])
        path.write_text(" ".join(w))
        try:
            scene = load(path)
            scene.local_transforms(scene.times[:1])
            outcomes["loaded"] += 1
        except ValueError as exc:
            assert str(path) in str(exc), exc
            outcomes["refused"] += 1
    assert outcomes["refused"] > 10, outcomes
