"""Recover a pose from target points with ``dqskin.autograd``: gradient descent through skinning
and forward kinematics.

    python tools/fit_pose.py [ASSET] [--method dqs] [--steps 600] [--angle 0.5] [--seed 0]

ASSET (default: CesiumMan from ../shared/assets) is loaded with :func:`dqskin.load`; its first
mesh is posed at random -- every joint's rest rotation turned by a random rotation of up to
``--angle`` radians, the root moved by up to 10% of the height -- and skinned by dqskin itself
(:meth:`dqskin.Skeleton.skinning_transforms` and :func:`dqskin.skin_points`, not the
differentiable path) into the target points. Starting from the rest pose, Adam fits a rotation
vector per joint (turning its rest rotation about world axes, so that a joint's turn does not
swing the orientations of its children) and the root translation to the target: a squared
distance per point, weighted by the inverse of the number of points that the point's main joint
carries (so the few points of an arm count as much as the many of the head), the learning rate
decayed to 0 on a cosine (Adam's second-moment decay 0.99). The joints of the unweighted chain
from the root keep their rest rotations: the first weighted joint's rotation and the root
translation place the body. Prints the largest and the mean distance between fitted and target
points over the steps, relative to the mesh's height.
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


def _rest_world(rig: autograd.Rig) -> torch.Tensor:
    """(J, 3, 3) world rotations of the rest pose (parents first)."""
    local = autograd.local_transforms(rig.rotations, torch.zeros_like(rig.translations))
    world: list[torch.Tensor] = []
    for j, p in enumerate(rig.parents.tolist()):
        r = local[j, :3, :3]
        world.append(r if p < 0 else world[p] @ r)
    return torch.stack(world)


def _local_rotations(rig: autograd.Rig, rest_world: torch.Tensor,
                     vectors: torch.Tensor) -> torch.Tensor:
    """(J, 3, 3) local rotations of the rest pose with each joint's world rotation turned by its
    (J, 3) rotation vector (world axes): a joint's turn leaves its children's orientations."""
    turn = autograd.local_transforms(vectors, torch.zeros_like(vectors))[:, :3, :3]
    world = turn @ rest_world
    parents = rig.parents.long()
    parent = torch.where((parents >= 0)[:, None, None], world[parents.clamp_min(0)],
                         torch.eye(3))
    return parent.transpose(1, 2) @ world


def _points(rig: autograd.Rig, rotations: torch.Tensor, root: torch.Tensor,
            method: str) -> torch.Tensor:
    """(V, 3) points of the rig with (J, 3, 3) local rotations and the root translation."""
    rest = autograd.local_transforms(rig.rotations, rig.translations, scales=rig.scales,
                                     root_translation=root, parents=rig.parents)
    top = torch.cat([rotations * rig.scales[:, None, :], rest[:, :3, 3:]], dim=2)
    local = torch.cat([top, rest[:, 3:]], dim=1)
    xf = autograd.fk(local, rig.parents, inverse_bind=rig.inverse_bind)
    out = autograd.skin(rig.points, rig.indices, rig.weights, xf, method)  # type: ignore[arg-type]
    assert isinstance(out, torch.Tensor)
    return out


def fitted_joints(rig: autograd.Rig) -> np.ndarray:
    """Indices of the joints whose rotations are fitted: all but the unweighted single-child
    chain from the root, whose rotations the next joint's and the root translation replace."""
    parents = rig.parents.numpy()
    weighted = np.zeros(len(parents), bool)
    weighted[rig.indices.numpy()[rig.weights.numpy() > 0]] = True
    children = np.bincount(parents[parents >= 0], minlength=len(parents))
    frozen = np.zeros(len(parents), bool)
    for j, p in enumerate(parents):
        frozen[j] = not weighted[j] and children[j] == 1 and (p < 0 or frozen[p])
    return np.flatnonzero(~frozen)


def point_weights(rig: autograd.Rig) -> torch.Tensor:
    """(V,) loss weights, mean 1: each point's inverse count of points sharing its main joint."""
    main = rig.indices.long().gather(1, rig.weights.argmax(dim=1, keepdim=True))[:, 0]
    w = 1.0 / torch.bincount(main, minlength=rig.parents.shape[0]).float()[main]
    return w / w.mean()


def fit_pose(rig: autograd.Rig, target: torch.Tensor, method: str, steps: int,
             lr: float = 0.2) -> tuple[torch.Tensor, torch.Tensor, list[tuple[float, float]]]:
    """Adam on rotation vectors turning the fitted joints' rest world rotations and on the (3,)
    root translation, from the rest pose; returns the (J, 4) quaternions, the root translation and
    the largest and mean point distances before each step."""
    joints = torch.as_tensor(fitted_joints(rig))
    vectors = torch.zeros(len(joints), 3, requires_grad=True)
    root = torch.zeros(3, requires_grad=True)
    weights = point_weights(rig)
    rest_world = _rest_world(rig)
    opt = torch.optim.Adam([vectors, root], lr=lr, betas=(0.9, 0.99))
    sched = torch.optim.lr_scheduler.CosineAnnealingLR(opt, steps)

    def rotations() -> torch.Tensor:
        full = torch.zeros(rig.rotations.shape[0], 3).index_copy(0, joints, vectors)
        return _local_rotations(rig, rest_world, full)

    history = []
    for _ in range(steps):
        opt.zero_grad()
        d = _points(rig, rotations(), root, method) - target
        (weights * (d * d).sum(dim=1)).mean().backward()
        opt.step()
        sched.step()
        dist = d.detach().norm(dim=1)
        history.append((float(dist.max()), float(dist.mean())))
    with torch.no_grad():
        q = torch.tensor(quat.from_matrix(rotations().double().numpy()), dtype=torch.float32)
        dist = (rig.pose(q, root, method=method) - target).norm(dim=1)
    history.append((float(dist.max()), float(dist.mean())))
    return q, root.detach(), history


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("asset", nargs="?", default=str(CESIUM))
    ap.add_argument("--method", default="dqs", choices=["lbs", "dqs"])
    ap.add_argument("--steps", type=int, default=600)
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
    for i in sorted({0, 10, 50, 100, 200, len(history) - 1}):
        if i < len(history):
            big, mean = history[i]
            print(f"after {i:4d} steps: distance largest {big / height:.2e}, "
                  f"mean {mean / height:.2e} of the height")


if __name__ == "__main__":
    main()
