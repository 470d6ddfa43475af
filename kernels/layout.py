"""The influence layout every kernel that blends influences reads (:class:`InfluenceLayout`), and
its weight sort built on the device.

The layout (packed by :class:`dqskin.influences.Influences`, the only place that builds one): a
vertex's ``K`` influences in ``C = max(1, ceil(K / 4))`` groups of four, ``indices`` and
``weights`` flat 1-D arrays of ``V·C`` ``wp.vec4i`` / ``wp.vec4`` (group ``c`` of vertex ``v`` at
``v·C + c``; a 1-D array is what Warp compiles with constant strides), zero-padded (joint 0,
weight 0); sorted by descending weight, so slot 0 is the DQS pivot, or (``unsorted``) in input
order with the pivot searched per vertex.

:class:`dqskin.influences.Influences` sorts each vertex's ``K`` influences by descending weight
(stable: the first input first on ties) and zero-pads them to ``C = max(1, ceil(K / 4))`` groups
of four. On the host that sort (argsort, gather, pad) costs several times the skinning of the same
points; here one thread per vertex ranks its influences, ``rank(k) = #{m : w_m > w_k or (w_m ==
w_k and m < k)}``, and writes each to its slot -- the same order as NumPy's stable argsort of
``-w`` for finite weights. Up to four influences (one group) go through a five-exchange sorting
network on ``(weight, input slot)`` in registers instead: the same order, several times faster.
"""

import warp as wp

from .._warp import Device
from .grid import launch_rows

wp.set_module_options({"enable_backward": False})  # forward-only kernels


@wp.struct
class InfluenceLayout:
    """A mesh's influences and per-vertex method data, as the skinning and velocity kernels read
    them (see the module docstring)."""

    indices: wp.array(dtype=wp.vec4i)
    """(V·C,) joint indices, four per group."""
    weights: wp.array(dtype=wp.vec4)
    """(V·C,) weights, same layout."""
    groups: int
    """C, the groups of four per vertex."""
    blend: wp.array(dtype=float)
    """(V,) DQS fraction of the blend method; empty otherwise."""
    centers: wp.array(dtype=wp.vec4)
    """(V,) centers of rotation of the COR method (bind space, ``w = 1``; ``w = 0``: none, the
    vertex falls back to DQS); empty otherwise."""
    running_sum: int
    """Sign reference of the rotation blends: 0 the pivot (largest weight, UsdSkel); nonzero the
    running sum of the blend so far, the slots in their input order (Blender)."""
    unsorted: int
    """Nonzero: the slots are in input order and the pivot of ``running_sum = 0`` is searched per
    vertex."""


# A kernel reads the layout's arrays through these: Warp gives the top-level arrays of a 1-D
# launch compile-time strides (``wp_linear_contiguous``) but not the arrays inside a struct, whose
# every access then multiplies by a stride loaded at run time (slower, most for the normal and
# velocity kernels). The layout's arrays are contiguous by
# construction (:class:`dqskin.influences.Influences`, ``blend`` and ``centers`` uploaded
# whole), so their stride is the element size.
_CONTIGUOUS = """
    auto r = a;
    r.strides[0] = sizeof(*a.data);
    return r;"""


@wp.func_native(_CONTIGUOUS)
def contiguous_vec4i(a: wp.array(dtype=wp.vec4i)) -> wp.array(dtype=wp.vec4i):
    """``a`` with its stride the element size, known to the compiler (``a`` contiguous)."""
    ...


@wp.func_native(_CONTIGUOUS)
def contiguous_vec4(a: wp.array(dtype=wp.vec4)) -> wp.array(dtype=wp.vec4):
    """``a`` with its stride the element size, known to the compiler (``a`` contiguous)."""
    ...


@wp.func_native(_CONTIGUOUS)
def contiguous_float(a: wp.array(dtype=float)) -> wp.array(dtype=float):
    """``a`` with its stride the element size, known to the compiler (``a`` contiguous)."""
    ...


@wp.func
def _exchange(wa: float, ia: int, oa: int, wb: float, ib: int, ob: int):
    """One compare-exchange of a sorting network on ``(weight, joint, input slot)``: the larger
    weight first, the earlier input slot first on ties."""
    if wb > wa or (wb == wa and ob < oa):
        return wb, ib, ob, wa, ia, oa
    return wa, ia, oa, wb, ib, ob


@wp.func
def _four(joint_indices: wp.array2d(dtype=wp.int32), joint_weights: wp.array2d(dtype=float),
          v: int, k: int):
    """Influence ``k`` of vertex ``v``, or the padding (joint 0, weight 0) past the last."""
    if k < joint_weights.shape[1]:
        return joint_weights[v, k], joint_indices[v, k]
    return 0.0, 0


@wp.kernel
def layout_kernel(
    joint_indices: wp.array2d(dtype=wp.int32),
    joint_weights: wp.array2d(dtype=float),
    groups: int,
    row_offset: int,
    # outputs
    indices: wp.array(dtype=wp.vec4i),
    weights: wp.array(dtype=wp.vec4),
):
    """Vertex ``row_offset + tid``: its (K,) influences → ``groups`` groups (flat, from
    ``v·groups``), largest weight first, padded with joint 0 and weight 0."""
    v = wp.tid() + row_offset
    count = joint_weights.shape[1]
    first = v * groups
    if count <= 4:  # the common case: a 5-exchange sorting network in registers
        w0, i0 = _four(joint_indices, joint_weights, v, 0)
        w1, i1 = _four(joint_indices, joint_weights, v, 1)
        w2, i2 = _four(joint_indices, joint_weights, v, 2)
        w3, i3 = _four(joint_indices, joint_weights, v, 3)
        o0, o1, o2, o3 = int(0), int(1), int(2), int(3)
        w0, i0, o0, w1, i1, o1 = _exchange(w0, i0, o0, w1, i1, o1)
        w2, i2, o2, w3, i3, o3 = _exchange(w2, i2, o2, w3, i3, o3)
        w0, i0, o0, w2, i2, o2 = _exchange(w0, i0, o0, w2, i2, o2)
        w1, i1, o1, w3, i3, o3 = _exchange(w1, i1, o1, w3, i3, o3)
        w1, i1, o1, w2, i2, o2 = _exchange(w1, i1, o1, w2, i2, o2)
        indices[first] = wp.vec4i(i0, i1, i2, i3)
        weights[first] = wp.vec4(w0, w1, w2, w3)
        return
    for c in range(groups):
        indices[first + c] = wp.vec4i(0, 0, 0, 0)
        weights[first + c] = wp.vec4(0.0, 0.0, 0.0, 0.0)
    for k in range(count):
        wk = joint_weights[v, k]
        rank = int(0)
        for m in range(count):
            wm = joint_weights[v, m]
            if wm > wk or (wm == wk and m < k):
                rank += 1
        c = rank // 4
        slot = rank - 4 * c
        iv = indices[first + c]
        wv = weights[first + c]
        iv[slot] = joint_indices[v, k]
        wv[slot] = wk
        indices[first + c] = iv
        weights[first + c] = wv


def layout(*, joint_indices: wp.array, joint_weights: wp.array, indices: wp.array,
           weights: wp.array, device: Device) -> None:
    """Fill ``indices`` (V·C,) ``wp.vec4i`` and ``weights`` (V·C,) ``wp.vec4`` from the (V, K)
    ``joint_indices`` (int32) and ``joint_weights`` (float32, finite), sorted by weight."""
    rows = joint_weights.shape[0]
    if rows:
        launch_rows(layout_kernel, rows, [joint_indices, joint_weights, indices.shape[0] // rows],
                    [indices, weights], device, min_chunk=65536)
