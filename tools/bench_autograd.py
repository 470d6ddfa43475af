"""Benchmark ``dqskin.autograd.skin``: forward + backward against the PyTorch reference.

    python tools/bench_autograd.py [--points 100000] [--joints 64] [--influences 4]
                                   [--batches 1 16] [--repeat 5] [--device cpu] [--json out.json]

A random rig: ``--points`` rest points, ``--influences`` random joints per vertex with random
weights summing to 1, ``--joints`` random rigid skinning transforms per pose, ``B`` poses. One
step is the forward pass and the backward pass of ``sum(out * g)`` with respect to the points,
the weights and the transforms, as a fitting loop runs it. Baseline: ``tests/torch_reference.py``
in float32, the usual PyTorch formulation: LBS gathers each vertex's (B, V, K, 3, 4) affines and
contracts them with ``einsum``; DQS converts the joints' rotation matrices to quaternions
(Shepperd), gathers the (B, V, K, 8) dual quaternions, flips their signs against the
largest-weight joint's, blends with ``einsum`` and applies the normalized blend. dqskin's DQS
also does what that baseline leaves out: the polar decomposition of every transform and the
blend of the scale/shear residuals; row ``dqs+S`` times the reference doing the same (dqskin's
semantics: Newton's polar iteration, the residuals gathered and blended). The two run
interleaved (A, B, A, B, ...), the best of ``--repeat`` steps each after three warm-up steps,
in the same process and thread count (PyTorch's intra-op threads and dqskin's CPU threads both
the core count unless set). Prints a table of milliseconds
per step and the speed-up; ``--json`` writes it.
"""

import argparse
import json
import os
import platform
import sys
import time
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tests"))
import torch_reference as ref  # noqa: E402

from dqskin import autograd  # noqa: E402


def rig(points, joints, influences, batch, device):
    g = torch.Generator().manual_seed(0)
    p = torch.randn(points, 3, generator=g)
    idx = torch.randint(0, joints, (points, influences), generator=g)
    w = torch.rand(points, influences, generator=g) + 0.05
    w = w / w.sum(1, keepdim=True)
    x = torch.eye(4).repeat(batch, joints, 1, 1)
    x[..., :3, :3] = ref.quat_to_matrix(torch.randn(batch, joints, 4, generator=g))
    x[..., :3, 3] = torch.randn(batch, joints, 3, generator=g)
    up = torch.randn(batch, points, 3, generator=g)
    return [t.to(device) for t in (p, idx, w, x, up)]


def step(fn, p, idx, w, x, up):
    """One forward + backward; seconds."""
    leaves = [t.detach().clone().requires_grad_() for t in (p, w, x)]
    t0 = time.perf_counter()
    out = fn(leaves[0], idx, leaves[1], leaves[2])
    (out * up).sum().backward()
    if p.is_cuda:
        torch.cuda.synchronize()
    return time.perf_counter() - t0


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--points", type=int, default=100_000)
    ap.add_argument("--joints", type=int, default=64)
    ap.add_argument("--influences", type=int, default=4)
    ap.add_argument("--batches", type=int, nargs="+", default=[1, 16])
    ap.add_argument("--repeat", type=int, default=5)
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--json")
    args = ap.parse_args()
    methods = {
        "lbs": (lambda p, i, w, x: autograd.skin(p, i, w, x, "lbs"),
                lambda p, i, w, x: ref.lbs(p, i, w, x)),
        "dqs": (lambda p, i, w, x: autograd.skin(p, i, w, x, "dqs"),
                lambda p, i, w, x: ref.dqs(p, i, w, x, rigid=True)),
        "dqs+S": (lambda p, i, w, x: autograd.skin(p, i, w, x, "dqs"),
                  lambda p, i, w, x: ref.dqs(p, i, w, x)),
    }
    rows = []
    for batch in args.batches:
        data = rig(args.points, args.joints, args.influences, batch, args.device)
        for name, (ours, theirs) in methods.items():
            for _ in range(3):  # warm-up: kernels compiled and loaded, buffers allocated
                step(ours, *data)
                step(theirs, *data)
            a, b = [], []
            for _ in range(args.repeat):
                a.append(step(ours, *data))
                b.append(step(theirs, *data))
            rows.append({"method": name, "batch": batch, "dqskin_ms": 1e3 * min(a),
                         "torch_ms": 1e3 * min(b), "speedup": min(b) / min(a)})
            r = rows[-1]
            print(f"{name:5s} B={batch:<3d} dqskin {r['dqskin_ms']:8.1f} ms   torch "
                  f"{r['torch_ms']:8.1f} ms   {r['speedup']:5.2f}x", flush=True)
    info = {"points": args.points, "joints": args.joints, "influences": args.influences,
            "device": args.device, "torch": torch.__version__,
            "torch_threads": torch.get_num_threads(), "cpu": platform.processor(),
            "cores": os.cpu_count(), "rows": rows}
    if args.json:
        Path(args.json).parent.mkdir(parents=True, exist_ok=True)
        Path(args.json).write_text(json.dumps(info, indent=2))


if __name__ == "__main__":
    main()
