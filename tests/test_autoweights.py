"""Automatic (bone-heat) weights: partition of unity, non-negativity, sparsity, locality, mirror
symmetry on a symmetric mesh, the cache, and the real characters' skinned positions against their
artists' weights, measured against Blender 5.0's automatic weights (the anchors of issue 14)."""

import dataclasses
from pathlib import Path

import numpy as np
import pytest
import trimesh
from scipy.spatial import cKDTree

from dqskin import Scene, Skeleton, autoweights, cache, readers
from dqskin.autoweights import automatic_weights, bone_heat_weights, bone_segments, sparsify
from dqskin.rigging import replace_weights


def capsule_body(skeleton, end_sites=None, *, radius=0.18, count=(12, 12), subdivide=0):
    """A mesh in the skeleton's rest pose: one capsule around every bone segment (radius a
    share of the bone's length, capped by the longest bone's), concatenated."""
    heads, tails, _ = bone_segments(skeleton, end_sites=end_sites)
    longest = np.linalg.norm(tails - heads, axis=1).max()
    parts = []
    for h, t in zip(heads, tails):
        length = np.linalg.norm(t - h)
        if length < 1e-6 * longest:
            continue
        r = min(radius * length, 0.12 * longest)
        c = trimesh.creation.capsule(height=length, radius=r, count=list(count))
        for _ in range(subdivide):
            c = c.subdivide()
        c.apply_transform(trimesh.geometry.align_vectors([0, 0, 1], (t - h) / length))
        c.apply_translation(0.5 * (h + t))
        parts.append(c)
    mesh = trimesh.util.concatenate(parts)
    return np.asarray(mesh.vertices, np.float32), np.asarray(mesh.faces, np.int32)


def arm_span():
    """A symmetric skeleton along x (root, then left and right chains of two bones) and a
    closed, connected, mirror-symmetric tube around it."""
    names = ["root", "l_upper", "l_lower", "r_upper", "r_lower"]
    parents = [-1, 0, 1, 0, 3]
    pos = np.array([[0, 0, 0], [0.2, 0, 0], [1.0, 0, 0], [-0.2, 0, 0], [-1.0, 0, 0]], float)
    bind = np.tile(np.eye(4), (5, 1, 1))
    bind[:, :3, 3] = pos
    skel = Skeleton(names, parents, bind)
    rings, around = 49, 20
    x = np.linspace(-1.6, 1.6, rings)
    a = np.linspace(0, 2 * np.pi, around, endpoint=False)
    pts = np.concatenate([np.stack([np.repeat(x, around), 0.15 * np.tile(np.cos(a), rings),
                                    0.15 * np.tile(np.sin(a), rings)], 1),
                          [[-1.6, 0, 0], [1.6, 0, 0]]])
    faces = []
    for k in range(rings - 1):  # quads split by mirror-image diagonals on the two halves
        for i in range(around):
            p, q = k * around + i, k * around + (i + 1) % around
            r, s = p + around, q + around
            faces += [[p, q, s], [p, s, r]] if k < (rings - 1) // 2 else [[p, q, r], [q, s, r]]
    end = rings * around
    for i in range(around):  # caps
        faces.append([end, (i + 1) % around, i])
        last = (rings - 1) * around
        faces.append([end + 1, last + i, last + (i + 1) % around])
    return skel, pts, np.array(faces)


def dense(idx, w, J):
    out = np.zeros((idx.shape[0], J))
    np.add.at(out, (np.arange(idx.shape[0])[:, None], idx), w)
    return out


@pytest.fixture(scope="module")
def arm():
    skel, pts, faces = arm_span()
    idx, w = automatic_weights(pts, faces, skel, cache=False, max_influences=4)
    return skel, pts, faces, idx, w


def test_first_calls_from_threads_load_the_kernel_module_once(tmp_path):
    """Four threads making a fresh process's first ``automatic_weights`` calls at the same
    moment: no thread loads the bone-heat kernel module while another is loading it (the
    launcher had loaded it outside the first-launch lock: a segfault in 3 runs of 4), and every
    thread gets the single-threaded result. Cold module loads are slowed here so that overlapping
    ones are certain to be seen."""
    import subprocess
    import sys
    script = """if True:
        import threading, time, traceback
        import numpy as np
        import trimesh
        import warp as wp
        import warp._src.context as context
        wp.config.log_level = wp.LOG_ERROR
        real, guard, inside, overlaps = context.Module.load, threading.Lock(), {}, []
        def load(self, *args, **kwargs):
            cold = not self.execs
            if cold:
                with guard:
                    if inside.get(self.name):
                        overlaps.append(self.name)
                    inside[self.name] = inside.get(self.name, 0) + 1
                time.sleep(0.2)
            try:
                return real(self, *args, **kwargs)
            finally:
                if cold:
                    with guard:
                        inside[self.name] -= 1
        context.Module.load = load
        import dqskin
        mesh = trimesh.creation.capsule(height=2.0, radius=0.3, count=[8, 8])
        bind = np.tile(np.eye(4), (3, 1, 1))
        bind[:, 2, 3] = [-1.0, 0.0, 1.0]
        skel = dqskin.Skeleton(["a", "b", "c"], [-1, 0, 1], bind)
        barrier, results, errors = threading.Barrier(4), [], []
        def work():
            barrier.wait()
            try:
                results.append(dqskin.automatic_weights(mesh.vertices, mesh.faces, skel,
                                                        cache=False))
            except Exception:
                errors.append(traceback.format_exc())
        threads = [threading.Thread(target=work) for _ in range(4)]
        for t in threads: t.start()
        for t in threads: t.join()
        ref = dqskin.automatic_weights(mesh.vertices, mesh.faces, skel, cache=False)
        same = all(np.array_equal(r[0], ref[0]) and np.array_equal(r[1], ref[1])
                   for r in results)
        print("OVERLAPS", sorted(set(overlaps)), "ERRORS", len(errors), "SAME", same)
        print(errors[0] if errors else "")
    """
    proc = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True,
                          timeout=300, cwd=tmp_path)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    assert "OVERLAPS [] ERRORS 0 SAME True" in proc.stdout, proc.stdout


def test_partition_of_unity_sparse_non_negative(arm):
    skel, pts, faces, idx, w = arm
    assert idx.shape == (len(pts), 4) and w.dtype == np.float32 and idx.dtype == np.int32
    assert np.all(w >= 0)
    np.testing.assert_allclose(w.sum(1), 1.0, atol=1e-6)
    assert np.all(np.diff(w, axis=1) <= 0), "largest first"
    assert idx.min() >= 0 and idx.max() < skel.joint_count


def test_locality_limb_vertices_follow_their_limb(arm):
    skel, pts, faces, idx, w = arm
    W = dense(idx, w, skel.joint_count)
    x = pts[:, 0]
    # the outer part of each forearm belongs to its lower bone, the upper arm to its own bone,
    # the middle to the root
    assert np.all(W[x > 1.3, 2] > 0.9) and np.all(W[x < -1.3, 4] > 0.9)
    assert np.all(W[(x > 0.4) & (x < 0.8), 1] > 0.8)
    assert np.all(W[np.abs(x) < 0.05, 0] > 0.5)
    left = x > 0.5
    assert np.all(W[left][:, [3, 4]] < 5e-3), "(almost) no weight crosses to the other arm"
    # monotone along the limb: the lower bone's weight grows outwards
    order = np.argsort(x[left])
    smooth = np.convolve(W[left][order, 2], np.ones(25) / 25, mode="valid")
    assert np.all(np.diff(smooth) > -1e-3)


def test_mirror_symmetry(arm):
    skel, pts, faces, idx, w = arm
    W = dense(idx, w, skel.joint_count)
    mirror = pts * [-1, 1, 1]
    dist, partner = cKDTree(pts).query(mirror)
    assert dist.max() < 1e-9, "the tube is mirror-symmetric"
    swap = [0, 3, 4, 1, 2]
    np.testing.assert_allclose(W[partner][:, swap], W, atol=2e-3)


def test_scale_free_and_unit_independent(arm):
    skel, pts, faces, idx, w = arm
    s = 39.37  # metres → inches
    bind = skel.bind_transforms.copy()
    bind[:, :3, 3] *= s
    big = Skeleton(skel.joint_names, skel.parents, bind)
    i2, w2 = automatic_weights(pts * s, faces, big, cache=False, max_influences=4)
    np.testing.assert_allclose(dense(i2, w2, 5), dense(idx, w, 5), atol=1e-3)  # (ties of tiny)


def test_hidden_bone_gives_no_heat():
    """A thick tube beside a thin one: the thin tube's bone is nearer to the facing side of the
    thick tube than the thick tube's own bone, but hidden behind the thin tube's surface. With
    visibility (Baran & Popović) the thick tube follows only its own bone; without, its facing
    side would follow the thin tube's."""
    a = trimesh.creation.cylinder(radius=0.3, height=1.0, sections=32).subdivide_to_size(0.08)
    b = trimesh.creation.cylinder(radius=0.05, height=1.0, sections=12).subdivide_to_size(0.08)
    b.apply_translation([0.37, 0, 0])
    m = trimesh.util.concatenate([a, b])
    heads = np.array([[0.0, 0, -0.5], [0.37, 0, -0.5]])
    tails = heads + [0, 0, 1.0]
    on_a = np.arange(len(m.vertices)) < len(a.vertices)
    for visibility in (True, False):
        idx, w = bone_heat_weights(m.vertices, m.faces, heads, tails, [0, 1], 2,
                                   visibility=visibility)
        W = dense(idx, w, 2)
        assert np.all(W[~on_a, 1] > 0.999)
        if visibility:
            assert np.all(W[on_a, 0] > 0.99)
        else:
            assert np.any(W[on_a, 1] > 0.5)


def test_points_without_faces_take_the_nearest_bone():
    pts = np.array([[0.1, 0, 0], [0.9, 0.1, 0], [2.0, 0, 0]])
    idx, w = bone_heat_weights(pts, np.zeros((0, 3), int), [[0, 0, 0], [1, 0, 0]],
                               [[0.5, 0, 0], [2, 0, 0]], [0, 1], 2)
    assert idx[:, 0].tolist() == [0, 1, 1] and np.all(w[:, 0] == 1)


def test_sparsify_keeps_largest_and_renormalizes():
    w = np.array([[0.1, 0.5, 0.2, 0.2, -0.1], [0, 0, 0, 0, 0]])
    idx, ww = sparsify(w, 2)
    assert idx[0].tolist() == [1, 2] or idx[0].tolist() == [1, 3]
    np.testing.assert_allclose(ww[0], [0.5 / 0.7, 0.2 / 0.7], rtol=1e-6)
    assert ww[1].tolist() == [1, 0]


def test_bad_input_is_named():
    with pytest.raises(ValueError, match="points"):
        bone_heat_weights(np.zeros((0, 3)), np.zeros((0, 3), int), [[0, 0, 0]], [[1, 0, 0]],
                          [0], 1)
    with pytest.raises(ValueError, match="faces"):
        bone_heat_weights(np.zeros((3, 3)), [[0, 1, 5]], [[0, 0, 0]], [[1, 0, 0]], [0], 1)
    with pytest.raises(ValueError, match="joint index out of range"):
        bone_heat_weights(np.zeros((3, 3)), [[0, 1, 2]], [[0, 0, 0]], [[1, 0, 0]], [3], 1)


def test_tests_never_use_the_users_cache():
    """tests/conftest.py points every test at a temporary cache folder."""
    home = Path.home() / ".cache"
    assert home not in cache.cache_dir().parents and cache.cache_dir() != home / "dqskin"


def test_cache_reused_and_keyed_by_inputs(tmp_path, monkeypatch):
    monkeypatch.setenv("DQSKIN_CACHE_DIR", str(tmp_path))
    skel, pts, faces = arm_span()
    first = automatic_weights(pts, faces, skel)
    files = list((tmp_path / "weights").glob("*.npz"))
    assert len(files) == 1 and cache.cache_dir() == tmp_path
    whole = files[0].read_bytes()

    def boom(*a, **k):
        raise AssertionError("recomputed despite a cached result")

    monkeypatch.setattr(autoweights, "bone_heat_weights", boom)
    again = automatic_weights(pts, faces, skel)
    np.testing.assert_array_equal(again[1], first[1])
    with pytest.raises(AssertionError, match="recomputed"):  # moved points: a new key
        automatic_weights(pts + [0, 0.01, 0], faces, skel)
    with pytest.raises(AssertionError, match="recomputed"):  # other influence count
        automatic_weights(pts, faces, skel, max_influences=2)
    monkeypatch.undo()
    monkeypatch.setenv("DQSKIN_CACHE_DIR", str(tmp_path))
    idx, w = first
    damaged = {  # each is a miss: computed again and replaced, never an exception
        "corrupt": b"corrupt", "empty": b"", "truncated": whole[:len(whole) // 2],
        "cut at the end": whole[:-10]}
    for what, data in damaged.items():
        files[0].write_bytes(data)
        got = automatic_weights(pts, faces, skel)
        np.testing.assert_array_equal(got[1], w, err_msg=what)
        assert files[0].read_bytes() == whole, what
    misfits = {"too few rows": (idx[:-1], w[:-1]), "float indices": (idx.astype(float), w),
               "float64 weights": (idx, w.astype(np.float64)),
               "index out of range": (idx + 5, w), "nan weight": (idx, np.full_like(w, np.nan))}
    for what, (a, b) in misfits.items():
        np.savez(files[0], joint_indices=a, joint_weights=b)
        got = automatic_weights(pts, faces, skel)
        np.testing.assert_array_equal(got[0], idx, err_msg=what)
        np.testing.assert_array_equal(got[1], w, err_msg=what)
    assert sorted(p.name for p in (tmp_path / "weights").iterdir()) == sorted(
        p.name for p in files), "no temporary file left"


def test_only_joints_owning_a_bone_are_solved(monkeypatch):
    """Joints without a bone (here: a non-deforming root, and an unused extra joint) take no
    right-hand side in the solve and get no weight."""
    import scipy.sparse.linalg as sla
    columns = []
    real = sla.splu

    class Spy:
        def __init__(self, a):
            self.lu = real(a)

        def solve(self, b):
            columns.append(b.shape[1])
            return self.lu.solve(b)

    monkeypatch.setattr(sla, "splu", Spy)
    skel, pts, faces = arm_span()
    heads, tails, owners = bone_segments(skel, joints=[1, 2, 3, 4])
    idx, w = bone_heat_weights(pts, faces, heads, tails, owners, 7, max_influences=4)
    assert columns == [4]
    assert set(np.unique(idx[w > 0])) <= {1, 2, 3, 4}


@pytest.mark.parametrize("bad", [0, -1, 2.5])
def test_max_influences_refused_before_the_solve(monkeypatch, bad):
    monkeypatch.setattr(autoweights, "_heat_sources", lambda *a, **k: 1 / 0)
    skel, pts, faces = arm_span()
    with pytest.raises(ValueError, match="max_influences"):
        automatic_weights(pts, faces, skel, max_influences=bad, cache=False)
    heads, tails, owners = bone_segments(skel)
    with pytest.raises(ValueError, match="max_influences"):
        bone_heat_weights(pts, faces, heads, tails, owners, 5, max_influences=bad)


# Blender automatic weights vs the artist's, first clip, worst frame: mean and 95th percentile of
# the skinned-position error, % of vertical height. The lowest of Blender's figures for each
# (issue 14: 5.0, bones pointed at their children; issue 31: 5.0.1's best configuration).
BLENDER = {"CesiumMan": (0.58, 1.25), "RiggedFigure": (0.27, 1.22)}


@pytest.mark.parametrize("name", sorted(BLENDER))
@pytest.mark.parametrize("source", ["khronos-gltf", "usd-wg"])
def test_real_characters_match_blender_or_better(shared_assets, name, source):
    suffix = ".glb" if source == "khronos-gltf" else ".usdz"
    scene = readers.load(shared_assets / source / name / f"{name}{suffix}")
    auto = replace_weights(scene, "auto", cache=False)
    # 24 frames a second, as Blender plays it (times are seconds in glTF, time codes in USD)
    step = scene.time_codes_per_second / 24
    frames = np.arange(scene.times[0], scene.times[-1] + 1e-9, step)
    assert len(frames) < 100, len(frames)  # both characters' first clips are about 2 s
    for m, a in zip(scene.meshes, auto.meshes):
        one = dataclasses.replace(scene, meshes=[m], _skinners={})
        other = dataclasses.replace(auto, meshes=[a], _skinners={})
        ref = one.skin(frames, method="lbs", space="skeleton").points[m.name].astype(np.float64)
        got = other.skin(frames, method="lbs", space="skeleton").points[m.name].astype(np.float64)
        g = m.geom_bind_transform
        rest = np.asarray(m.points, np.float64) @ g[:3, :3].T + g[:3, 3]
        assert np.argmax(np.ptp(rest, axis=0)) == 2  # standing along Z: the height is vertical
        err = np.linalg.norm(ref - got, axis=-1) / np.ptp(rest[:, 2]) * 100
        mean, p95 = err.mean(1).max(), np.percentile(err, 95, axis=1).max()
        print(f"{name} {m.name}: mean {mean:.3f}%, 95th percentile {p95:.3f}% of vertical "
              "height")
        assert mean <= BLENDER[name][0] and p95 <= BLENDER[name][1]
    assert isinstance(auto, Scene)


def test_leaf_bones_point_into_the_region_they_own():
    """A head that juts forward from its neck (a snout): its leaf bone points along the snout,
    not on along the neck, and the snout's tip takes the head's weight."""
    neck = trimesh.creation.box(extents=[0.2, 1.0, 0.2])
    neck.apply_translation([0, 0.5, 0])
    snout = trimesh.creation.box(extents=[0.3, 0.3, 1.2])
    snout.apply_translation([0, 1.1, 0.45])
    body = trimesh.util.concatenate([neck, snout]).subdivide().subdivide()
    bind = np.tile(np.eye(4), (2, 1, 1))
    bind[1, :3, 3] = [0, 1.0, 0]
    skel = Skeleton(["neck", "head"], [-1, 0], bind)
    heads, tails, owners = bone_segments(skel, points=body.vertices)
    d = tails[owners == 1][0] - heads[owners == 1][0]
    assert d[2] > 2 * abs(d[1]), d  # along +Z, the snout
    along, _, _ = bone_segments(skel)
    assert np.allclose(along[owners == 1], heads[owners == 1])  # (no mesh: along the neck)
    idx, w = automatic_weights(body.vertices, body.faces, skel, cache=False)
    tip = body.vertices[:, 2] > 0.9
    head_w = np.where(idx == 1, w, 0).sum(1)
    assert head_w[tip].min() > 0.99
