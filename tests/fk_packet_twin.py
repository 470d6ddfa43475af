"""The packet FK kernel over the CUDA branch of ``rigid_packet`` compiled for the CPU (it leaves
every frame to the one-frame path), for ``test_fk.py``."""

import warp as wp

from dqskin.kernels import fk as FK
from dqskin.kernels import fk_native as native
from dqskin.kernels.dqmath import vec8

wp.set_module_options({"enable_backward": False})


@wp.func_native(native.packet_source(all_fallback=True))
def no_lane_packet(matrices: wp.array(dtype=wp.mat44), world: wp.array(dtype=wp.mat44),
                   world_dqs: wp.array(dtype=vec8), world_rigid: wp.array(dtype=wp.uint8),
                   f0: int, n: int, stride: int, j: int, pj: int) -> int:
    ...


fallback_kernel = FK._forward_kinematics_kernel(False, "fk_packet_fallback_kernel",
                                               no_lane_packet)
