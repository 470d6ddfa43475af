"""The scalar (CUDA) branches of :mod:`dqskin.kernels.fk_native` compiled for the CPU, beside the
vector branches the CPU build uses, in one kernel (for ``test_fk.py``)."""

import warp as wp

from dqskin.kernels import fk_native as native
from dqskin.kernels.dqmath import vec8

wp.set_module_options({"enable_backward": False})


@wp.func_native(native.step_source(scalar_on_cpu=True))
def scalar_step(m: wp.mat44, parent: vec8, has_parent: int) -> vec8:
    ...


@wp.func_native(native.matrix_source(scalar_on_cpu=True))
def scalar_matrix(a: vec8) -> wp.mat44:
    ...


@wp.func_native(native.check_source(scalar_on_cpu=True))
def scalar_check(m: wp.mat44) -> wp.vec2:
    ...


@wp.kernel
def both_branches(m: wp.array(dtype=wp.mat44), parent: wp.array(dtype=vec8),
                  has_parent: wp.array(dtype=int), step: wp.array2d(dtype=vec8),
                  matrix: wp.array2d(dtype=wp.mat44), check: wp.array2d(dtype=wp.vec2)):
    """Row 0: the CPU (vector) branch; row 1: the scalar branch."""
    i = wp.tid()
    step[0, i] = native.rigid_step(m[i], parent[i], has_parent[i])
    step[1, i] = scalar_step(m[i], parent[i], has_parent[i])
    matrix[0, i] = native.rigid_matrix(parent[i])
    matrix[1, i] = scalar_matrix(parent[i])
    check[0, i] = native.local_check(m[i])
    check[1, i] = scalar_check(m[i])
