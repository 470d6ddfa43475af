"""The LBS blend ``Σ wᵢ·A[o + jᵢ]`` of a vertex's 3×4 joint affines as a native snippet, so that
the CPU build uses SIMD (:func:`affine_gather`, a ``@wp.func`` usable in any kernel: LBS points,
the COR centers, velocities).

Warp compiles ``@wp.func`` matrix arithmetic to scalar code on the CPU, one float at a time. On the
CPU this snippet loads each joint's 12 floats as clang vectors (``ext_vector_type``, 8 + 4 floats:
AVX2, NEON or SSE, as the CPU has) and multiply-adds them whole, keeping the sum in registers
(``tools/bench.py``'s "Kernels alone" table compares it with a minimal scalar kernel). On CUDA
(``__CUDA_ARCH__``) it is the plain scalar sum.

The dual-quaternion blend stays a ``@wp.func`` (:func:`~.skin.dq_gather`): the same treatment
gains nothing there, its cost being the sign tests and the
transform rather than the sum. On the CPU, LBS and rigid DQS of one group of four influences run
eight vertices at a time instead (:mod:`.packets`); this blend serves the other cases (more
influences, COR, velocities) and CUDA.

Influence layout of :mod:`.skin`: ``groups`` groups of four per vertex in flat ``indices`` /
``weights``, group 0 already read as ``iv`` / ``wv``. The sum runs joint 0 to 3 of group 0, then
of group 1, ..., from zero: the order of the scalar sum it replaces. Group 0 is summed
straight-line and the others (usually none) in a loop: one loop over every group is slower.
"""

import warp as wp

from .dqmath import mat34

wp.set_module_options({"enable_backward": False})  # forward-only kernels

_CUDA_GROUP = """
        for (int k = 0; k < 4; ++k)
            r = wp::add(r, wp::mul(wp::index(values, o + IDX[k]), WTS[k]));"""

_CPU_GROUP = """
        for (int k = 0; k < 4; ++k) {
            const char* m = (const char*)wp::address(values, o + IDX[k]);
            f8 a;
            f4 b;
            __builtin_memcpy(&a, m, 32);
            __builtin_memcpy(&b, m + 32, 16);
            hi += a * WTS[k];
            lo += b * WTS[k];
        }"""


def _groups(body):
    """C++ running ``body`` (over ``IDX`` and ``WTS``) for group 0, then for the other groups."""
    return ("\n    {" + body.replace("IDX", "iv").replace("WTS", "wv") + "\n    }"
            "\n    for (int c = 1; c < groups; ++c) {"
            "\n        const wp::vec_t<4, wp::int32> ic = wp::index(indices, v * groups + c);"
            "\n        const wp::vec_t<4, wp::float32> wc = wp::index(weights, v * groups + c);"
            + body.replace("IDX", "ic").replace("WTS", "wc") + "\n    }\n")


_AFFINE = """
#if defined(__CUDA_ARCH__)
    wp::mat_t<3, 4, wp::float32> r;""" + _groups(_CUDA_GROUP) + """    return r;
#else
    typedef float f8 __attribute__((ext_vector_type(8)));
    typedef float f4 __attribute__((ext_vector_type(4)));
    f8 hi = 0.0f;
    f4 lo = 0.0f;""" + _groups(_CPU_GROUP) + """    wp::mat_t<3, 4, wp::float32> r;
    __builtin_memcpy(&r, &hi, 32);
    __builtin_memcpy((char*)&r + 32, &lo, 16);
    return r;
#endif
"""


@wp.func_native(_AFFINE)
def affine_gather(values: wp.array(dtype=mat34), o: int, indices: wp.array(dtype=wp.vec4i),
                  weights: wp.array(dtype=wp.vec4), v: int, groups: int, iv: wp.vec4i,
                  wv: wp.vec4) -> mat34:
    """``Σ wᵢ·values[o + jᵢ]`` over vertex ``v``'s ``groups`` groups of four (group 0: ``iv``,
    ``wv``); ``values`` a contiguous 1-D array of 3×4 affines, ``o`` the frame's first joint."""
    ...
