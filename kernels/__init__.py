"""Warp kernels of dqskin, installed as ``dqskin.kernels``.

``dqmath`` holds the dual-quaternion algebra as ``@wp.func``; ``fk`` forward kinematics; ``skin``
the per-vertex skinning kernels. Kernels sit beside the functions that launch them.
"""
