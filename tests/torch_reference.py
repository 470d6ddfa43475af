"""Skinning and forward kinematics in plain PyTorch, written from the equations: the independent
reference of ``tests/test_autograd.py`` (float64) and the baseline of
``tools/bench_autograd.py`` (float32, the usual gather + ``einsum``).

Batched: transforms ``(B, J, 4, 4)`` (column vectors), points ``(V, 3)`` or ``(B, V, 3)``,
influences ``(V, K)``. Semantics of dqskin (UsdSkel): weights as given; DQS splits each
transform by the polar decomposition ``A = R·S``, blends the residuals ``Σ wᵢ·Sᵢ·p`` and the
sign-aligned dual quaternions of ``(R, t)``; COR (Le & Hodgins) ``R·Σ wᵢSᵢ(p − c) + Σ wᵢAᵢ[c, 1]``.
"""

import torch


def qmul(a, b):
    """Hamilton product of (..., 4) quaternions (w, x, y, z)."""
    aw, ax, ay, az = a.unbind(-1)
    bw, bx, by, bz = b.unbind(-1)
    return torch.stack([aw * bw - ax * bx - ay * by - az * bz,
                        aw * bx + ax * bw + ay * bz - az * by,
                        aw * by - ax * bz + ay * bw + az * bx,
                        aw * bz + ax * by - ay * bx + az * bw], -1)


def qconj(q):
    return q * torch.tensor([1.0, -1.0, -1.0, -1.0], dtype=q.dtype, device=q.device)


def quat_to_matrix(q):
    """(..., 3, 3) rotation of (..., 4) quaternions, normalized first."""
    q = q / q.norm(dim=-1, keepdim=True)
    w, x, y, z = q.unbind(-1)
    return torch.stack([
        torch.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
        torch.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1),
        torch.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1),
    ], -2)


def axis_angle_to_quat(v):
    """(..., 4) unit quaternions of (..., 3) rotation vectors (angles away from 0)."""
    angle = v.norm(dim=-1, keepdim=True)
    return torch.cat([torch.cos(angle / 2), torch.sin(angle / 2) * v / angle], -1)


def matrix_to_quat(m):
    """(..., 4) unit quaternion of (..., 3, 3) rotations: Shepperd's method, the branch of the
    largest of ``(tr, m00, m11, m22)`` (sign: that component positive)."""
    m00, m11, m22 = m[..., 0, 0], m[..., 1, 1], m[..., 2, 2]
    tr = m00 + m11 + m22
    d0, d1, d2 = (m[..., 2, 1] - m[..., 1, 2], m[..., 0, 2] - m[..., 2, 0],
                  m[..., 1, 0] - m[..., 0, 1])
    s0, s1, s2 = (m[..., 0, 1] + m[..., 1, 0], m[..., 0, 2] + m[..., 2, 0],
                  m[..., 1, 2] + m[..., 2, 1])
    c = torch.stack([
        torch.stack([1 + tr, d0, d1, d2], -1),
        torch.stack([d0, 1 + m00 - m11 - m22, s0, s1], -1),
        torch.stack([d1, s0, 1 - m00 + m11 - m22, s2], -1),
        torch.stack([d2, s1, s2, 1 - m00 - m11 + m22], -1)], -2)  # rows ∝ 4·q_i·q
    pick = torch.stack([tr, m00, m11, m22], -1).argmax(-1)
    row = torch.gather(c, -2, pick[..., None, None].expand(*pick.shape, 1, 4))[..., 0, :]
    return row / row.norm(dim=-1, keepdim=True)


def polar(a, steps=40):
    """Rotation factor of ``A = R·S`` (det +1; a reflection negated), by Newton's iteration
    ``X ← ½(X + X⁻ᵀ)``."""
    x = a
    for _ in range(steps):
        x = 0.5 * (x + torch.linalg.inv(x).transpose(-1, -2))
    return torch.where((torch.linalg.det(a) < 0)[..., None, None], -x, x)


def gf_orthonormalize(m, steps=20):
    """Columns of ``m`` orthonormalized as ``GfMatrix3d::Orthonormalize`` (its symmetric
    iteration, all steps)."""
    t = [m[..., :, i] / m[..., :, i].norm(dim=-1, keepdim=True) for i in range(3)]

    def dot(a, b):
        return (a * b).sum(-1, keepdim=True)

    for _ in range(steps):
        b = []
        for i in range(3):
            o1, o2 = [t[k] for k in range(3) if k != i]
            bi = t[i] - o1 * dot(o1, t[i])
            bi = bi - o2 * dot(o2, bi)
            b.append(bi)
        t = [(t[i] + b[i]) / (t[i] + b[i]).norm(dim=-1, keepdim=True) for i in range(3)]
    return torch.stack(t, -1)


def rotate(q, v):
    """Rotate (..., 3) ``v`` by (..., 4) ``q`` divided by ``|q|²`` (``q·v·q*/|q|²``)."""
    vq = torch.cat([torch.zeros_like(v[..., :1]), v], -1)
    return qmul(qmul(q, vq), qconj(q))[..., 1:] / (q * q).sum(-1, keepdim=True)


def lbs(points, idx, w, xf):
    """Linear blend: gather each vertex's (B, V, K, 3, 4) affines, ``einsum`` with the weights."""
    a = xf[:, idx, :3, :]
    m = torch.einsum("vk,bvkij->bvij", w, a)
    p = points.expand(xf.shape[0], -1, -1)
    return torch.einsum("bvij,bvj->bvi", m[..., :3], p) + m[..., 3]


def _signs(q, w, running_sum):
    """(B, V, K) signs of the gathered (B, V, K, 4) real parts: against the largest weight's
    (first on ties), or the running sum's (a zero sum, +1)."""
    if not running_sum:
        pivot = torch.gather(q, 2, w.argmax(1)[None, :, None, None].expand(q.shape[0], -1, 1, 4))
        return torch.where((q * pivot).sum(-1) < 0, -1.0, 1.0).to(q.dtype)
    signs, acc = [], torch.zeros_like(q[:, :, 0])
    for k in range(q.shape[2]):
        s = torch.where((q[:, :, k] * acc).sum(-1) < 0, -1.0, 1.0).to(q.dtype)
        acc = acc + (s * w[:, k])[..., None] * q[:, :, k]
        signs.append(s)
    return torch.stack(signs, -1)


def joint_dqs(xf, rigid=False):
    """(B, J, 8) unit dual quaternions of the transforms' polar rotations and translations, and
    (B, J, 3, 3) residuals ``S = Rᵀ·A``; ``rigid``: ``R = A``, no residuals (the usual DQS)."""
    a = xf[..., :3, :3]
    r = a if rigid else polar(a)
    q = matrix_to_quat(r)
    t = torch.cat([torch.zeros_like(xf[..., :1, 3]), xf[..., :3, 3]], -1)
    d = 0.5 * qmul(t, q)
    return torch.cat([q, d], -1), None if rigid else r.transpose(-1, -2) @ a


def dq_blend(idx, w, dq, running_sum=False):
    """(B, V, 8) sign-aligned blends of the gathered dual quaternions."""
    g = dq[:, idx]  # (B, V, K, 8)
    s = _signs(g[..., :4], w, running_sum)
    return torch.einsum("bvk,bvkc->bvc", s * w, g)


def dq_apply(b, x):
    """Apply the blend ``b = r + ε·d`` normalized: ``r·x·r*/|r|² + 2·(d·r*)_vec/|r|²``."""
    r, d = b[..., :4], b[..., 4:]
    n2 = (r * r).sum(-1, keepdim=True)
    return rotate(r, x) + 2.0 * qmul(d, qconj(r))[..., 1:] / n2


def dqs(points, idx, w, xf, running_sum=False, rigid=False):
    """Dual-quaternion skinning (residuals blended unless ``rigid``)."""
    dq, s = joint_dqs(xf, rigid)
    p = points.expand(xf.shape[0], -1, -1)
    x = p if rigid else torch.einsum("vk,bvkij,bvj->bvi", w, s[:, idx], p)
    return dq_apply(dq_blend(idx, w, dq, running_sum), x)


def blend(points, idx, w, xf, beta, running_sum=False):
    return (1 - beta[:, None]) * lbs(points, idx, w, xf) + beta[:, None] * dqs(
        points, idx, w, xf, running_sum)


def cor(points, idx, w, xf, centers, running_sum=False):
    """Optimized centers of rotation; rows of ``centers`` with NaN: DQS."""
    dq, s = joint_dqs(xf)
    p = points.expand(xf.shape[0], -1, -1)
    ok = ~torch.isnan(centers[:, 0])
    c = torch.where(ok[:, None], centers, torch.zeros_like(centers))
    b = dq_blend(idx, w, dq, running_sum)
    y = torch.einsum("vk,bvkij,bvj->bvi", w, s[:, idx], p - c)
    lc = lbs(c, idx, w, xf)
    return torch.where(ok[:, None], rotate(b[..., :4], y) + lc, dq_apply(b, torch.einsum(
        "vk,bvkij,bvj->bvi", w, s[:, idx], p)))


def normals(method, n, idx, w, xf, beta=None, running_sum=False):
    """Skinned unit normals: LBS ``Σ wᵢ·Aᵢ⁻ᵀ·n``; DQS the sign-aligned blend of the rotations
    of ``N = A⁻ᵀ`` (Gf-orthonormalized) applied to ``Σ wᵢ·Sₙᵢ·n``; blend the mix."""
    nm = torch.linalg.inv(xf[..., :3, :3]).transpose(-1, -2)
    nn = n.expand(xf.shape[0], -1, -1)

    def unit(v):
        return v / v.norm(dim=-1, keepdim=True)

    lin = unit(torch.einsum("vk,bvkij,bvj->bvi", w, nm[:, idx], nn))
    if method == "lbs":
        return lin
    rn = gf_orthonormalize(nm)
    q = matrix_to_quat(rn)
    sn = rn.transpose(-1, -2) @ nm
    g = q[:, idx]
    r = torch.einsum("bvk,bvkc->bvc", _signs(g, w, running_sum) * w, g)
    d = unit(rotate(r, torch.einsum("vk,bvkij,bvj->bvi", w, sn[:, idx], nn)))
    if method == "blend":
        return unit((1 - beta[:, None]) * lin + beta[:, None] * d)
    return d


def fk(local, parents, inverse_bind=None):
    """(B, J, 4, 4) world transforms (times ``inverse_bind`` when given)."""
    world = []
    for j, p in enumerate(parents):
        world.append(local[:, j] if p < 0 else world[p] @ local[:, j])
    out = torch.stack(world, 1)
    return out if inverse_bind is None else out @ inverse_bind


def local_matrices(rotations, translations, scales=None, root=None, parents=None):
    """(B, J, 4, 4) ``T·R·S`` of (B, J, 4) quaternions or (B, J, 3) rotation vectors."""
    q = rotations if rotations.shape[-1] == 4 else axis_angle_to_quat(rotations)
    r = quat_to_matrix(q)
    if scales is not None:
        r = r * scales[..., None, :]
    t = translations.expand(rotations.shape[0], -1, -1)
    if root is not None:
        is_root = torch.tensor([p < 0 for p in parents], device=t.device)[None, :, None]
        t = t + torch.where(is_root, root[:, None, :], torch.zeros_like(root[:, None, :]))
    top = torch.cat([r, t[..., None]], -1)
    bottom = torch.zeros_like(top[..., :1, :])
    bottom[..., 0, 3] = 1.0
    return torch.cat([top, bottom], -2)
