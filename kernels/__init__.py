"""Warp kernels of dqskin, installed as ``dqskin.kernels``.

``dqmath``: dual-quaternion algebra as ``@wp.func`` (usable in any kernel); ``fk``: forward
kinematics; ``skin``: per-vertex skinning (the influence layout and the blends every kernel
shares); ``blend``: the LBS blend, a native snippet using SIMD on the CPU; ``velocity``:
skinned-point velocities; ``metrics``: artifact measures; ``render``: ray casting. Each
module exposes keyword-argument launchers beside its kernels, built on ``grid`` (one launch on
CUDA, chunks on a CPU thread pool); nothing outside this package calls ``wp.launch``. The
public Python API over them lives in :mod:`dqskin`.
"""
