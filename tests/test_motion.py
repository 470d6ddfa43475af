"""Pose interpolation and motion-blur velocities (dqskin.motion) against independent oracles.

Oracles: scipy's ``Slerp``, ``CubicSpline`` (natural) and ``CubicHermiteSpline``; the ramp of
Montgomery-Smith & Shy eq. 32-33 written out again here; forward kinematics, LBS and DQS written
from their equations in float64 NumPy below (quaternions via scipy); raw glTF accessor values read
with pygltflib; and central finite differences for every analytic derivative.
"""

import numpy as np
import pygltflib as gl
import pytest
from scipy.interpolate import CubicHermiteSpline, CubicSpline
from scipy.spatial.transform import Rotation, Slerp

from dqskin import animation, dq, motion
from dqskin.animation import Animation
from dqskin.options import INTERPOLATIONS

CESIUM = "khronos-gltf/CesiumMan/CesiumMan.glb"
INTERPS = INTERPOLATIONS

# --------------------------------------------------------------------------------------------
# independent float64 helpers
# --------------------------------------------------------------------------------------------


def qmul(a, b):
    """Hamilton product, (w, x, y, z)."""
    aw, av = a[..., :1], a[..., 1:]
    bw, bv = b[..., :1], b[..., 1:]
    return np.concatenate([aw * bw - np.sum(av * bv, -1, keepdims=True),
                           aw * bv + bw * av + np.cross(av, bv)], -1)


def quat_wxyz(rot):
    return np.roll(rot.as_quat(), 1, axis=-1)


def matrices(rot, t, scale=None):
    """4x4 from a scipy Rotation (..., ) and translations (..., 3), optional diagonal scale."""
    r = rot.as_matrix()
    m = np.zeros(r.shape[:-2] + (4, 4))
    m[..., :3, :3] = r if scale is None else r * scale[..., None, :]
    m[..., :3, 3] = t
    m[..., 3, 3] = 1
    return m


def key_dqs(local):
    """Unit DQs (K, J, 8) of rigid keys, each key sign-aligned with the previous one."""
    q = quat_wxyz(Rotation.from_matrix(local[..., :3, :3].reshape(-1, 3, 3))).reshape(
        local.shape[:-2] + (4,))
    for k in range(1, q.shape[0]):
        q[k] *= np.where(np.sum(q[k] * q[k - 1], -1) < 0, -1.0, 1.0)[:, None]
    t = np.concatenate([np.zeros(q.shape[:-1] + (1,)), local[..., :3, 3]], -1)
    return np.concatenate([q, 0.5 * qmul(t, q)], -1)


def dq_matrix(g):
    """4x4 of normalize(g) for (..., 8) g: rotation by r/|r|, translation 2 vec(d r*)/|r|^2."""
    r, d = g[..., :4], g[..., 4:]
    n2 = np.sum(r * r, -1, keepdims=True)
    conj = r * np.array([1, -1, -1, -1])
    m = np.zeros(g.shape[:-1] + (4, 4))
    m[..., :3, :3] = Rotation.from_quat(np.roll(r, -1, -1).reshape(-1, 4)).as_matrix().reshape(
        g.shape[:-1] + (3, 3))
    m[..., :3, 3] = 2 * qmul(d, conj)[..., 1:] / n2
    m[..., 3, 3] = 1
    return m


def axial(k):
    """Axial vector of a (near) skew-symmetric (..., 3, 3) matrix."""
    return np.stack([k[..., 2, 1], k[..., 0, 2], k[..., 1, 0]], -1)


def fk(parents, local):
    world = np.empty_like(local)
    for j, p in enumerate(parents):
        lj = local[..., j, :, :]
        world[..., j, :, :] = lj if p < 0 else world[..., p, :, :] @ lj
    return world


def lbs(points, idx, w, xf):
    """(F, V, 3): sum_i w_i A_i [p, 1]."""
    a = np.einsum("vk,fvkij->fvij", w, xf[:, idx])
    return np.einsum("fvij,vj->fvi", a[..., :3, :3], points) + a[..., :3, 3]


def dqs(points, idx, w, xf):
    """(F, V, 3): UsdSkel DQS (pivot = largest weight, residual path where any S != I)."""
    out = np.empty((xf.shape[0],) + points.shape)
    for f, a in enumerate(xf):
        u, _, vt = np.linalg.svd(a[:, :3, :3])
        r = u @ vt
        r[np.linalg.det(r) < 0] *= -1
        s = np.swapaxes(r, 1, 2) @ a[:, :3, :3]
        q = quat_wxyz(Rotation.from_matrix(r))
        d = 0.5 * qmul(np.concatenate([np.zeros((len(a), 1)), a[:, :3, 3]], -1), q)
        pivot = q[idx[np.arange(len(idx)), np.argmax(w, 1)]]
        sign = np.where(np.sum(q[idx] * pivot[:, None], -1) < 0, -1.0, 1.0) * w
        rb = np.sum(sign[..., None] * q[idx], 1)
        db = np.sum(sign[..., None] * d[idx], 1)
        x = points
        if np.abs(s - np.eye(3)).max() > 1e-6:
            x = np.einsum("vk,vkij,vj->vi", w, s[idx], points)
        n2 = np.sum(rb * rb, -1, keepdims=True)
        rot = Rotation.from_quat(np.roll(rb, -1, -1)).apply(x)
        out[f] = rot + 2 * qmul(db, rb * np.array([1, -1, -1, -1]))[:, 1:] / n2
    return out


SKIN = {"lbs": lbs, "dqs": dqs}


def random_keys(seed, K=6, J=4, scale=False):
    rng = np.random.default_rng(seed)
    kt = np.cumsum(rng.random(K) + 0.4)
    local = matrices(Rotation.random(K * J, random_state=seed), rng.normal(size=(K * J, 3)),
                     1 + 0.3 * rng.random((K * J, 3)) if scale else None).reshape(K, J, 4, 4)
    return kt, local


def inside(kt, n=4):
    """Times strictly inside every interval, away from the keys."""
    u = (np.arange(n) + 0.5) / n
    return (kt[:-1, None] + u * np.diff(kt)[:, None]).ravel()


# --------------------------------------------------------------------------------------------
# sampling
# --------------------------------------------------------------------------------------------


@pytest.mark.parametrize("interp", INTERPS)
def test_keys_reproduced_and_clamped(interp):
    kt, local = random_keys(1, scale=True)
    anim = animation.KeyedAnimation(kt, local)
    np.testing.assert_allclose(animation.sample(anim, kt, interp), local, atol=1e-12)
    ends = animation.sample(anim, [kt[0] - 5, kt[-1] + 5], interp)
    np.testing.assert_allclose(ends, local[[0, -1]], atol=1e-12)
    _, vel = animation.sample_with_derivative(anim, [kt[0] - 5, kt[-1] + 5], interp)
    assert np.all(vel == 0)


def test_trs_is_slerp_lerp_of_keys():
    rng = np.random.default_rng(2)
    K, J = 5, 3
    kt = np.cumsum(rng.random(K) + 0.3)
    rots = Rotation.random(K * J, random_state=3)
    tr = rng.normal(size=(K, J, 3))
    sc = 0.5 + rng.random((K, J, 3))
    keys = matrices(rots, tr.reshape(-1, 3), sc.reshape(-1, 3)).reshape(K, J, 4, 4)
    anim = animation.KeyedAnimation(kt, keys)
    t = np.linspace(kt[0], kt[-1], 41)
    got = animation.sample(anim, t, "trs")
    for j in range(J):
        rj = Slerp(kt, Rotation.from_matrix(rots.as_matrix().reshape(K, J, 3, 3)[:, j]))(t)
        tj = np.stack([np.interp(t, kt, tr[:, j, c]) for c in range(3)], -1)
        sj = np.stack([np.interp(t, kt, sc[:, j, c]) for c in range(3)], -1)
        np.testing.assert_allclose(got[:, j], matrices(rj, tj, sj), atol=1e-12)


def screw_keys(thetas, ds, axis, point):
    """Screw motions about the fixed line (axis through point): rotate theta, slide d."""
    rot = Rotation.from_rotvec(np.outer(thetas, axis))
    r = rot.as_matrix()
    t = point - r @ point + np.outer(ds, axis)
    return rot, matrices(rot, t)


def test_sclerp_fixed_axis_matches_scipy_slerp():
    axis = np.array([1.0, 2.0, -0.5]) / np.linalg.norm([1.0, 2.0, -0.5])
    point = np.array([0.3, -1.0, 2.0])
    kt = np.array([0.0, 1.0, 2.5, 3.0])
    thetas = np.array([0.0, 2.5, 5.5, 4.0])  # 2.5 -> 5.5 rad is taken the short way (-3.28 rad)
    ds = np.array([0.0, 1.0, -0.5, 2.0])
    rot, keys = screw_keys(thetas, ds, axis, point)
    anim = animation.KeyedAnimation(kt, keys[:, None])
    t = np.linspace(0, 3, 61)
    got = animation.sample(anim, t, "sclerp")[:, 0]
    ref_rot = Slerp(kt, rot)(t)  # scipy: constant angular velocity, shorter arc
    # slide: linear in t along the axis; the short-way rotation does not change the slide
    ref = matrices(ref_rot, point - ref_rot.apply(point) + np.outer(np.interp(t, kt, ds), axis))
    np.testing.assert_allclose(got, ref, atol=1e-12)
    # shortest path: between keys 1 and 2 the rotation never exceeds the short angle
    seg = (t > 1) & (t < 2.5)
    rel = (rot[1].inv() * Rotation.from_matrix(got[seg, :3, :3])).magnitude()
    assert rel.max() <= 2 * np.pi - 3.0 + 1e-9


def test_sclerp_constant_screw_and_exp_log():
    kt, local = random_keys(4, K=4, J=3)
    anim = animation.KeyedAnimation(kt, local)
    for k in range(len(kt) - 1):
        t = np.linspace(kt[k], kt[k + 1], 9)[:-1]
        m = animation.sample(anim, t, "sclerp")
        step = np.linalg.inv(m[:-1]) @ m[1:]  # body-frame increment over equal time steps
        np.testing.assert_allclose(step, np.broadcast_to(step[0], step.shape), atol=1e-12)
        # constant twist equal to the key-to-key relative rotation spread over the interval
        # (inside it: at an interior key the twist is the mean of both sides)
        omega, v = motion.joint_twists(anim, t[1:], "sclerp")
        rel = np.linalg.inv(local[k]) @ local[k + 1]
        rotvec = Rotation.from_matrix(rel[:, :3, :3]).as_rotvec()
        want = np.broadcast_to(rotvec / (kt[k + 1] - kt[k]), omega.shape)
        np.testing.assert_allclose(omega, want, atol=1e-10)
        np.testing.assert_allclose(v, np.broadcast_to(v[0], v.shape), atol=1e-10)
        # a exp(u log(a^-1 b)) and dq.sclerp
        a, b = dq.from_matrix(local[k]), dq.from_matrix(local[k + 1])
        b = np.where(dq.dot(a, b)[..., None] < 0, -b, b)
        u = ((t - kt[k]) / (kt[k + 1] - kt[k]))[:, None, None]
        via_log = dq.mul(a, dq.exp(u * dq.log(dq.mul(dq.conjugate_quat(a), b))))
        np.testing.assert_allclose(m, dq.to_matrix(via_log), atol=1e-12)
        np.testing.assert_allclose(m, dq.to_matrix(dq.sclerp(a, b, u[..., 0])), atol=1e-12)


def test_dlb_and_catmull_rom_against_scipy():
    kt, local = random_keys(5, K=6, J=3)
    anim = animation.KeyedAnimation(kt, local)
    p = key_dqs(local)
    t = np.linspace(kt[0], kt[-1], 77)
    # dlb: normalized linear blend of consecutive (aligned) keys
    i = np.clip(np.searchsorted(kt, t, "right") - 1, 0, len(kt) - 2)
    u = ((t - kt[i]) / (kt[i + 1] - kt[i]))[:, None, None]
    np.testing.assert_allclose(animation.sample(anim, t, "dlb"),
                               dq_matrix((1 - u) * p[i] + u * p[i + 1]), atol=1e-12)
    # Catmull-Rom tangents (central differences, one-sided at the ends), Hermite, normalized
    m = np.gradient(p, kt, axis=0, edge_order=1)
    m[1:-1] = (p[2:] - p[:-2]) / (kt[2:] - kt[:-2])[:, None, None]
    herm = CubicHermiteSpline(kt, p, m, axis=0)
    np.testing.assert_allclose(animation.sample(anim, t, "catmull-rom"), dq_matrix(herm(t)),
                               atol=1e-12)
    # C1 at interior keys: one-sided derivatives agree
    _, left = animation.sample_with_derivative(anim, kt[1:-1] - 1e-9, "catmull-rom")
    _, right = animation.sample_with_derivative(anim, kt[1:-1], "catmull-rom")
    np.testing.assert_allclose(left, right, atol=1e-6)


def ramp_oracle(t, k):
    """[MS] eq. 32-33, written out case by case."""
    f = lambda x: 0.5 + 0.5 * (2 - x) * x ** 3  # noqa: E731
    t0, t1, tm, tn = k[0], k[1], k[-2], k[-1]
    out = []
    for x in t:
        if x < t0:
            out.append(0.5 * (t0 + t1))
        elif x < t1:
            out.append(t0 + (t1 - t0) * f((x - t0) / (t1 - t0)))
        elif x < tm:
            out.append(x)
        elif x < tn:
            out.append(tn - (tn - tm) * f((tn - x) / (tn - tm)))
        else:
            out.append(0.5 * (tm + tn))
    return np.array(out)


def test_ramp_eq32_33():
    k = np.array([0.0, 0.8, 1.1, 2.0, 3.5])
    t = np.linspace(-1, 4.5, 301)
    s, s_dot = animation.ramp(t, k)
    np.testing.assert_allclose(s, ramp_oracle(t, k), atol=1e-14)
    np.testing.assert_allclose(animation.ramp(k[1:-1], k)[0], k[1:-1], atol=1e-14)  # s(t_k) = t_k
    h = 1e-6
    fd = (ramp_oracle(t + h, k) - ramp_oracle(t - h, k)) / (2 * h)
    np.testing.assert_allclose(s_dot, fd, atol=1e-6)
    sd_ends = animation.ramp(k[[0, -1]], k)[1]
    assert np.all(sd_ends == 0)  # f'(0) = 0
    np.testing.assert_allclose(animation.ramp(k[[1, -2]], k)[1], 1.0)  # f'(1) = 1


@pytest.mark.parametrize("K", [2, 3, 6])
def test_spline_is_normalized_natural_spline_with_ramp(K):
    kt, local = random_keys(6, K=K, J=3)
    anim = animation.KeyedAnimation(kt, local)
    p = key_dqs(local)
    keys_t = kt
    if K == 2:  # documented: the screw midpoint is inserted
        mid = dq.sclerp(dq.from_matrix(local[0]), dq.from_matrix(local[1]), 0.5)
        keys_t = np.array([kt[0], kt.mean(), kt[1]])
        local3 = np.stack([local[0], dq.to_matrix(mid), local[1]])
        p = key_dqs(local3)
    knots = keys_t.copy()
    knots[0], knots[-1] = keys_t[:2].mean(), keys_t[-2:].mean()
    spline = CubicSpline(knots, p, axis=0, bc_type="natural")
    t = np.linspace(kt[0] - 0.2, kt[-1] + 0.2, 97)
    np.testing.assert_allclose(animation.sample(anim, t, "spline"),
                               dq_matrix(spline(ramp_oracle(t, keys_t))), atol=1e-11)
    np.testing.assert_allclose(animation.sample(anim, kt, "spline"), local, atol=1e-12)
    # ramp-up / ramp-down: zero velocity at t0 and tn, growing quadratically (zero acceleration)
    _, v_end = animation.sample_with_derivative(anim, kt[[0, -1]], "spline")
    assert np.abs(v_end).max() < 1e-12
    d = 1e-3 * (kt[1] - kt[0])
    _, v1 = animation.sample_with_derivative(anim, [kt[0] + d, kt[-1] - d], "spline")
    _, v2 = animation.sample_with_derivative(anim, [kt[0] + 2 * d, kt[-1] - 2 * d], "spline")
    ratio = np.abs(v2).max(axis=(1, 2, 3)) / np.abs(v1).max(axis=(1, 2, 3))
    np.testing.assert_allclose(ratio, 4.0, rtol=1e-2)


@pytest.mark.parametrize("interp", INTERPS)
def test_derivative_at_interior_keys_is_the_central_difference(interp):
    """At an interior key the derivative is the mean of both one-sided ones: the central
    difference of the sampled transforms (rotation, translation and a residual scale that all
    change rate at the key; an independent check of the averaged twist and scale rate)."""
    kt, local = random_keys(11, K=5, J=3, scale=True)
    anim = animation.KeyedAnimation(kt, local)
    t, h = kt[1:-1], 1e-6
    _, m_dot = animation.sample_with_derivative(anim, t, interp)
    central = (animation.sample(anim, t + h, interp) - animation.sample(anim, t - h, interp))
    np.testing.assert_allclose(m_dot, central / (2 * h), atol=2e-5 * np.abs(m_dot).max())
    # the kink is real for the piecewise interpolants: the sides differ by far more than that
    if interp in ("trs", "sclerp", "dlb"):
        left = (animation.sample(anim, t, interp) - animation.sample(anim, t - h, interp)) / h
        assert np.abs(left - m_dot).max() > 1e-2 * np.abs(m_dot).max()


def third_difference_max(anim, interp, t0, t1, h, point):
    t = np.arange(t0, t1, h)
    m = animation.sample(anim, t, interp)
    x = m[:, :, :3, :3] @ point + m[:, :, :3, 3]
    return np.abs(np.diff(x, n=3, axis=0)).max() / h ** 3


def test_spline_low_jerk():
    kt, local = random_keys(7, K=7, J=2)
    anim = animation.KeyedAnimation(kt, local)
    point = np.array([0.5, -0.3, 0.8])
    jerk = {(i, h): third_difference_max(anim, i, kt[0] - 0.5, kt[-1] + 0.5, h, point)
            for i in ("spline", "sclerp", "dlb") for h in (2e-3, 1e-3)}
    # spline: the third-derivative estimate converges (bounded jerk, also through the ends)
    assert jerk["spline", 1e-3] < 1.2 * jerk["spline", 2e-3]
    # piecewise interpolants have velocity kinks: the estimate grows like 1/h^2
    for i in ("sclerp", "dlb"):
        assert jerk[i, 1e-3] > 3.0 * jerk[i, 2e-3]
        assert jerk[i, 1e-3] > 100 * jerk["spline", 1e-3]


def test_gltf_trs_matches_key_values(shared_assets):
    from dqskin.readers.gltf import (
        load_gltf,  # must exist: fail, not skip, if the loader is missing
    )

    path = shared_assets / CESIUM
    scene = load_gltf(path)
    anim, skel = scene.animations[0], scene.skeletons[0]
    g = gl.GLTF2().load(str(path))
    blob = g.binary_blob()

    def read(index):
        a = g.accessors[index]
        v = g.bufferViews[a.bufferView]
        n = {"SCALAR": 1, "VEC3": 3, "VEC4": 4}[a.type]
        assert a.componentType == 5126 and not v.byteStride
        start = (v.byteOffset or 0) + (a.byteOffset or 0)
        return np.frombuffer(blob, "<f4", a.count * n, start).reshape(a.count, n).astype(np.float64)

    joint = {name: j for j, name in enumerate(skel.joint_names)}
    checked = 0
    for ch in g.animations[0].channels:
        sam = g.animations[0].samplers[ch.sampler]
        times, values = read(sam.input)[:, 0], read(sam.output)
        j = joint[g.nodes[ch.target.node].name]
        m = animation.sample(anim, times, "trs")[:, j]
        lin = m[:, :3, :3]
        scale = np.linalg.norm(lin, axis=1)
        if ch.target.path == "translation":
            got = m[:, :3, 3]
        elif ch.target.path == "scale":
            got = scale
        else:
            q = quat_wxyz(Rotation.from_matrix(lin / scale[:, None, :]))
            want = np.roll(values, 1, -1) / np.linalg.norm(values, axis=1, keepdims=True)
            got = q * np.where(np.sum(q * want, 1) < 0, -1.0, 1.0)[:, None]
            values = want
        np.testing.assert_allclose(got, values, atol=1e-6)
        checked += 1
    assert checked == len(g.animations[0].channels) > 0
    # every DQ interpolant passes through the clip's key poses as well
    keys = anim.local_transforms(anim.key_times)
    for interp in INTERPS[1:]:
        np.testing.assert_allclose(animation.sample(anim, anim.key_times, interp), keys, atol=1e-9)


# --------------------------------------------------------------------------------------------
# velocities
# --------------------------------------------------------------------------------------------


def two_joint_rig(nonrigid):
    """A 4-unit cylinder along x bending at the root and twisting/bending at x = 2."""
    kt = np.array([0.0, 0.7, 1.5, 2.0, 3.1])
    k = np.arange(len(kt), dtype=np.float64)
    root = matrices(Rotation.from_rotvec(np.outer(0.6 * np.sin(1.3 * k), [0, 0, 1])),
                    np.stack([0.3 * k, 0.2 * np.sin(k), 0.1 * k ** 1.5], -1))
    child_rot = (Rotation.from_rotvec(np.outer(0.9 * np.cos(0.8 * k) - 0.5, [0, 0, 1]))
                 * Rotation.from_rotvec(np.outer(1.1 * np.sin(0.9 * k), [1, 0, 0])))
    child = matrices(child_rot, np.tile([2.0, 0, 0], (len(k), 1)),
                     np.stack([1 + 0.25 * np.sin(k), 1 + 0.1 * k, np.ones_like(k)], -1)
                     if nonrigid else None)
    local = np.stack([root, child], 1)
    bind = np.stack([np.eye(4), matrices(Rotation.identity(), np.array([2.0, 0, 0]))])
    rng = np.random.default_rng(8)
    x = rng.random(300) * 4
    ang = rng.random(300) * 2 * np.pi
    pts = np.stack([x, 0.5 * np.cos(ang), 0.5 * np.sin(ang)], -1)
    w1 = np.clip((x - 1.5) / 1.0, 0, 1)
    w1 = w1 * w1 * (3 - 2 * w1)
    weights = np.stack([1 - w1, w1], -1)
    idx = np.tile([0, 1], (300, 1))
    geom = matrices(Rotation.from_rotvec([0.2, -0.1, 0.3]), np.array([0.1, 0.2, -0.3]))
    mesh_pts = (pts - geom[:3, 3]) @ geom[:3, :3]  # geom maps these back onto the cylinder
    return kt, local, bind, mesh_pts, idx, weights, geom


@pytest.mark.parametrize("nonrigid", [False, True], ids=["rigid", "scaled"])
@pytest.mark.parametrize("interp", INTERPS)
@pytest.mark.parametrize("method", ["lbs", "dqs"])
def test_skinned_velocities_match_finite_differences(method, interp, nonrigid, device):
    kt, local, bind, pts, idx, w, geom = two_joint_rig(nonrigid)
    anim = animation.KeyedAnimation(kt, local)
    parents = np.array([-1, 0])
    t = inside(kt, 3)
    loc, loc_dot = animation.sample_with_derivative(anim, t, interp)
    world, world_dot = motion.forward_kinematics_derivative(parents, loc, loc_dot)
    inv_bind = np.linalg.inv(bind)
    vel = motion.skinned_velocities(pts, idx, w, world @ inv_bind, world_dot @ inv_bind, method,
                                    geom_bind_transform=geom, device=device)
    bind_pts = pts @ geom[:3, :3].T + geom[:3, 3]
    h = 1e-5

    def skinned(tt):
        xf = fk(parents, animation.sample(anim, tt, interp)) @ inv_bind
        return SKIN[method](bind_pts, idx, w, xf)

    fd = (skinned(t + h) - skinned(t - h)) / (2 * h)
    err = np.linalg.norm(vel - fd, axis=-1)
    speed = np.linalg.norm(fd, axis=-1)
    assert vel.dtype == np.float32 and vel.shape == fd.shape
    assert np.all(err <= 1e-3 * speed + 1e-5 * speed.max()), err.max() / speed.max()


def test_world_joint_twists_match_finite_differences():
    kt, local, *_ = two_joint_rig(False)
    anim = animation.KeyedAnimation(kt, local)
    parents = np.array([-1, 0])
    t = inside(kt, 2)
    for interp in ("trs", "spline"):
        omega, v = motion.joint_twists(anim, t, interp, frame="world", parents=parents)
        h = 1e-6
        wp_, wm = (fk(parents, animation.sample(anim, t + s * h, interp)) for s in (1, -1))
        w0 = fk(parents, animation.sample(anim, t, interp))
        np.testing.assert_allclose(v, (wp_[..., :3, 3] - wm[..., :3, 3]) / (2 * h), atol=1e-6)
        spin = (wp_[..., :3, :3] - wm[..., :3, :3]) / (2 * h) @ np.swapaxes(w0[..., :3, :3], -1, -2)
        np.testing.assert_allclose(omega, axial(spin), atol=1e-6)
        # local body twists: dt/dt = R v and dR/dt = R [omega]x of each parent-relative transform
        om_l, v_l = motion.joint_twists(anim, t, interp)
        lp, lm = (animation.sample(anim, t + s * h, interp) for s in (1, -1))
        l0 = animation.sample(anim, t, interp)
        np.testing.assert_allclose(np.einsum("fjab,fjb->fja", l0[..., :3, :3], v_l),
                                   (lp[..., :3, 3] - lm[..., :3, 3]) / (2 * h), atol=1e-6)
        body = np.swapaxes(l0[..., :3, :3], -1, -2) @ (lp[..., :3, :3] - lm[..., :3, :3]) / (2 * h)
        np.testing.assert_allclose(om_l, axial(body), atol=1e-6)


@pytest.mark.parametrize("method", ["lbs", "dqs"])
def test_velocities_at_keys_are_the_mean_of_both_sides(shared_assets, method):
    """Caches are sampled exactly at keys, where linear keyframes have a kink; a renderer's shutter
    spans both sides, so the velocity authored there is the central one: it matches the central
    difference of the skinned points (one-sided derivatives were off by ~20% of the peak speed)."""
    from dqskin.readers.gltf import load_gltf

    scene = load_gltf(shared_assets / CESIUM)
    kt = scene.animations[0].key_times
    t = kt[3:-3:5]  # interior keys
    vel = scene.skin(t, method, velocities=True).velocities
    h = 1e-4
    plus, minus = scene.skin(t + h, method).points, scene.skin(t - h, method).points
    for m in scene.meshes:
        fd = (plus[m.name].astype(np.float64) - minus[m.name]) / (2 * h)
        speed = np.linalg.norm(fd, axis=-1).max()
        assert speed > 0.1
        err = np.linalg.norm(vel[m.name] - fd, axis=-1).max()
        assert err <= 2e-2 * speed, err / speed
    one_sided = scene.skin(t + 1e-9, method, velocities=True).velocities
    assert max(np.abs(one_sided[m.name] - vel[m.name]).max() for m in scene.meshes) > 0.05 * speed


@pytest.mark.parametrize("method", ["lbs", "dqs"])
def test_cesium_man_velocities_match_finite_differences(shared_assets, method):
    from dqskin.readers.gltf import (
        load_gltf,  # must exist: fail, not skip, if the loader is missing
    )

    scene = load_gltf(shared_assets / CESIUM)
    kt = scene.animations[0].key_times
    t = inside(kt[::6], 1)  # interval midpoints of every 6th key: away from kinks at keys
    t = 0.5 * (kt[np.searchsorted(kt, t) - 1] + kt[np.searchsorted(kt, t)])
    vel = scene.skin(t, method, velocities=True).velocities
    h = 3e-3  # float32 skinning: larger steps average out rounding; still inside the interval
    plus, minus = scene.skin(t + h, method).points, scene.skin(t - h, method).points
    for m in scene.meshes:
        fd = (plus[m.name].astype(np.float64) - minus[m.name]) / (2 * h)
        err = np.linalg.norm(vel[m.name] - fd, axis=-1)
        speed = np.linalg.norm(fd, axis=-1)
        assert speed.max() > 0.1
        assert err.max() <= 1e-3 * speed.max(), err.max() / speed.max()
    # the same clip through the DQ spline: velocities of the curve sample() draws
    sk = scene.skeletons[0]
    m = scene.meshes[0]
    vel = scene.skin(t, method, velocities=True, interp="spline").velocities[m.name]
    bind = np.linalg.inv(sk.bind_transforms)
    g = m.geom_bind_transform
    pts = m.points.astype(np.float64) @ g[:3, :3].T + g[:3, 3]
    h = 1e-5

    def skinned(tt):
        pose = fk(sk.parents, animation.sample(scene.animations[0], tt, "spline"))
        return SKIN[method](pts, m.joint_indices, m.joint_weights.astype(np.float64), pose @ bind)

    fd = (skinned(t + h) - skinned(t - h)) / (2 * h)
    err = np.linalg.norm(vel - fd, axis=-1)
    assert err.max() <= 1e-3 * np.linalg.norm(fd, axis=-1).max()


def test_scene_velocities_per_second():
    kt, local, bind, pts, idx, w, geom = two_joint_rig(False)
    from dqskin.scene import Mesh, Scene
    from dqskin.skeleton import Skeleton

    skel = Skeleton(["a", "b"], [-1, 0], bind_transforms=bind,
                    animation=animation.KeyedAnimation(kt * 24, local))
    mesh = Mesh("m", pts.astype(np.float32), np.zeros((0, 3), np.int32), idx.astype(np.int32),
                w.astype(np.float32), geom_bind_transform=geom, skinning_method="dqs")
    scene = Scene("rig", [mesh], [skel], kt * 24, time_codes_per_second=24.0)
    t = inside(kt, 2) * 24
    per_code = motion.skinned_velocities(pts, idx, w, *motion.skinning_transforms_with_derivative(
        skel, scene.animations[0], t), "dqs", geom_bind_transform=geom)
    got = scene.skin(t, velocities=True).velocities["m"]
    np.testing.assert_allclose(got, 24.0 * per_code, rtol=1e-5, atol=1e-5 * np.abs(got).max())
    still = Scene("rest", [mesh], [Skeleton(["a", "b"], [-1, 0], bind_transforms=bind)],
                  np.zeros(1))
    assert np.all(still.skin(velocities=True).velocities["m"] == 0)


# --------------------------------------------------------------------------------------------
# bad input
# --------------------------------------------------------------------------------------------


class StepAnimation(Animation):
    """Holds each key until the next (glTF STEP): not linear TRS."""

    def __init__(self, kt, local):
        self.key_times, self._local = kt, local

    def local_transforms(self, times):
        i = np.clip(np.searchsorted(self.key_times, times, "right") - 1, 0, len(self.key_times) - 1)
        return self._local[i]


def test_bad_input():
    kt, local = random_keys(9, K=3, J=2)
    anim = animation.KeyedAnimation(kt, local)
    with pytest.raises(ValueError, match="interp"):
        animation.sample(anim, kt, "cubic")
    with pytest.raises(ValueError, match="strictly increasing"):
        animation.KeyedAnimation(kt[::-1], local)
    with pytest.raises(ValueError, match=r"\(3, J, 4, 4\)"):
        animation.KeyedAnimation(kt, local[:2])
    step = StepAnimation(kt, local)
    np.testing.assert_allclose(animation.sample(step, kt, "sclerp"), local, atol=1e-12)
    with pytest.raises(ValueError, match="not linear TRS"):
        animation.sample_with_derivative(step, inside(kt), "trs")
    with pytest.raises(ValueError, match="parents"):
        motion.joint_twists(anim, kt, frame="world")
    with pytest.raises(ValueError, match="method"):
        motion.skinned_velocities(np.zeros((1, 3)), [[0]], [[1.0]], np.eye(4)[None],
                                  np.zeros((1, 4, 4)), "blend")
    before = local.copy()
    animation.sample(anim, kt, "spline")
    assert np.array_equal(local, before)


@pytest.mark.parametrize("meshes", [1, 2])  # one mesh: the per-mesh loop; two: the batched one
def test_velocities_beyond_float32_per_second_name_file_and_mesh(meshes):
    """Joint rates finite per time code but beyond float32 per second are refused with the file,
    the mesh and the field named (not a bare argument name, nor infinite velocities)."""
    from dqskin.scene import Mesh, Scene
    from dqskin.skeleton import Skeleton
    kt = np.array([0.0, 1.0])
    local = np.tile(np.eye(4), (2, 1, 1, 1))
    local[1, 0, 0, 3] = 1e37  # the root moves 1e37 units in one time code
    skel = Skeleton(["a"], [-1], bind_transforms=np.eye(4)[None],
                    animation=animation.KeyedAnimation(kt, local))
    parts = [Mesh(f"m{i}", np.zeros((3, 3), np.float32), np.zeros((0, 3), np.int32),
                  np.zeros((3, 1), np.int32), np.ones((3, 1), np.float32), skinning_method="lbs")
             for i in range(meshes)]
    scene = Scene("rig.usda", parts, [skel], kt, time_codes_per_second=100.0)
    assert np.isfinite(scene.skin(np.array([0.5])).points["m0"]).all()
    with pytest.raises(ValueError, match=r"^rig\.usda: m0.*: velocities: .*overflows float32"):
        scene.skin(np.array([0.5]), velocities=True)


def test_keyed_refine_gives_exact_trs_poses_between_keys():
    """``KeyedAnimation(refine=...)``: "trs" reads the poses ``refine`` returns for the asked
    times (here a closed-form turn about z by 90°·t², not linear between the keys 0 and 1), so
    the player and its velocity are exact at those times; "sclerp" still interpolates the keys;
    None from ``refine`` falls back to the keys."""
    def pose(t):
        m = np.tile(np.eye(4), (len(t), 1, 1, 1))
        m[:, 0, :3, :3] = Rotation.from_euler("z", 90.0 * np.asarray(t)[:, None] ** 2,
                                              degrees=True).as_matrix()
        return m

    def refine(t):
        if np.all(np.isin(t, [0.0, 1.0])):
            return None
        kt = np.unique(np.concatenate([[0.0, 1.0], t - 1e-6, t, t + 1e-6]))
        return kt, pose(kt)

    keys = np.array([0.0, 1.0])
    anim = animation.KeyedAnimation(keys, pose(keys), refine=refine)
    t = np.array([0.25, 0.5, 0.75])
    np.testing.assert_allclose(anim.local_transforms(t), pose(t), atol=1e-12)
    np.testing.assert_allclose(animation.sample(anim, t, "trs"), pose(t), atol=1e-12)
    _, dot = animation.sample_with_derivative(anim, t, "trs")
    # d/dt of the z turn by θ(t) = (π/2)·t²: θ' = π·t
    theta, rate = np.pi / 2 * t ** 2, np.pi * t
    want = np.zeros((len(t), 3, 3))
    want[:, 0, 0] = want[:, 1, 1] = -np.sin(theta) * rate
    want[:, 0, 1], want[:, 1, 0] = -np.cos(theta) * rate, np.cos(theta) * rate
    np.testing.assert_allclose(dot[:, 0, :3, :3], want, atol=1e-4)
    plain = animation.KeyedAnimation(keys, pose(keys))
    np.testing.assert_allclose(animation.sample(anim, t, "sclerp"),
                               animation.sample(plain, t, "sclerp"), atol=0)
    np.testing.assert_allclose(anim.local_transforms(keys), pose(keys), atol=1e-12)
    assert not np.allclose(plain.local_transforms(t), pose(t), atol=1e-3)
