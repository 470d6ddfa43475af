"""Warp kernels of dqskin, installed as ``dqskin.kernels``.

``dqmath``: dual-quaternion algebra as ``@wp.func`` (usable in any kernel); ``fk``: forward
kinematics; ``skin``: per-vertex skinning; ``velocity``: skinned-point velocities; ``metrics``:
artifact measures; ``render``: ray casting. Each module also holds the thin functions that launch
its kernels where that is all they need; the public Python API that launches them lives in
:mod:`dqskin` (``skinning``, ``skeleton``, ``motion``, ``metrics``, ``render``).
"""
