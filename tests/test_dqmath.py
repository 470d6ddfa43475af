"""The Warp ``@wp.func`` dual-quaternion API (kernels/dqmath.py) against the float64 NumPy algebra
(``dqskin.dq``) and against matrices built with SciPy."""

import numpy as np
import warp as wp
from scipy.spatial.transform import Rotation

from dqskin import dq
from dqskin.kernels.dqmath import (
    dq_blend_add,
    dq_conjugate,
    dq_from_rt,
    dq_from_transform,
    dq_mul,
    dq_to_matrix,
    dq_to_transform,
    dq_transform_point,
    dq_transform_vector,
    dq_translation,
    vec8,
)


@wp.kernel
def dq_api_kernel(
    a: wp.array(dtype=vec8),
    b: wp.array(dtype=vec8),
    p: wp.array(dtype=wp.vec3),
    w: wp.array(dtype=float),
    # outputs
    product: wp.array(dtype=vec8),
    conjugate: wp.array(dtype=vec8),
    moved: wp.array(dtype=wp.vec3),
    turned: wp.array(dtype=wp.vec3),
    to_matrix: wp.array(dtype=wp.mat44),
    via_transform: wp.array(dtype=vec8),
    translation: wp.array(dtype=wp.vec3),
    blend: wp.array(dtype=vec8),
):
    i = wp.tid()
    product[i] = dq_mul(a[i], b[i])
    conjugate[i] = dq_conjugate(a[i])
    moved[i] = dq_transform_point(a[i], p[i])
    turned[i] = dq_transform_vector(a[i], p[i])
    to_matrix[i] = dq_to_matrix(a[i])
    via_transform[i] = dq_from_transform(dq_to_transform(a[i]))
    translation[i] = dq_translation(dq_from_rt(wp.quat_identity(), p[i]))
    acc = dq_blend_add(vec8(), a[i], w[i], a[i])
    blend[i] = dq_blend_add(acc, b[i] * -1.0, 1.0 - w[i], a[i])


def test_wp_func_api_matches_numpy(device):
    rng = np.random.default_rng(0)
    n = 64
    rot = Rotation.random(2 * n, random_state=rng)
    q = rot.as_quat()[:, [3, 0, 1, 2]]
    t = rng.normal(size=(2 * n, 3))
    x = dq.from_rt(q, t)
    a, b = x[:n], x[n:]
    p = rng.normal(size=(n, 3))
    w = rng.random(n)
    arr = lambda v, dt: wp.array(np.asarray(v, np.float32), dtype=dt, device=device)  # noqa: E731
    outs = dict(product=vec8, conjugate=vec8, moved=wp.vec3, turned=wp.vec3, to_matrix=wp.mat44,
                via_transform=vec8, translation=wp.vec3, blend=vec8)
    res = {k: wp.empty(n, dtype=v, device=device) for k, v in outs.items()}
    wp.launch(dq_api_kernel, dim=n, inputs=[arr(a, vec8), arr(b, vec8), arr(p, wp.vec3),
                                            arr(w, float)],
              outputs=list(res.values()), device=device)
    r = {k: v.numpy().astype(np.float64) for k, v in res.items()}
    tol = dict(atol=2e-5)
    np.testing.assert_allclose(r["product"], dq.mul(a, b), **tol)
    np.testing.assert_allclose(r["conjugate"], dq.conjugate_quat(a), **tol)
    np.testing.assert_allclose(r["moved"], dq.transform_point(a, p), **tol)
    np.testing.assert_allclose(r["turned"], dq.transform_vector(a, p), **tol)
    np.testing.assert_allclose(r["to_matrix"], dq.to_matrix(a), **tol)
    np.testing.assert_allclose(r["via_transform"], a, **tol)
    np.testing.assert_allclose(r["translation"], p, **tol)
    # blend of a (weight w) and −b (weight 1 − w), pivot a: −b is flipped where a·b ≥ 0
    ref = dq.dlb(np.stack([a, -b], 1), np.stack([w, 1 - w], 1))
    np.testing.assert_allclose(dq.to_matrix(dq.normalize(r["blend"])), dq.to_matrix(ref), **tol)
