"""Recover a pose from target points with ``dqskin.autograd``: gradient descent through skinning
and forward kinematics.

    python tools/fit_pose.py [ASSET] [--method dqs] [--steps 300] [--angle 0.5] [--seed 0]

ASSET (default: CesiumMan from ../shared/assets) is loaded with :func:`dqskin.load`; its first
mesh is posed at random -- every joint's rest rotation turned by a random rotation of up to
``--angle`` radians, the root moved by up to 10% of the height -- and skinned by dqskin itself
(:meth:`dqskin.Skeleton.skinning_transforms` and :func:`dqskin.skin_points`, not the
differentiable path) into the target points. Starting from the rest pose, Adam fits the joint
quaternions and the root translation to the target (mean squared distance, the learning rate
decayed over the steps). Prints the largest distance between fitted and target points over the
steps and at the end, relative to the mesh's height.
"""

import argparse
import sys
from pathlib import Path

import numpy as np
import torch

import dqskin
from dqskin import autograd, quat

ROOT = Path(__file__).resolve().parents[1]
CESIUM = ROOT.parent / "shared" / "assets" / "khronos-gltf" / "CesiumMan" / "CesiumMan.glb"


def random_pose(rig: autograd.Rig, angle: float, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """(J, 4) quaternions: each rest rotation turned by a random rotation of at most ``angle``
    radians; (3,) root offset within 10% of the height."""
    rng = np.random.default_rng(seed)
    joints = rig.rotations.shape[0]
    axes = rng.normal(size=(joints, 3))
    axes /= np.linalg.norm(axes, axis=1, keepdims=True)
    turn = quat.from_axis_angle(axes, rng.uniform(0, angle, joints))
    rotations = quat.mul(rig.rotations.double().numpy(), turn)
    height = float(np.ptp(rig.points.numpy(), axis=0).max())
    return rotations, rng.uniform(-0.1, 0.1, 3) * height


def target_points(scene: dqskin.Scene, rig: autograd.Rig, rotations: np.ndarray,
                  root: np.ndarray, method: str) -> np.ndarray:
    """Points of the pose skinned by dqskin's own path (not the differentiable one)."""
    skel = scene.skeletons[scene.meshes[0].skeleton]
    translations = rig.translations.double().numpy().copy()
    translations[skel.parents < 0] += root
    xf = skel.skinning_transforms((translations, rotations, rig.scales.double().numpy()))
    return dqskin.skin_points(rig.points.numpy(), rig.indices.numpy(), rig.weights.numpy(), xf,
                              method)


def fit_pose(rig: autograd.Rig, target: torch.Tensor, method: str, steps: int,
             lr: float = 0.02) -> tuple[torch.Tensor, torch.Tensor, list[float]]:
    """Adam on the (J, 4) joint quaternions and the (3,) root translation, from the rest pose;
    returns them and the largest point distance after each step."""
    rotations = rig.rotations.clone().requires_grad_()
    root = torch.zeros(3, requires_grad=True)
    opt = torch.optim.Adam([rotations, root], lr=lr)
    sched = torch.optim.lr_scheduler.CosineAnnealingLR(opt, steps)
    history = []
    for _ in range(steps):
        opt.zero_grad()
        d = rig.pose(rotations, root, method=method) - target
        (d * d).sum(dim=1).mean().backward()
        opt.step()
        sched.step()
        history.append(float(d.detach().norm(dim=1).max()))
    return rotations.detach(), root.detach(), history


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("asset", nargs="?", default=str(CESIUM))
    ap.add_argument("--method", default="dqs", choices=["lbs", "dqs"])
    ap.add_argument("--steps", type=int, default=300)
    ap.add_argument("--angle", type=float, default=0.5)
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()
    if not Path(args.asset).is_file():
        sys.exit(f"{args.asset}: not found")
    scene = dqskin.load(args.asset)
    rig = autograd.Rig.from_scene(scene)
    rotations, root = random_pose(rig, args.angle, args.seed)
    target = torch.as_tensor(target_points(scene, rig, rotations, root, args.method))
    height = float(np.ptp(rig.points.numpy(), axis=0).max())
    _, _, history = fit_pose(rig, target, args.method, args.steps)
    for i in sorted({0, 9, 49, 99, 199, len(history) - 1}):
        if i < len(history):
            print(f"step {i + 1:4d}: largest distance {history[i] / height:.2e} of the height")


if __name__ == "__main__":
    main()
