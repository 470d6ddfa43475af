"""Side-by-side benchmark: dqskin vs UsdSkel (C++) vs vectorized NumPy, same data, one run.

    python tools/bench.py [--sizes 10000,100000,1000000] [--json out/bench.json] [--quick]

Skinning: random rigid rigs, 4 influences, 64 joints, float32; each implementation skins the same
points with the same transforms; per-call time is the best over ``--repeat`` rounds of the mean of
a burst of back-to-back calls. dqskin times include uploading the
frame's transforms, preparing them and reading the result back (the mesh is uploaded once, as a
pipeline would); "one-shot" is ``dqskin.skin_points`` (validation, influence layout and upload
of the mesh included, as ``UsdSkel.SkinPoints`` converts its inputs every call). Kernels alone
(:func:`bench_kernels`): one thread, dqskin's point kernels against minimal LBS/DQS kernels.
FK: 1,000 skeletons × 64 joints. Crowds (:func:`bench_crowd`): 100 and 1,000 CesiumMen (glTF, from
../shared; the bundled humanoid without it) against one mesh of the same total points. Sign rules
(:func:`bench_sign_rules`): DQS with Blender's running sum against UsdSkel's rule on a
598,959-point CesiumMan tiling. The one-shot and crowd ratios are also measured from calls
alternated one by one (:func:`paired_ratios`), and every round records the minor page faults per
call and the CPU other processes took meanwhile (:func:`machine_cpu`), in the JSON and the
tables. Prints tables and writes JSON.
"""

import argparse
import json
import os
import platform
import sys
import time
from pathlib import Path

import numpy as np
import warp as wp
from pxr import Gf, UsdSkel, Vt
from scipy.spatial.transform import Rotation

import dqskin
from dqskin.kernels.dqmath import dq_blend_add, mat34, vec8
from dqskin.kernels.skin import dqs_apply
from dqskin.skeleton import forward_kinematics

JOINTS, INFLUENCES = 64, 4


def machine_cpu():
    """``(CPU seconds of the whole machine, of this process, minor page faults of this process)``
    so far (the machine's from Linux's /proc/stat, the faults from ``resource``; None where
    missing): their differences over a round say how much of it other processes took and how
    much memory it touched first."""
    try:
        import resource
        faults = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
    except ImportError:
        faults = None
    try:
        with open("/proc/stat") as f:
            ticks = [int(x) for x in f.readline().split()[1:8]]
        busy = (ticks[0] + ticks[1] + ticks[2] + ticks[5] + ticks[6]) / os.sysconf("SC_CLK_TCK")
    except (OSError, ValueError, IndexError, AttributeError):
        busy = None
    return busy, time.process_time(), faults


def others_cores(busy0, busy1, own, wall):
    """CPU cores other processes took over ``wall`` seconds, from two :func:`machine_cpu`
    readings of the machine (``busy0``, ``busy1``) and this process's CPU seconds ``own``
    meanwhile; None when unknown or when ``wall`` is under 0.2 s (the machine's count moves in
    ticks of 10 ms)."""
    if busy0 is None or wall < 0.2:
        return None
    return ((busy1 - busy0) - own) / wall


def best_times(fns, repeat, burst_seconds=0.1, rounds=None):
    """Per-call wall time of each callable: the best over ``repeat`` rounds of the mean of a burst
    of back-to-back calls (about ``burst_seconds`` long, so steady state, as in a pipeline).
    Rounds are interleaved so machine noise hits every implementation alike, with a pause before
    each burst so the previous implementation's worker threads (TBB, BLAS) go idle. ``rounds``:
    a dict that receives each callable's per-round records: ``seconds`` per call, ``faults``
    (minor page faults per call), ``others`` (CPU seconds other processes used per second of
    the round: 1.0 is one core taken)."""
    bursts = {}
    for name, fn in fns.items():
        fn()  # warm-up (kernel load, caches)
        t0 = time.perf_counter()
        fn()
        bursts[name] = max(1, min(50, int(burst_seconds / max(time.perf_counter() - t0, 1e-6))))
    best = dict.fromkeys(fns, float("inf"))
    for _ in range(repeat):
        for name, fn in fns.items():
            time.sleep(0.3)
            busy0, own0, faults0 = machine_cpu()
            t0 = time.perf_counter()
            for _ in range(bursts[name]):
                fn()
            wall = time.perf_counter() - t0
            busy1, own1, faults1 = machine_cpu()
            per_call = wall / bursts[name]
            best[name] = min(best[name], per_call)
            if rounds is not None:
                rec = rounds.setdefault(name, {"seconds": [], "faults": [], "others": []})
                rec["seconds"].append(per_call)
                rec["faults"].append(None if faults0 is None else
                                     (faults1 - faults0) / bursts[name])
                rec["others"].append(others_cores(busy0, busy1, own1 - own0, wall))
    return best


def paired_ratios(base, other, repeat, round_seconds=1.0):
    """Per-round ``other`` ÷ ``base`` time from calls alternated within each round (A B B A A B
    ...: a call of each, then the other order, so both see the same share of the machine when
    other processes come and go): ``repeat`` rounds of about ``round_seconds``, a pause before
    each. Returns ``{"ratio": [...], "others": [...]}`` (other processes' CPU seconds per
    second of the round, as :func:`best_times`)."""
    base(), other()
    t0 = time.perf_counter()
    base(), other()
    pairs = max(1, int(round_seconds / max(time.perf_counter() - t0, 1e-6)))
    out = {"ratio": [], "others": []}
    for _ in range(repeat):
        time.sleep(0.3)
        spent = [0.0, 0.0]
        busy0, own0, _ = machine_cpu()
        w0 = time.perf_counter()
        for k in range(pairs):
            for i in ((0, 1) if k % 2 == 0 else (1, 0)):
                t0 = time.perf_counter()
                (base, other)[i]()
                spent[i] += time.perf_counter() - t0
        wall = time.perf_counter() - w0
        busy1, own1, _ = machine_cpu()
        out["ratio"].append(spent[1] / spent[0])
        out["others"].append(others_cores(busy0, busy1, own1 - own0, wall))
    return out


def make_rig(rng, V):
    points = rng.normal(size=(V, 3)).astype(np.float32)
    idx = rng.integers(0, JOINTS, size=(V, INFLUENCES)).astype(np.int32)
    w = rng.random((V, INFLUENCES)).astype(np.float32)
    w /= w.sum(1, keepdims=True)
    M = np.tile(np.eye(4), (JOINTS, 1, 1))
    M[:, :3, :3] = Rotation.random(JOINTS, random_state=rng).as_matrix()
    M[:, :3, 3] = rng.normal(size=(JOINTS, 3))
    return points, idx, w, M


def numpy_lbs(points, idx, w, M):
    A = M[:, :3, :].astype(np.float32)
    blended = np.einsum("vk,vkij->vij", w, A[idx])
    return np.einsum("vij,vj->vi", blended[:, :, :3], points) + blended[:, :, 3]


def numpy_dqs(points, idx, w, M):
    q = Rotation.from_matrix(M[:, :3, :3]).as_quat().astype(np.float32)  # (x, y, z, w)
    t = M[:, :3, 3].astype(np.float32)
    # dual part d = ½·t·q, as (x, y, z, w)
    dv = 0.5 * (q[:, 3:] * t + np.cross(t, q[:, :3]))
    dw = -0.5 * np.sum(t * q[:, :3], 1, keepdims=True)
    d = np.concatenate([dv, dw], 1)
    qr, qd = q[idx], d[idx]
    pivot = qr[np.arange(len(idx)), np.argmax(w, 1)]
    s = np.where(np.einsum("vki,vi->vk", qr, pivot) < 0, -w, w)
    r = np.einsum("vk,vki->vi", s, qr)
    e = np.einsum("vk,vki->vi", s, qd)
    rv, rw, ev, ew = r[:, :3], r[:, 3:], e[:, :3], e[:, 3:]
    inv = 2.0 / np.sum(r * r, 1, keepdims=True)
    return points + inv * (np.cross(rv, np.cross(rv, points) + rw * points)
                           + rw * ev - ew * rv + np.cross(rv, ev))


def bench_skinning(sizes, repeat, devices, rows):
    rng = np.random.default_rng(0)
    for V in sizes:
        points, idx, w, M = make_rig(rng, V)
        rep = repeat
        xf = Vt.Matrix4dArray.FromNumpy(np.ascontiguousarray(M.transpose(0, 2, 1)))
        vi, vw = Vt.IntArray.FromNumpy(idx.ravel()), Vt.FloatArray.FromNumpy(w.ravel())
        for method, token in (("lbs", "classicLinear"), ("dqs", "dualQuaternion")):
            fns = {}
            for dev in devices:
                sk = dqskin.Skinner(points, idx, w, device=dev)
                fns[f"dqskin {dev}"] = (lambda sk=sk: (sk.skin(M, method), wp.synchronize()))
                fns[f"dqskin {dev} one-shot"] = (lambda dev=dev: (
                    dqskin.skin_points(points, idx, w, M, method, device=dev), wp.synchronize()))
            src = Vt.Vec3fArray.FromNumpy(points)
            for serial in (True, False):
                def usd(serial=serial):
                    p = Vt.Vec3fArray(src)
                    UsdSkel.SkinPoints(token, Gf.Matrix4d(1), xf, vi, vw, INFLUENCES, p, serial)
                fns["UsdSkel " + ("serial" if serial else "parallel")] = usd
            oracle = numpy_lbs if method == "lbs" else numpy_dqs
            fns["NumPy"] = lambda oracle=oracle: oracle(points, idx, w, M)
            per_round = {}
            res = best_times(fns, rep, rounds=per_round)
            paired = {f"dqskin {dev} one-shot": paired_ratios(fns[f"dqskin {dev}"],
                                                              fns[f"dqskin {dev} one-shot"], rep)
                      for dev in devices}
            for impl, t in res.items():
                extra = {f"paired_{k}": v for k, v in paired[impl].items()} \
                    if impl in paired else {}
                rows.append(dict(kind="skin", method=method, vertices=V, impl=impl, seconds=t,
                                 mpts_per_s=V / t / 1e6, **extra,
                                 **{f"round_{k}": v for k, v in per_round[impl].items()}))


@wp.kernel
def minimal_lbs_kernel(points: wp.array(dtype=wp.vec3), idx: wp.array(dtype=wp.vec4i),
                       wts: wp.array(dtype=wp.vec4), affines: wp.array(dtype=mat34),
                       out: wp.array(dtype=wp.vec3)):
    """The reference of item 3: LBS of one frame, 4 influences, nothing else (1-D arrays, one
    vertex per thread)."""
    v = wp.tid()
    iv = idx[v]
    wv = wts[v]
    a = (affines[iv[0]] * wv[0] + affines[iv[1]] * wv[1] + affines[iv[2]] * wv[2]
         + affines[iv[3]] * wv[3])
    p = points[v]
    out[v] = a * wp.vec4(p[0], p[1], p[2], 1.0)


@wp.kernel
def minimal_dqs_kernel(points: wp.array(dtype=wp.vec3), idx: wp.array(dtype=wp.vec4i),
                       wts: wp.array(dtype=wp.vec4), dqs: wp.array(dtype=vec8),
                       out: wp.array(dtype=wp.vec3)):
    """DQS of one frame, 4 influences sorted (pivot in slot 0), normalization folded in."""
    v = wp.tid()
    iv = idx[v]
    wv = wts[v]
    pv = dqs[iv[0]]
    b = pv * wv[0]
    for k in range(1, 4):
        b = dq_blend_add(b, dqs[iv[k]], wv[k], pv)
    out[v] = dqs_apply(b, points[v])


def bench_kernels(rows, repeat=9, V=1_000_000):
    """One thread (``DQSKIN_THREADS=1`` for the section): the skinning kernels alone (the
    launcher ``dqskin.kernels.skin.skin_points`` on prepared joints, output preallocated) against
    the minimal kernels above, 1M points × 1 frame and 62,500 points × 16 frames (frame blocks)."""
    from dqskin.kernels import skin as K
    saved = os.environ.get("DQSKIN_THREADS")
    os.environ["DQSKIN_THREADS"] = "1"
    try:
        for verts, frames in ((V, 1), (V // 16, 16)):
            points, idx, w, M = make_rig(np.random.default_rng(4), verts)
            sk = dqskin.Skinner(points, idx, w, device="cpu")
            prep, _, _ = sk._prepare(np.broadcast_to(M, (frames,) + M.shape))
            j = prep["joints"]
            fns = {}
            for method, code in (("lbs", K.LBS), ("dqs", K.DQS)):
                out = wp.empty((frames, verts), dtype=wp.vec3, device="cpu")
                fns[f"dqskin {method}"] = (lambda code=code, out=out: K.skin_points(
                    method=code, points=sk._points, influences=sk._inf, joints=j, rigid=True,
                    out=out, device="cpu"))
                if frames == 1:
                    per_joint = j.affines if method == "lbs" else j.dqs
                    kern = minimal_lbs_kernel if method == "lbs" else minimal_dqs_kernel
                    args = [sk._points.flatten(), sk._inf.indices.flatten(),
                            sk._inf.weights.flatten(), per_joint.flatten(), out.flatten()]
                    fns[f"minimal {method}"] = (lambda kern=kern, args=args: wp.launch(
                        kern, dim=verts, inputs=args, device="cpu"))
            res = best_times(fns, repeat)
            for impl, t in res.items():
                rows.append(dict(kind="kernel", method=impl.split()[1], vertices=verts,
                                 frames=frames, impl=impl, seconds=t,
                                 mpts_per_s=verts * frames / t / 1e6))
    finally:
        if saved is None:
            del os.environ["DQSKIN_THREADS"]
        else:
            os.environ["DQSKIN_THREADS"] = saved


def bench_overhead(devices, rows, repeat=5, calls=200):
    """Per-call time of ``Skinner.skin`` on one point with 64 joints (the fixed cost of a call:
    checking and uploading the transforms, preparing them, launching, reading back)."""
    rng = np.random.default_rng(3)
    points, idx, w, M = make_rig(rng, 1)
    for dev in devices:
        sk = dqskin.Skinner(points, idx, w, device=dev)
        for method in ("lbs", "dqs"):
            sk.skin(M, method)
            best = float("inf")
            for _ in range(repeat):
                t0 = time.perf_counter()
                for _ in range(calls):
                    sk.skin(M, method)
                wp.synchronize()
                best = min(best, (time.perf_counter() - t0) / calls)
            rows.append(dict(kind="overhead", device=dev, method=method, joints=JOINTS,
                             impl=f"dqskin {dev}", seconds=best))


def bench_fk(devices, rows, skeletons=1000):
    """FK of ``skeletons`` × 64 joints from local matrices and from TRS (what animations store).

    UsdSkel: ``ConcatJointTransforms`` per skeleton (its API is one skeleton per call), after
    ``MakeTransforms`` for TRS. Inputs are converted to each implementation's native form untimed.
    """
    rng = np.random.default_rng(1)
    parents = np.array([-1] + [int(rng.integers(0, j)) for j in range(1, JOINTS)])
    rot = Rotation.random(skeletons * JOINTS, random_state=rng)
    q_wxyz = rot.as_quat()[:, [3, 0, 1, 2]].reshape(skeletons, JOINTS, 4).astype(np.float32)
    trans = rng.normal(size=(skeletons, JOINTS, 3)).astype(np.float32)
    scale = np.ones((skeletons, JOINTS, 3), np.float32)
    local = np.tile(np.eye(4, dtype=np.float32), (skeletons, JOINTS, 1, 1))
    local[..., :3, :3] = rot.as_matrix().reshape(skeletons, JOINTS, 3, 3)
    local[..., :3, 3] = trans

    def numpy_fk():
        world = np.empty_like(local)
        for j, p in enumerate(parents):
            world[:, j] = local[:, j] if p < 0 else world[:, p] @ local[:, j]
        return world
    topo = UsdSkel.Topology(Vt.IntArray([int(p) for p in parents]))
    usd_local = [Vt.Matrix4dArray.FromNumpy(np.ascontiguousarray(
        local[s].astype(np.float64).transpose(0, 2, 1))) for s in range(skeletons)]
    usd_trs = [(Vt.Vec3fArray.FromNumpy(trans[s]),
                Vt.QuatfArray([Gf.Quatf(float(w), float(x), float(y), float(z))
                               for w, x, y, z in q_wxyz[s]]),
                Vt.Vec3hArray.FromNumpy(scale[s].astype(np.float16))) for s in range(skeletons)]
    fns = {}
    for dev in devices:
        fns[f"dqskin {dev} matrices"] = lambda dev=dev: forward_kinematics(
            parents, local, device=dev)
        fns[f"dqskin {dev} TRS"] = lambda dev=dev: forward_kinematics(
            parents, (trans, q_wxyz, scale), device=dev)
    fns["NumPy matrices"] = numpy_fk
    fns["UsdSkel matrices"] = lambda: [UsdSkel.ConcatJointTransforms(topo, x) for x in usd_local]
    fns["UsdSkel TRS"] = lambda: [UsdSkel.ConcatJointTransforms(topo, UsdSkel.MakeTransforms(*x))
                                  for x in usd_trs]
    res = best_times(fns, 5)
    for impl, t in res.items():
        rows.append(dict(kind="fk", skeletons=skeletons, joints=JOINTS, impl=impl, seconds=t,
                         mjoints_per_s=skeletons * JOINTS / t / 1e6))


def crowd_character():
    """CesiumMan (glTF, 3,273 points, 21 joints) from ../shared, else the bundled humanoid."""
    root = Path(__file__).resolve().parents[1]
    glb = root.parent / "shared" / "assets" / "khronos-gltf" / "CesiumMan" / "CesiumMan.glb"
    return dqskin.load(glb if glb.exists() else root / "assets" / "humanoid.usda")


def bench_crowd(devices, rows, counts=(100, 1000), frames=16, repeat=5):
    """A crowd of ``count`` instances of one character (random time offsets and root
    transforms) against one mesh with the same total points (4 influences, 64 joints), both
    skinning ``frames`` frames per call and reading the result back.

    "crowd skin": the instances' skinning transforms given (one skinning launch); "crowd
    FK+skin": from sampled local transforms (one FK launch, then one skinning launch);
    "crowd end-to-end": :meth:`dqskin.Crowd.skin` from times (animation sampling on the host
    included; only for the smallest count, it is host-bound)."""
    char = crowd_character()
    V1 = sum(len(m.points) for m in char.meshes)
    rng = np.random.default_rng(2)
    t = np.arange(frames) / 24.0 if char.time_codes_per_second == 1 else np.arange(float(frames))
    for count in counts:
        V = count * V1
        for dev in devices:
            crowd = dqskin.Crowd(device=dev)
            for k in range(count):
                root = np.eye(4)
                root[:3, :3] = Rotation.from_euler("y", rng.uniform(0, 360), degrees=True)\
                    .as_matrix()
                root[:3, 3] = [3.0 * (k % 40), 0.0, 3.0 * (k // 40)]
                crowd.add(char, time_offset=float(rng.uniform(0, 1)), root_transform=root)
            local = crowd.local_transforms(t)
            xf = crowd.pose(local)
            points, idx, w, _ = make_rig(rng, V)
            M = np.tile(make_rig(rng, 1)[3], (frames, 1, 1, 1))
            # the same frames with a 1e-5 scale: DQS then runs its residual (scale/shear) kernel,
            # as it does for CesiumMan, whose skinning transforms are that far from rigid
            M_res = M.copy()
            M_res[..., :3, :3] *= 1.00001
            one = dqskin.Skinner(points, idx, w, device=dev)
            mesh = char.meshes[0]
            single = dqskin.Skinner(mesh.points, mesh.joint_indices, mesh.joint_weights,
                                    geom_bind_transform=mesh.geom_bind_transform, device=dev)
            host = xf.numpy()
            per_instance = [np.ascontiguousarray(host[:, sl])
                            for sl in crowd._build().joints.joints]
            for method in ("lbs", "dqs"):
                # rounds run in this order: the two the ratio compares ("one mesh, residual",
                # "crowd skin") each follow a call with an output of the same size, not the
                # per-instance loop, whose thousand small outputs slowed whichever came next
                # (in three runs "crowd FK+skin", which does more, beat the "crowd skin" after it)
                fns = {
                    "one mesh": lambda: (one.skin(M, method), wp.synchronize()),
                    "one mesh, residual": lambda: (one.skin(M_res, method), wp.synchronize()),
                    "crowd skin": lambda: (crowd.skin_transforms(xf, method), wp.synchronize()),
                    "per-instance loop": lambda: ([single.skin(x, method) for x in per_instance],
                                                  wp.synchronize()),
                    "crowd FK+skin": lambda: (crowd.skin_transforms(crowd.pose(local), method),
                                              wp.synchronize()),
                }
                if count == min(counts):
                    fns["crowd end-to-end"] = lambda: (crowd.skin(t, method), wp.synchronize())
                per_round = {}
                res = best_times(fns, repeat, burst_seconds=0.5, rounds=per_round)
                # the ratio again, from calls alternated one by one (same machine share)
                paired = paired_ratios(fns["one mesh, residual"], fns["crowd skin"], repeat,
                                       round_seconds=2.0)
                for impl, sec in res.items():
                    extra = {f"paired_{k}": v for k, v in paired.items()} \
                        if impl == "crowd skin" else {}
                    rows.append(dict(kind="crowd", device=dev, method=method, instances=count,
                                     vertices=V, frames=frames, impl=impl, seconds=sec,
                                     mpts_per_s=V * frames / sec / 1e6, **extra,
                                     **{f"round_{k}": v for k, v in per_round[impl].items()}))


def bench_sign_rules(rows, copies=183, frames=48, repeat=5):
    """DQS with Blender's sign rule (``running_sum``) against UsdSkel's (``largest_weight``) on
    one mesh: CesiumMan's influences and walk tiled ``copies`` times (598,959 points), one frame
    per ``Skinner.skin`` call, every sixth of its first ``frames`` frames; "before" is the
    running sum on the one-vertex kernel (the packet kernels withheld), as the tree ran it
    before the packet kernels took the rule."""
    from dqskin.kernels import skin as KS

    char = crowd_character()
    mesh = char.meshes[0]
    tile = (copies, 1)
    sk = dqskin.Skinner(np.tile(mesh.points, tile), np.tile(mesh.joint_indices, tile),
                        np.tile(mesh.joint_weights, tile),
                        geom_bind_transform=mesh.geom_bind_transform, device="cpu")
    t = np.arange(frames) / 24.0 if char.time_codes_per_second == 1 else np.arange(float(frames))
    xf = char.skinning_transforms(t)[::6]
    takes = KS.takes_packets

    def run(rule, packet=True):
        def fn():
            if not packet:
                KS.takes_packets = lambda *a: False
            try:
                for x in xf:
                    sk.skin(x, "dqs", sign_reference=rule)
            finally:
                KS.takes_packets = takes
        return fn

    res = best_times({"largest_weight": run("largest_weight"), "running_sum": run("running_sum"),
                      "running_sum, one-vertex kernel": run("running_sum", False)},
                     repeat)
    for impl, sec in res.items():
        rows.append(dict(kind="sign", impl=impl, vertices=sk.vertex_count,
                         seconds=sec / len(xf), mpts_per_s=sk.vertex_count * len(xf) / sec / 1e6))


def bench_startup(rows, rounds=15):
    """Start-up: ``dqskin --help`` and ``dqskin info`` on CesiumMan (USDZ, ../shared; the bundled
    humanoid without it) against ``python -c "import numpy"``, each a fresh process started the
    same way (the console script beside this interpreter), in ``rounds`` interleaved rounds;
    wall time and, where ``/usr/bin/time`` runs them (a small process, so the child's peak is
    its own, not this process's image it was forked from), peak memory."""
    import subprocess
    import tempfile

    root = Path(__file__).resolve().parents[1]
    usdz = root.parent / "shared" / "assets" / "usd-wg" / "CesiumMan" / "CesiumMan.usdz"
    asset = usdz if usdz.exists() else root / "assets" / "humanoid.usda"
    script = Path(sys.executable).with_name("dqskin")
    dqskin_cmd = [str(script)] if script.exists() else [sys.executable, "-m", "dqskin.cli"]
    cmds = {'python -c "import numpy"': [sys.executable, "-c", "import numpy"],
            "dqskin --help": dqskin_cmd + ["--help"],
            f"dqskin info {asset.name}": dqskin_cmd + ["info", str(asset)]}
    gnu_time = Path("/usr/bin/time")
    times = {k: [] for k in cmds}
    peak = dict.fromkeys(cmds, 0.0)
    with tempfile.TemporaryDirectory() as tmp:
        kb = Path(tmp) / "kb"
        start = [str(gnu_time), "-f", "%M", "-o", str(kb)] if gnu_time.exists() else []
        for _ in range(rounds):
            for name, cmd in cmds.items():
                t0 = time.perf_counter()
                subprocess.run(start + cmd, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
                               check=True)
                times[name].append(time.perf_counter() - t0)
                if start:
                    peak[name] = max(peak[name], float(kb.read_text().split()[-1]) / 1024)
    for name, ts in times.items():
        rows.append(dict(kind="startup", impl=name, seconds=float(np.median(ts)),
                         worst=float(np.max(ts)), best=float(np.min(ts)), rounds=rounds,
                         peak_mb=peak[name] or None))


def print_startup_table(start):
    base = start[0]
    print(f"\nStart-up, fresh processes, {base['rounds']} interleaved rounds (ratio = median ÷ "
          f"the median of {base['impl']}; targets: --help ≤ 2.5, info ≤ 5)")
    print("| command | median s | best s | worst s | peak MB | ratio |")
    print("|---|---|---|---|---|---|")
    for r in start:
        print(f"| {r['impl']} | {r['seconds']:.3f} | {r['best']:.3f} | {r['worst']:.3f} | "
              f"{r['peak_mb'] or 0:.0f} | {r['seconds'] / base['seconds']:.2f} |")


def print_sign_table(sign):
    base = next(r for r in sign if r["impl"] == "largest_weight")["seconds"]
    print(f"\nDQS sign rules, {sign[0]['vertices']:,} points (CesiumMan tiled), one frame a "
          "call, CPU (ratio = time ÷ largest_weight's, target ≤ 1.3 for running_sum)")
    print("| rule | ms per frame | M points/s | ratio |")
    print("|---|---|---|---|")
    for r in sign:
        print(f"| {r['impl']} | {r['seconds'] * 1e3:.2f} | {r['mpts_per_s']:.0f} | "
              f"{r['seconds'] / base:.2f} |")


def print_crowd_table(crowd):
    print(f"\nCrowds: {crowd[0]['frames']} frames per call (M point-frames/s; ratio = crowd "
          "skin time ÷ one-mesh time with a residual as the crowd has, best rounds; then the "
          "median and worst of the ratios round by round, and of the ratios of calls alternated "
          "one by one (paired); target ≤ 1.3; others: CPU cores other processes took, the "
          "least and most over the rounds)")
    impls = list(dict.fromkeys(r["impl"] for r in crowd))
    print("| instances | points | device | method | " + " | ".join(impls)
          + " | ratio | median | worst | paired median | paired worst | others |")
    print("|" + "---|" * (len(impls) + 10))
    for key in dict.fromkeys((r["instances"], r["device"], r["method"]) for r in crowd):
        sel = {r["impl"]: r for r in crowd
               if (r["instances"], r["device"], r["method"]) == key}
        cells = " | ".join(f"{sel[i]['mpts_per_s']:.1f}" if i in sel else "-" for i in impls)
        ratio = sel["crowd skin"]["seconds"] / sel["one mesh, residual"]["seconds"]
        by_round = np.array(sel["crowd skin"]["round_seconds"]) / np.array(
            sel["one mesh, residual"]["round_seconds"])
        paired = np.array(sel["crowd skin"]["paired_ratio"])
        V = next(iter(sel.values()))["vertices"]
        print(f"| {key[0]} | {V} | {key[1]} | {key[2]} | {cells} | {ratio:.2f} | "
              f"{np.median(by_round):.2f} | {by_round.max():.2f} | {np.median(paired):.2f} | "
              f"{paired.max():.2f} | {others_range(sel.values())} |")


def others_range(rows):
    """``"lo–hi"``: the least and most CPU cores other processes took over the rounds of
    ``rows`` long enough to tell ("?" when none is)."""
    vals = [o for r in rows for k in ("round_others", "paired_others") for o in r.get(k, ())
            if o is not None]
    if not vals:
        return "?"
    return f"{min(vals):.2f}–{max(vals):.2f}"


def print_tables(rows):
    skin = [r for r in rows if r["kind"] == "skin"]
    if skin:
        print_skin_table(skin)
    kern = [r for r in rows if r["kind"] == "kernel"]
    if kern:
        print("\nKernels alone, one thread (M point-frames/s; minimal: 1-D arrays, one frame)")
        for r in kern:
            print(f"| {r['vertices']:>8} × {r['frames']:>2} | {r['impl']:>12} | "
                  f"{r['mpts_per_s']:7.1f} |")
    for r in (r for r in rows if r["kind"] == "overhead"):
        print(f"\nper-call overhead, Skinner.skin of 1 point, {r['joints']} joints, "
              f"{r['method']} on {r['device']}: {r['seconds'] * 1e6:.0f} µs")
    crowd = [r for r in rows if r["kind"] == "crowd"]
    if crowd:
        print_crowd_table(crowd)
    sign = [r for r in rows if r["kind"] == "sign"]
    if sign:
        print_sign_table(sign)
    start = [r for r in rows if r["kind"] == "startup"]
    if start:
        print_startup_table(start)
    fk = [r for r in rows if r["kind"] == "fk"]
    if fk:
        print(f"\nFK: {fk[0]['skeletons']} skeletons × {fk[0]['joints']} joints (M joints/s)")
        for r in fk:
            print(f"| {r['impl']:>22} | {r['mjoints_per_s']:8.2f} | {r['seconds'] * 1e3:8.2f} ms |")


def print_skin_table(skin):
    print(f"\nSkinning: {INFLUENCES} influences, {JOINTS} joints, float32 "
          "(Mpts/s, higher is better)")
    impls = list(dict.fromkeys(r["impl"] for r in skin))
    head = f"| {'vertices':>9} | method | " + " | ".join(f"{i:>17}" for i in impls)
    print(head + " | ×UsdSkel par. | one-shot ×UsdSkel par. | one-shot ÷ Skinner time | "
                 "paired median | paired worst | others | DQS/LBS time |")
    print("|" + "---|" * (len(impls) + 9))
    for V in dict.fromkeys(r["vertices"] for r in skin):
        for method in ("lbs", "dqs"):
            sel = {r["impl"]: r for r in skin if r["vertices"] == V and r["method"] == method}
            ours = next(i for i in impls if i.startswith("dqskin"))
            usd = sel["UsdSkel parallel"]["seconds"]
            one = sel[ours + " one-shot"]["seconds"]
            other = {r["impl"]: r for r in skin if r["vertices"] == V and r["method"] == "lbs"}
            dl = sel[ours]["seconds"] / other[ours]["seconds"]
            cells = " | ".join(f"{sel[i]['mpts_per_s']:17.1f}" for i in impls)
            paired = np.array(sel[ours + " one-shot"]["paired_ratio"])
            print(f"| {V:>9} | {method:6} | {cells} | {usd / sel[ours]['seconds']:12.2f}× | "
                  f"{usd / one:12.2f}× | {one / sel[ours]['seconds']:12.2f}× | "
                  f"{np.median(paired):.2f}× | {paired.max():.2f}× | "
                  f"{others_range(sel.values())} | {dl:11.2f}× |")


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sizes", default="10000,100000,1000000")
    ap.add_argument("--repeat", type=int, default=7)
    ap.add_argument("--json", default="out/bench.json")
    ap.add_argument("--quick", action="store_true", help="10k and 100k only, fewer repeats")
    ap.add_argument("--skip", default="",
                    help="comma list of sections to skip: "
                    "skin,kernel,overhead,fk,crowd,sign,startup,bake")
    ap.add_argument("--crowds", default="100,1000", help="crowd sizes (instances)")
    ap.add_argument("--crowd-frames", type=int, default=16, help="frames per crowd call")
    args = ap.parse_args(argv)
    sizes = [int(s) for s in args.sizes.split(",")]
    if args.quick:
        sizes, args.repeat = [s for s in sizes if s <= 100_000], 3
    wp.config.quiet = True
    wp.config.log_level = wp.LOG_ERROR
    wp.init()
    import dqskin.kernels
    # which trees are measured: an A/B against an old worktree on PYTHONPATH still gets this
    # checkout's kernels through the editable install unless the worktree links dqskin/kernels
    sources = dict(dqskin=str(Path(dqskin.__file__).parent),
                   kernels=str(Path(dqskin.kernels.__file__).parent))
    print(f"dqskin from {sources['dqskin']}, its kernels from {sources['kernels']}")
    devices = ["cpu"] + (["cuda:0"] if wp.get_cuda_device_count() > 0 else [])
    skip = set(filter(None, args.skip.split(",")))
    sections = ("skin", "kernel", "overhead", "fk", "crowd", "sign", "startup", "bake")
    unknown = skip - set(sections)
    if unknown:
        ap.error(f"--skip: unknown section(s) {', '.join(sorted(unknown))}; "
                 f"sections: {','.join(sections)}")
    rows = []
    if "skin" not in skip:
        bench_skinning(sizes, args.repeat, devices, rows)
    if "kernel" not in skip:
        bench_kernels(rows)
    if "overhead" not in skip:
        bench_overhead(devices, rows)
    if "fk" not in skip:
        bench_fk(devices, rows)
    if "crowd" not in skip:
        bench_crowd(devices, rows, [int(c) for c in args.crowds.split(",")],
                    frames=args.crowd_frames)
    if "sign" not in skip:
        bench_sign_rules(rows)
    if "startup" not in skip:
        bench_startup(rows)
    if "bake" not in skip:
        from bench_bake import bench_bake  # noqa: E402  (tools/ sibling)
        bench_bake(rows)
    print_tables(rows)
    out = Path(args.json)
    out.parent.mkdir(parents=True, exist_ok=True)
    meta = dict(python=sys.version.split()[0], warp=wp.__version__, numpy=np.__version__,
                machine=platform.machine(), cpus=os.cpu_count(),
                threads=int(os.environ.get("DQSKIN_THREADS", os.cpu_count() or 1)), **sources)
    tmp = out.with_suffix(".tmp")
    tmp.write_text(json.dumps(dict(meta=meta, rows=rows), indent=1))
    os.replace(tmp, out)
    print(f"\nwrote {out}")


if __name__ == "__main__":
    sys.path.insert(0, str(Path(__file__).resolve().parent))
    main()
