"""Optimized centers of rotation (Le & Hodgins 2016): the per-vertex integral, float64.

A vertex's center is ``p* = Σₜ s(wᵥ, wₜ)·aₜ·cₜ / Σₜ s(wᵥ, wₜ)·aₜ`` over triangles ``t`` (area
``aₜ``, centroid ``cₜ``, weights ``wₜ`` the mean of its corners'), with the similarity

    ``s(wᵥ, wₜ) = Σ_{j≠k} wᵥⱼ·wᵥₖ·wₜⱼ·wₜₖ·exp(−(wᵥⱼ·wₜₖ − wᵥₖ·wₜⱼ)²/σ²)``.

Each term belongs to one joint pair ``{j, k}`` and vanishes unless both vertex and triangle weigh
both joints, so the sum runs pair by pair over only the triangles that share that pair
(:mod:`dqskin.cor` builds the lists): a thread handles one distinct weight vector, looping over its
pairs (``rows``) and each pair's triangle entries. A pair's two orders ``(j, k)``, ``(k, j)`` give
equal terms; the factor 2 cancels in the ratio and is left out.
"""

import warp as wp

from .._warp import Device
from .grid import launch_rows

wp.set_module_options({"enable_backward": False})  # forward-only kernels


@wp.kernel
def centers_kernel(
    row_offsets: wp.array(dtype=wp.int32),
    row_entries: wp.array(dtype=wp.vec2i),
    row_weights: wp.array(dtype=wp.vec2d),
    entry_weights: wp.array(dtype=wp.vec2d),
    entry_areas: wp.array(dtype=wp.float64),
    entry_moments: wp.array(dtype=wp.vec3d),
    inv_sigma2: wp.float64,
    row_offset: int,
    # outputs
    centers: wp.array(dtype=wp.vec4d),
):
    """One weight vector ``u``: rows ``row_offsets[u] .. row_offsets[u + 1]`` are its joint pairs,
    each with the entry range ``row_entries`` of the triangles sharing the pair and the vertex's
    two weights ``row_weights``; an entry holds the triangle's two weights, area ``a`` and moment
    ``a·c``. ``centers[u] = (p*, 1)``, or zeros when no triangle is similar."""
    u = wp.tid() + row_offset
    num = wp.vec3d()
    den = wp.float64(0.0)
    for r in range(row_offsets[u], row_offsets[u + 1]):
        span = row_entries[r]
        wv = row_weights[r]
        for e in range(span[0], span[1]):
            wt = entry_weights[e]
            d = wv[0] * wt[1] - wv[1] * wt[0]
            s = wv[0] * wv[1] * wt[0] * wt[1] * wp.exp(-d * d * inv_sigma2)
            num += entry_moments[e] * s
            den += entry_areas[e] * s
    if den > wp.float64(0.0):
        c = num / den
        centers[u] = wp.vec4d(c[0], c[1], c[2], wp.float64(1.0))
    else:
        centers[u] = wp.vec4d()


def centers(*, row_offsets: wp.array, row_entries: wp.array, row_weights: wp.array,
            entry_weights: wp.array, entry_areas: wp.array, entry_moments: wp.array,
            sigma: float, out: wp.array, device: Device) -> None:
    """Fill ``out`` (U,) ``wp.vec4d`` with the centers of ``U`` weight vectors (see
    :func:`centers_kernel`), chunked over the CPU cores."""
    launch_rows(centers_kernel, out.shape[0],
                [row_offsets, row_entries, row_weights, entry_weights, entry_areas, entry_moments,
                 1.0 / (float(sigma) ** 2)], [out], device, min_chunk=256)
