"""Check dqskin on a CUDA device: parity tests, skinning/FK/crowd benchmarks, achieved bandwidth.

    python tools/gpu_check.py [--json out/gpu_check.json] [--quick] [--device cuda:0]

Without a CUDA device it says so and exits 0 (nothing to check; CUDA code generation is covered
on every machine by tests/test_cuda_codegen.py). With one:

1. Parity: pytest runs the device-parametrized and default-device tests (``tests/test_skinning.py``,
   ``test_fk.py``, ``test_one_shot.py``, ``test_crowd.py``, ``test_usd.py``; the default device is
   CUDA when present), and ``tests/test_cuda_codegen.py``; pass/fail counts go to the JSON.
2. Benchmarks: ``tools/bench.py``'s skinning (10k, 100k, 1M points; Skinner and one-shot), FK
   (1,000 skeletons × 64 joints) and crowd (100 and 1,000 CesiumMen vs one mesh) sections on the
   device, beside UsdSkel on the host.
3. Bandwidth: a crowd of 1,000 instances × 50k points (4 influences, 64 joints each) skinned for
   16 frames with LBS and DQS on the device, output left on the device; the bytes a launch must
   move (rest points and influences once, 16 output frames, the joints) over its time, as a share
   of a measured device-to-device copy of 1 GiB (read + write). Target: ≥ 70%.

``--device cpu`` runs the same checks on the CPU (small sizes with ``--quick``): a dry run of this
script's own code where no GPU is lent.
"""

import argparse
import json
import os
import platform
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import warp as wp

ROOT = Path(__file__).resolve().parents[1]
PARITY_TESTS = ["tests/test_cuda_codegen.py", "tests/test_skinning.py", "tests/test_fk.py",
                "tests/test_one_shot.py", "tests/test_crowd.py", "tests/test_usd.py"]
TARGET_SHARE = 0.70


def _timed(fn, device, repeat):
    """Best wall time of ``fn`` over ``repeat`` runs, the device synchronized around each."""
    fn()
    wp.synchronize_device(device)
    best = float("inf")
    for _ in range(repeat):
        wp.synchronize_device(device)
        t0 = time.perf_counter()
        fn()
        wp.synchronize_device(device)
        best = min(best, time.perf_counter() - t0)
    return best


def copy_bandwidth(device, nbytes, repeat=10):
    """Bytes per second of a device-to-device copy (read + write counted)."""
    n = nbytes // 4
    src = wp.zeros(n, dtype=wp.float32, device=device)
    dst = wp.empty(n, dtype=wp.float32, device=device)
    t = _timed(lambda: wp.copy(dst, src), device, repeat)
    return 2 * n * 4 / t, t


def synthetic_character(points, joints=64, influences=4, seed=0):
    """A :class:`dqskin.Scene` of one random mesh bound to a random chain-and-branch skeleton
    (rest pose rotated at random: rigid joints), for the bandwidth crowd."""
    from scipy.spatial.transform import Rotation

    import dqskin
    from dqskin.scene import Mesh, Scene

    rng = np.random.default_rng(seed)
    parents = np.array([-1] + [int(rng.integers(0, j)) for j in range(1, joints)])
    rest = np.tile(np.eye(4), (joints, 1, 1))
    rest[:, :3, :3] = Rotation.random(joints, random_state=rng).as_matrix()
    rest[:, :3, 3] = rng.normal(size=(joints, 3))
    bind = np.empty_like(rest)
    for j, p in enumerate(parents):
        bind[j] = rest[j] if p < 0 else bind[p] @ rest[j]
    skel = dqskin.Skeleton([f"j{j}" for j in range(joints)], parents, bind, rest)
    w = rng.random((points, influences)).astype(np.float32)
    w /= w.sum(1, keepdims=True)
    mesh = Mesh(name="body", points=rng.normal(size=(points, 3)).astype(np.float32),
                faces=np.zeros((0, 3), np.int32),
                joint_indices=rng.integers(0, joints, (points, influences)).astype(np.int32),
                joint_weights=w)
    return Scene(path="synthetic", meshes=[mesh], skeletons=[skel], times=np.zeros(1))


def bandwidth(device, instances, points, frames, repeat):
    """Achieved bytes/s of crowd skinning (LBS, DQS) and its share of a D2D copy."""
    import dqskin

    char = synthetic_character(points)
    crowd = dqskin.Crowd(device=device)
    rng = np.random.default_rng(1)
    for _ in range(instances):
        root = np.eye(4)
        root[:3, 3] = rng.normal(size=3) * 100
        crowd.add(char, time_offset=float(rng.uniform(0, 1)), root_transform=root)
    xf = crowd.pose(crowd.local_transforms(np.zeros(frames)))
    V, J = crowd.vertex_count, crowd.joint_count
    copy_bps, _ = copy_bandwidth(device, 1 << 30)
    out = []
    for method in ("lbs", "dqs"):
        t = _timed(lambda m=method: crowd.skin_transforms(xf, m, as_warp=True), device, repeat)
        # rest points (12 B) and influences (2 × 16 B) read once, 12 B written per frame,
        # joint data read once per frame (affine 48 B, dual quaternion 32 B, residual 36 B)
        moved = V * (12 + 32 + 12 * frames) + frames * J * (48 + 32 + 36)
        out.append(dict(method=method, instances=instances, points_per_instance=points,
                        vertices=V, frames=frames, seconds=t, bytes=moved,
                        bytes_per_s=moved / t, copy_bytes_per_s=copy_bps,
                        share_of_copy=moved / t / copy_bps,
                        mpts_per_s=V * frames / t / 1e6, target=TARGET_SHARE))
    return out


def parity(device_is_cuda):
    """Run the parity tests; returns ``{"returncode", "summary"}``."""
    env = dict(os.environ)
    if not device_is_cuda:  # a dry run on the CPU: the code generation test is enough
        tests = PARITY_TESTS[:1]
    else:
        tests = PARITY_TESTS
    proc = subprocess.run([sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider",
                           *tests], cwd=ROOT, env=env, capture_output=True, text=True)
    lines = [ln for ln in proc.stdout.splitlines() if ln.strip()]
    return dict(returncode=proc.returncode, tests=tests, summary=lines[-1] if lines else "",
                failures=[ln for ln in lines if ln.startswith("FAILED")][:50])


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--json", default="out/gpu_check.json")
    ap.add_argument("--device", default="cuda:0")
    ap.add_argument("--quick", action="store_true",
                    help="small sizes (a smoke run): 10k/100k points, 20 instances × 5k points")
    ap.add_argument("--skip", default="", help="comma list: parity,bench,bandwidth")
    args = ap.parse_args(argv)
    wp.config.quiet = True
    wp.init()
    cuda = args.device.startswith("cuda")
    if cuda and wp.get_cuda_device_count() == 0:
        print("gpu_check: no CUDA device (Warp sees only the CPU): nothing to check here; CUDA "
              "code generation is tested everywhere by tests/test_cuda_codegen.py")
        return 0
    device = wp.get_device(args.device)
    skip = set(filter(None, args.skip.split(",")))
    report = dict(device=str(device), name=getattr(device, "name", str(device)),
                  warp=wp.__version__, python=sys.version.split()[0],
                  machine=platform.machine(), quick=args.quick)
    ok = True
    if "parity" not in skip:
        report["parity"] = parity(cuda)
        ok &= report["parity"]["returncode"] == 0
        print(f"parity: {report['parity']['summary']}")
    if "bench" not in skip:
        sys.path.insert(0, str(ROOT / "tools"))
        import bench

        rows = []
        sizes = [10_000, 100_000] if args.quick else [10_000, 100_000, 1_000_000]
        bench.bench_skinning(sizes, 3, [str(device)], rows)
        bench.bench_fk([str(device)], rows)
        bench.bench_crowd([str(device)], rows, (20,) if args.quick else (100, 1000))
        bench.print_tables(rows)
        report["bench"] = rows
    if "bandwidth" not in skip:
        inst, pts = (20, 5_000) if args.quick else (1000, 50_000)
        rows = bandwidth(str(device), inst, pts, 16, 3 if args.quick else 10)
        report["bandwidth"] = rows
        for r in rows:
            print(f"bandwidth {r['method']}: {r['instances']} × {r['points_per_instance']} points "
                  f"× {r['frames']} frames: {r['bytes_per_s'] / 1e9:.1f} GB/s = "
                  f"{100 * r['share_of_copy']:.0f}% of a D2D copy "
                  f"({r['copy_bytes_per_s'] / 1e9:.1f} GB/s; target {100 * TARGET_SHARE:.0f}%), "
                  f"{r['mpts_per_s']:.0f} M points/s")
    out = Path(args.json)
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = out.with_suffix(".tmp")
    tmp.write_text(json.dumps(report, indent=1, default=str))
    os.replace(tmp, out)
    print(f"wrote {out}")
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
