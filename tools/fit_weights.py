"""Fit skinning weights to example poses with ``dqskin.autograd``: gradient descent through
skinning, projected onto valid weights.

    python tools/fit_weights.py [ASSET] [--method lbs] [--steps 300] [--influences 4]
                                [--candidates 12]

ASSET (default: CesiumMan from ../shared/assets) is loaded with :func:`dqskin.load`; its
animation is baked by dqskin itself (:meth:`dqskin.Scene.skinning_transforms` and
:func:`dqskin.skin_points` with ``--method``) at every key time. The even frames are the
examples, the odd frames held out. Each vertex may use the ``--candidates`` joints whose bind
positions are nearest (the asset's own influences are not looked at). Its weights are the
softmax of free logits (so non-negative and summing to 1), fitted by Adam to the examples' mean
squared point distance for half the steps, starting equal; then projected to at most
``--influences`` influences -- the largest kept, renormalized -- and fitted again, the other half
of the steps, over those. Prints the point error on the held-out frames (root mean square and
largest, relative to the mesh's height) and the difference from the asset's weights (mean over
vertices of the L1 distance between the weight vectors, 0 to 2).
"""

import argparse
import sys
from pathlib import Path

import numpy as np
import torch

import dqskin
from dqskin import autograd

ROOT = Path(__file__).resolve().parents[1]
CESIUM = ROOT.parent / "shared" / "assets" / "khronos-gltf" / "CesiumMan" / "CesiumMan.glb"


def candidates(scene: dqskin.Scene, rig: autograd.Rig, count: int) -> torch.Tensor:
    """(V, count) int32: each vertex's nearest joints (bind positions)."""
    joints = np.asarray(scene.skeletons[scene.meshes[0].skeleton].bind_transforms)[:, :3, 3]
    d = np.linalg.norm(rig.points.numpy()[:, None] - joints[None], axis=2)
    return torch.as_tensor(np.argsort(d, axis=1)[:, :count].astype(np.int32))


def bake(scene: dqskin.Scene, rig: autograd.Rig, method: str
         ) -> tuple[torch.Tensor, torch.Tensor]:
    """(F, J, 4, 4) skinning transforms at the key times and the (F, V, 3) points dqskin skins
    with them."""
    xf = scene.skinning_transforms(scene.times)
    pts = dqskin.skin_points(rig.points.numpy(), rig.indices.numpy(), rig.weights.numpy(), xf,
                             method)
    return torch.as_tensor(xf), torch.as_tensor(pts)


def fit_logits(rig: autograd.Rig, idx: torch.Tensor, logits: torch.Tensor, xf: torch.Tensor,
               target: torch.Tensor, method: str, steps: int, lr: float) -> torch.Tensor:
    """Adam on per-vertex logits, the weights their softmax over the joints ``idx``."""
    logits = logits.clone().requires_grad_()
    opt = torch.optim.Adam([logits], lr=lr)
    sched = torch.optim.lr_scheduler.CosineAnnealingLR(opt, steps)
    for _ in range(steps):
        opt.zero_grad()
        d = autograd.skin(rig.points, idx, logits.softmax(1), xf, method) - target
        (d * d).sum(2).mean().backward()
        opt.step()
        sched.step()
    return logits.detach()


def fit_weights(rig: autograd.Rig, idx: torch.Tensor, xf: torch.Tensor, target: torch.Tensor,
                method: str, influences: int, steps: int, lr: float = 0.1
                ) -> tuple[torch.Tensor, torch.Tensor]:
    """``(indices, weights)``, (V, ``influences``), fitted to ``target`` (F, V, 3) under
    transforms ``xf`` (F, J, 4, 4) from the candidate joints ``idx`` (V, C)."""
    logits = fit_logits(rig, idx, torch.zeros(idx.shape), xf, target, method, steps // 2, lr)
    top, slot = logits.softmax(1).topk(influences, dim=1)
    idx = idx.gather(1, slot)
    logits = fit_logits(rig, idx, (top / top.sum(1, keepdim=True)).log(), xf, target, method,
                        steps - steps // 2, lr)
    return idx, logits.softmax(1)


def dense(idx: torch.Tensor, w: torch.Tensor, joints: int) -> torch.Tensor:
    """(V, J) weights of (V, K) influences."""
    return torch.zeros(idx.shape[0], joints).scatter_add(1, idx.long(), w)


def report(scene: dqskin.Scene, method: str, steps: int, influences: int, count: int
           ) -> dict[str, float]:
    """Fit on the even frames; errors on the odd ones and against the asset's weights."""
    rig = autograd.Rig.from_scene(scene)
    xf, pts = bake(scene, rig, method)
    idx, w = fit_weights(rig, candidates(scene, rig, count), xf[0::2], pts[0::2], method,
                         influences, steps)
    with torch.no_grad():
        d = (autograd.skin(rig.points, idx, w, xf[1::2], method) - pts[1::2]).norm(dim=2)
    height = float(np.ptp(rig.points.numpy(), axis=0).max())
    joints = rig.parents.shape[0]
    l1 = (dense(idx, w, joints) - dense(rig.indices, rig.weights, joints)).abs().sum(1)
    return {"heldout_rms": float(d.pow(2).mean().sqrt()) / height,
            "heldout_max": float(d.max()) / height, "weights_l1": float(l1.mean()),
            "influences": int(w.shape[1]), "weight_sum_error": float((w.sum(1) - 1).abs().max()),
            "negative": int((w < 0).sum())}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("asset", nargs="?", default=str(CESIUM))
    ap.add_argument("--method", default="lbs", choices=["lbs", "dqs"])
    ap.add_argument("--steps", type=int, default=300)
    ap.add_argument("--influences", type=int, default=4)
    ap.add_argument("--candidates", type=int, default=12)
    args = ap.parse_args()
    if not Path(args.asset).is_file():
        sys.exit(f"{args.asset}: not found")
    r = report(dqskin.load(args.asset), args.method, args.steps, args.influences,
               args.candidates)
    print(f"held-out frames: RMS error {r['heldout_rms']:.2e}, largest {r['heldout_max']:.2e} "
          f"of the height")
    print(f"weights: mean L1 distance to the asset's {r['weights_l1']:.3f}; at most "
          f"{r['influences']} influences, sums within {r['weight_sum_error']:.1e} of 1")


if __name__ == "__main__":
    main()
