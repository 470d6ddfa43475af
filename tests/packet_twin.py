"""The scalar (CUDA) branches of :mod:`dqskin.kernels.packets` compiled for the CPU, launched
beside the vector branches the CPU build uses (for ``test_packets.py``)."""

import warp as wp

from dqskin.kernels import packets as P
from dqskin.kernels.dqmath import mat34, vec8

wp.set_module_options({"enable_backward": False})


@wp.func_native(P.packet_source("lbs", scalar_on_cpu=True))
def scalar_lbs(points: wp.array(dtype=wp.vec3), point_base: wp.int64,
               indices: wp.array(dtype=wp.vec4i), weights: wp.array(dtype=wp.vec4),
               joints: wp.array(dtype=mat34), o: int, v0: int, count: int,
               out: wp.array(dtype=wp.vec3), out_base: wp.int64, joint_count: int,
                  check: int, flags: wp.array(dtype=wp.int32)) -> int:
    ...


@wp.func_native(P.packet_source("dqs", "sorted", scalar_on_cpu=True))
def scalar_sorted(points: wp.array(dtype=wp.vec3), point_base: wp.int64,
                  indices: wp.array(dtype=wp.vec4i), weights: wp.array(dtype=wp.vec4),
                  joints: wp.array(dtype=vec8), residuals: wp.array(dtype=wp.mat33),
                  scaled: int, o: int, v0: int, count: int,
                  out: wp.array(dtype=wp.vec3), out_base: wp.int64, joint_count: int,
                  check: int, flags: wp.array(dtype=wp.int32)) -> int:
    ...


@wp.func_native(P.packet_source("dqs", "searched", scalar_on_cpu=True))
def scalar_searched(points: wp.array(dtype=wp.vec3), point_base: wp.int64,
                    indices: wp.array(dtype=wp.vec4i), weights: wp.array(dtype=wp.vec4),
                    joints: wp.array(dtype=vec8), residuals: wp.array(dtype=wp.mat33),
                    scaled: int, o: int, v0: int, count: int,
                    out: wp.array(dtype=wp.vec3), out_base: wp.int64, joint_count: int,
                  check: int, flags: wp.array(dtype=wp.int32)) -> int:
    ...


@wp.func_native(P.packet_source("dqs", "running", scalar_on_cpu=True))
def scalar_running(points: wp.array(dtype=wp.vec3), point_base: wp.int64,
                   indices: wp.array(dtype=wp.vec4i), weights: wp.array(dtype=wp.vec4),
                   joints: wp.array(dtype=vec8), residuals: wp.array(dtype=wp.mat33),
                   scaled: int, o: int, v0: int, count: int,
                   out: wp.array(dtype=wp.vec3), out_base: wp.int64, joint_count: int,
                   check: int, flags: wp.array(dtype=wp.int32)) -> int:
    ...


def _kernel(vector, scalar, joint_type, name, dqs):
    def kernel(points: wp.array(dtype=wp.vec3), indices: wp.array(dtype=wp.vec4i),
               weights: wp.array(dtype=wp.vec4), joints: wp.array(dtype=joint_type),
               residuals: wp.array(dtype=wp.mat33), scaled: wp.array(dtype=int),
               joint_count: int, frames: int, vertices: int, check: int,
               out_vector: wp.array(dtype=wp.vec3), out_scalar: wp.array(dtype=wp.vec3),
               flags_vector: wp.array(dtype=wp.int32), flags_scalar: wp.array(dtype=wp.int32)):
        """Packet ``tid`` of every frame (points, joints and outputs frame-major) through both
        branches; the DQS snippets blend frame ``f``'s points through ``residuals`` when
        ``scaled[f]``; with ``check``, each branch flags its own array."""
        v0 = wp.tid() * 8
        for f in range(frames):
            base = wp.int64(f) * wp.int64(vertices)
            o = f * joint_count
            if wp.static(dqs):
                vector(points, base, indices, weights, joints, residuals, scaled[f], o, v0,
                       vertices, out_vector, base, joint_count, check, flags_vector)
                scalar(points, base, indices, weights, joints, residuals, scaled[f], o, v0,
                       vertices, out_scalar, base, joint_count, check, flags_scalar)
            else:
                vector(points, base, indices, weights, joints, o, v0, vertices, out_vector, base,
                       joint_count, check, flags_vector)
                scalar(points, base, indices, weights, joints, o, v0, vertices, out_scalar, base,
                       joint_count, check, flags_scalar)

    return wp.kernel(kernel, name=name)


BOTH = {"lbs": _kernel(P.lbs_packet, scalar_lbs, mat34, "both_lbs", False),
        "sorted": _kernel(P.dqs_sorted_packet, scalar_sorted, vec8, "both_sorted", True),
        "searched": _kernel(P.dqs_searched_packet, scalar_searched, vec8, "both_searched", True),
        "running": _kernel(P.dqs_running_packet, scalar_running, vec8, "both_running", True)}
"""Kernels running both branches of each snippet, by rule (``"lbs"``, ``"sorted"``,
``"searched"``, ``"running"``)."""
