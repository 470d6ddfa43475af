"""Skinning API: :func:`skin_points`, :func:`skin_normals` and the reusable :class:`Skinner`.

Conventions: points ``(V, 3)`` in the mesh's own space; skinning transforms ``(J, 4, 4)`` or
``(F, J, 4, 4)``, each joint's bind-relative transform (``world ∘ inverse(bind)``) in the
column-vector convention ``p' = M @ [p, 1]``; the optional geom-bind transform maps mesh space to
bind (skeleton) space before skinning. Results are float32 in skeleton space. Same meaning as
``UsdSkel.SkinPoints`` / ``UsdSkel.SkinNormals`` up to the matrix convention (USD is row-vector).
"""

import threading

import numpy as np
import warp as wp

from ._warp import FRAME_BLOCK, launch_blocks, resolve_device
from .kernels import skin as K
from .kernels.dqmath import vec8

__all__ = ["METHODS", "Skinner", "check_influences", "skin_points", "skin_normals"]

METHODS = {"lbs": K.LBS, "dqs": K.DQS, "blend": K.BLEND}
"""Skinning methods: linear blend, dual quaternion, per-vertex blend of the two."""


def _method_code(method):
    try:
        return int(METHODS[method])
    except KeyError:
        raise ValueError(f"method must be one of {sorted(METHODS)}, got {method!r}") from None


def _as_array(name, x, dtype, tail):
    a = np.asarray(x, dtype=dtype)
    if a.ndim < len(tail) or tuple(a.shape[a.ndim - len(tail):]) != tuple(
            t if t is not None else a.shape[a.ndim - len(tail) + i] for i, t in enumerate(tail)):
        want = "(..., " + ", ".join("n" if t is None else str(t) for t in tail) + ")"
        raise ValueError(f"{name}: expected shape {want}, got {a.shape}")
    return a


def _transforms(skinning_transforms):
    x = _as_array("skinning_transforms", skinning_transforms, np.float64, (4, 4))
    if x.ndim == 3:
        return x[None], False
    if x.ndim == 4:
        return x, True
    raise ValueError(f"skinning_transforms: expected (J, 4, 4) or (F, J, 4, 4), got {x.shape}")


def _frames_of(name, a, count):
    """(V, 3) or (F, V, 3) → (Fp, V, 3) with Fp 1 or F."""
    if a.ndim == 2:
        return a[None]
    if a.ndim == 3 and a.shape[0] in (1, count):
        return a
    raise ValueError(f"{name}: expected (V, 3) or ({count}, V, 3), got {a.shape}")


def check_influences(joint_indices, joint_weights, vertex_count=None, joint_count=None):
    """Validate per-vertex influences; returns ``(indices (V, K) int64, weights (V, K) float32)``.

    1-D inputs are one influence per vertex. Raises ValueError naming ``joint_indices`` or
    ``joint_weights`` for mismatched shapes, non-integer or out-of-range indices (``0 <= index <
    joint_count`` when given), and NaN, infinite or negative weights.
    """
    idx = np.asarray(joint_indices)
    wts = np.asarray(joint_weights, dtype=np.float32)
    if idx.ndim == 1:
        idx, wts = idx[:, None], wts[:, None]
    if idx.ndim != 2 or wts.shape != idx.shape or (vertex_count is not None
                                                   and idx.shape[0] != vertex_count):
        want = "(V, K)" if vertex_count is None else f"({vertex_count}, K)"
        raise ValueError(f"joint_indices {idx.shape} and joint_weights {wts.shape} must both be "
                         f"{want}")
    if not np.issubdtype(idx.dtype, np.integer):
        raise ValueError(f"joint_indices: expected integers, got {idx.dtype}")
    if idx.size and idx.min() < 0:
        raise ValueError(f"joint_indices: negative index {int(idx.min())}")
    if joint_count is not None and idx.size and idx.max() >= joint_count:
        raise ValueError(f"joint_indices: index {int(idx.max())} out of range for {joint_count} "
                         "joints")
    if not np.all(np.isfinite(wts)):
        raise ValueError("joint_weights: NaN or infinite weight")
    if wts.size and wts.min() < 0:
        raise ValueError(f"joint_weights: negative weight {float(wts.min())}")
    return idx.astype(np.int64), wts


class Skinner:
    """A mesh's skinning data uploaded once to a device, skinned for many frames.

    Parameters
    ----------
    points : (V, 3) float
        Rest points in mesh space.
    joint_indices : (V, K) int
        Joint of each influence, ``0 <= index < J``. Any ``K`` (1, 4, 8, ...); pad with weight 0.
    joint_weights : (V, K) float
        Influence weights, finite and non-negative; used as given (never renormalized, as UsdSkel).
    geom_bind_transform : (4, 4) float, optional
        Mesh space → bind space, column-vector convention. Identity by default.
    blend_weights : (V,) float, optional
        Per-vertex DQS fraction for ``method="blend"`` (0 = LBS, 1 = DQS).
    device : str, optional
        Warp device; CUDA when present, else CPU.
    """

    def __init__(self, points, joint_indices, joint_weights, *, geom_bind_transform=None,
                 blend_weights=None, device=None):
        self.device = resolve_device(device)
        pts = _as_array("points", points, np.float64, (3,))
        if pts.ndim != 2:
            raise ValueError(f"points: expected (V, 3), got {pts.shape}")
        idx, wts = check_influences(joint_indices, joint_weights, pts.shape[0])
        self.vertex_count, self.influence_count = idx.shape
        # largest weight first (stable: first on ties) -- the kernels' antipodality pivot -- then
        # zero-padded to groups of four (kernels.skin's influence layout)
        order = np.argsort(-wts, axis=1, kind="stable")
        idx, wts = np.take_along_axis(idx, order, 1), np.take_along_axis(wts, order, 1)
        pad = -idx.shape[1] % 4
        idx = np.pad(idx, ((0, 0), (0, pad)))
        wts = np.pad(wts, ((0, 0), (0, pad)))
        self.joint_count_min = int(idx.max()) + 1 if idx.size else 0
        g = np.eye(4) if geom_bind_transform is None else _as_array(
            "geom_bind_transform", geom_bind_transform, np.float64, (4, 4)).reshape(4, 4)
        self.geom_bind_transform = g
        self._cache = {}
        self._lock = threading.Lock()
        d = self.device
        self._points = wp.array(self._bind_points(pts)[None], dtype=wp.vec3, device=d)
        V = self.vertex_count
        self._indices = wp.array(idx.astype(np.int32).reshape(V, -1, 4), dtype=wp.vec4i, device=d)
        self._weights = wp.array(wts.reshape(V, -1, 4), dtype=wp.vec4, device=d)
        if blend_weights is None:
            self._blend = wp.zeros(0, dtype=wp.float32, device=d)
        else:
            b = np.asarray(blend_weights, dtype=np.float32).reshape(-1)
            if b.shape != (self.vertex_count,) or not np.all((b >= 0) & (b <= 1)):
                raise ValueError(f"blend_weights: expected ({self.vertex_count},) values in [0, 1]")
            self._blend = wp.array(b, dtype=wp.float32, device=d)

    def _bind_points(self, pts):
        g = self.geom_bind_transform
        return (pts @ g[:3, :3].T + g[:3, 3]).astype(np.float32)

    def _check_method(self, method):
        code = _method_code(method)
        if code == K.BLEND and self._blend.shape[0] == 0:
            raise ValueError('method "blend" needs blend_weights')
        return code

    _POINT_BUFFERS = dict(affines=K.mat34, dqs=vec8, residuals=wp.mat33)
    _VECTOR_BUFFERS = dict(linears=wp.mat33, rotations=wp.quat, normal_linears=wp.mat33,
                           normal_residuals=wp.mat33, normal_rotations=wp.quat)

    def _buffers(self, kind, frames, joints):
        """Per-(frame, joint) work arrays, allocated once per shape and reused across calls."""
        key = (kind, frames, joints)
        buf = self._cache.get(key)
        if buf is None:
            spec = self._POINT_BUFFERS if kind == "points" else self._VECTOR_BUFFERS
            buf = {k: wp.empty((frames, joints), dtype=t, device=self.device)
                   for k, t in spec.items()}
            if kind == "points":
                buf["has_residual"] = wp.zeros(frames, dtype=wp.int32, device=self.device)
            self._cache[key] = buf
        return buf

    def _prepare(self, skinning_transforms, vectors=False):
        d = self.device
        if isinstance(skinning_transforms, wp.array):
            x = skinning_transforms
            if x.dtype != wp.mat44 or x.ndim != 2 or x.device != d:
                raise ValueError("skinning_transforms: a Warp array must be 2-D (F, J) of wp.mat44 on "
                                 f"{d}, got {x.ndim}-D {x.dtype} on {x.device}")
            batched = True
        else:
            xs, batched = _transforms(skinning_transforms)
            x = wp.array(xs.astype(np.float32), dtype=wp.mat44, device=d)
        frames, joints = x.shape
        if joints < self.joint_count_min:
            raise ValueError(f"joint_indices: index {self.joint_count_min - 1} out of range for "
                             f"{joints} skinning transforms")
        prep = dict(self._buffers("points", frames, joints))
        prep["has_residual"].zero_()
        wp.launch(K.prepare_points_kernel, dim=(frames, joints), inputs=[x],
                  outputs=[prep[k] for k in ("affines", "dqs", "residuals", "has_residual")],
                  device=d)
        if vectors:
            vec = self._buffers("vectors", frames, joints)
            wp.launch(K.prepare_vectors_kernel, dim=(frames, joints), inputs=[x],
                      outputs=list(vec.values()), device=d)
            prep.update(vec)
        return prep, frames, batched

    def _output(self, out, output_transforms, frames, normals):
        """Apply per-frame output transforms (F, 4, 4) to ``out`` (F, N) in place, on the device."""
        if output_transforms is None:
            return
        xf = _as_array("output_transforms", output_transforms, np.float64, (4, 4)).reshape(-1, 4, 4)
        if xf.shape[0] not in (1, frames):
            raise ValueError(f"output_transforms: expected (4, 4) or ({frames}, 4, 4), got {xf.shape}")
        xf = np.broadcast_to(xf, (frames, 4, 4))
        if normals:
            lin = np.linalg.inv(xf[:, :3, :3]).transpose(0, 2, 1)
            xf = np.zeros((frames, 4, 4))
            xf[:, :3, :3] = lin
            xf[:, 3, 3] = 1.0
        wp.launch(K.transform_frames_kernel, dim=out.shape,
                  inputs=[wp.array(xf.astype(np.float32), dtype=wp.mat44, device=self.device),
                          int(normals)], outputs=[out], device=self.device)

    def skin(self, skinning_transforms, method="dqs", *, points=None, output_transforms=None,
             as_warp=False):
        """Skin the points for one or many frames.

        Parameters
        ----------
        skinning_transforms : (J, 4, 4) or (F, J, 4, 4) float, or wp.array2d of wp.mat44 (F, J)
            Bind-relative joint transforms, column-vector convention. A Warp array on this
            skinner's device is used in place (no copy).
        method : {"dqs", "lbs", "blend"}
        points : (V, 3) or (F, V, 3) float, optional
            Rest points replacing the uploaded ones (e.g. after blend shapes), mesh space.
        output_transforms : (4, 4) or (F, 4, 4) float, optional
            Applied to the skinned points on the device (e.g. skeleton space → prim space).
        as_warp : bool
            Return the device array ``wp.array2d(dtype=wp.vec3)`` of shape (F, V) without a copy.

        Returns
        -------
        (V, 3) or (F, V, 3) float32
            Skinned points in skeleton space (or where ``output_transforms`` take them); (F, V, 3)
            when the transforms have a frame axis.
        """
        with self._lock:  # the per-shape work buffers are shared between calls
            return self._skin(skinning_transforms, method, points, output_transforms, as_warp)

    def _skin(self, skinning_transforms, method, points, output_transforms, as_warp):
        code = self._check_method(method)
        prep, frames, batched = self._prepare(skinning_transforms)
        src = self._points
        if points is not None:
            p = _frames_of("points", _as_array("points", points, np.float64, (3,)), frames)
            if p.shape[1] != self.vertex_count:
                raise ValueError(f"points: expected {self.vertex_count} points, got {p.shape[1]}")
            src = wp.array(np.stack([self._bind_points(q) for q in p]), dtype=wp.vec3,
                           device=self.device)
        out = wp.empty((frames, self.vertex_count), dtype=wp.vec3, device=self.device)

        pts = [src, self._indices, self._weights]
        if code == K.LBS:
            kernel, inputs = K.skin_lbs_kernel, pts + [prep["affines"]]
        elif code == K.DQS and not prep["has_residual"].numpy().any():
            kernel, inputs = K.skin_dqs_rigid_kernel, pts + [prep["dqs"]]
        else:
            dqs = [prep["dqs"], prep["residuals"], prep["has_residual"]]
            kernel, inputs = ((K.skin_dqs_kernel, pts + dqs) if code == K.DQS else
                              (K.skin_blend_kernel, pts + [self._blend, prep["affines"]] + dqs))

        def launch(block_offset, blocks, offset, count):
            wp.launch(kernel, dim=(blocks, count),
                      inputs=inputs + [FRAME_BLOCK, block_offset, offset], outputs=[out],
                      device=self.device)

        launch_blocks(launch, self.vertex_count, frames, self.device)
        self._output(out, output_transforms, frames, normals=False)
        if as_warp:
            return out
        res = out.numpy()
        return res if batched else res[0]

    def skin_vectors(self, skinning_transforms, vectors, method="dqs", *, kind="normal",
                     vector_vertex=None, output_transforms=None, as_warp=False):
        """Skin normals or tangents; results are unit length.

        Parameters
        ----------
        skinning_transforms : (J, 4, 4) or (F, J, 4, 4) float
        vectors : (N, 3) or (F, N, 3) float
            Directions in mesh space.
        kind : {"normal", "tangent"}
            Normals transform by the inverse transpose of each linear part; tangents by the part.
        vector_vertex : (N,) int, optional
            Vertex whose influences each vector uses (for faceVarying data); identity by default,
            which requires ``N == V``.
        output_transforms : (4, 4) or (F, 4, 4) float, optional
            Point transforms applied after skinning (normals get their inverse transpose and are
            renormalized; tangents their linear part).

        Returns
        -------
        (N, 3) or (F, N, 3) float32, skeleton space.
        """
        with self._lock:
            return self._skin_vectors(skinning_transforms, vectors, method, kind, vector_vertex,
                                      output_transforms, as_warp)

    def _skin_vectors(self, skinning_transforms, vectors, method, kind, vector_vertex,
                      output_transforms, as_warp):
        if kind not in ("normal", "tangent"):
            raise ValueError(f'kind must be "normal" or "tangent", got {kind!r}')
        code = self._check_method(method)
        prep, frames, batched = self._prepare(skinning_transforms, vectors=True)
        vec = _frames_of("vectors", _as_array("vectors", vectors, np.float64, (3,)), frames)
        n = vec.shape[1]
        if vector_vertex is None:
            if n != self.vertex_count:
                raise ValueError(f"vectors: {n} vectors for {self.vertex_count} points; pass "
                                 "vector_vertex for face-varying data")
            vv = np.arange(n, dtype=np.int32)
        else:
            vv = np.asarray(vector_vertex, dtype=np.int64).reshape(-1)
            if vv.shape != (n,) or (n and (vv.min() < 0 or vv.max() >= self.vertex_count)):
                raise ValueError(f"vector_vertex: expected ({n},) indices into {self.vertex_count} "
                                 "points")
        g = self.geom_bind_transform[:3, :3]
        gm = np.linalg.inv(g).T if kind == "normal" else g
        d = self.device
        src = wp.array((vec @ gm.T).astype(np.float32), dtype=wp.vec3, device=d)
        vv_w = wp.array(vv.astype(np.int32), dtype=wp.int32, device=d)
        if kind == "normal":
            lin, rot, res = prep["normal_linears"], prep["normal_rotations"], prep["normal_residuals"]
        else:
            lin, rot, res = prep["linears"], prep["rotations"], prep["residuals"]
        out = wp.empty((frames, n), dtype=wp.vec3, device=d)

        def launch(block_offset, blocks, offset, count):
            wp.launch(K.skin_vectors_kernel, dim=(blocks, count),
                      inputs=[src, vv_w, self._indices, self._weights, self._blend, lin, rot, res,
                              prep["has_residual"], code, FRAME_BLOCK, block_offset, offset],
                      outputs=[out], device=d)

        launch_blocks(launch, n, frames, d)
        if output_transforms is not None:
            xf = np.array(np.broadcast_to(_as_array("output_transforms", output_transforms,
                                                    np.float64, (4, 4)), (frames, 4, 4)))
            xf[:, :3, 3] = 0.0
            if kind == "normal":
                self._output(out, xf, frames, normals=True)
            else:
                self._output(out, xf, frames, normals=False)
                wp.launch(K.transform_frames_kernel, dim=out.shape,
                          inputs=[wp.array(np.tile(np.eye(4, dtype=np.float32), (frames, 1, 1)),
                                           dtype=wp.mat44, device=d), 1],
                          outputs=[out], device=d)
        if as_warp:
            return out
        r = out.numpy()
        return r if batched else r[0]


def skin_points(points, joint_indices, joint_weights, skinning_transforms, method="dqs", *,
                geom_bind_transform=None, blend_weights=None, device=None):
    """Skin points with LBS, DQS or a per-vertex blend (one call; see :class:`Skinner`).

    Parameters
    ----------
    points : (V, 3) float
        Rest points, mesh space.
    joint_indices : (V, K) int
    joint_weights : (V, K) float
    skinning_transforms : (J, 4, 4) or (F, J, 4, 4) float
        Bind-relative joint transforms (world ∘ inverse bind), column-vector convention.
    method : {"dqs", "lbs", "blend"}
    geom_bind_transform : (4, 4) float, optional
    blend_weights : (V,) float, optional
        DQS fraction per vertex, required for ``"blend"``.
    device : str, optional

    Returns
    -------
    (V, 3) or (F, V, 3) float32
        Skinned points in skeleton space.
    """
    sk = Skinner(points, joint_indices, joint_weights, geom_bind_transform=geom_bind_transform,
                 blend_weights=blend_weights, device=device)
    return sk.skin(skinning_transforms, method)


def skin_normals(normals, joint_indices, joint_weights, skinning_transforms, method="dqs", *,
                 geom_bind_transform=None, blend_weights=None, normal_vertex=None, device=None):
    """Skin normals consistently with :func:`skin_points` (inverse-transpose for LBS and scale).

    Parameters
    ----------
    normals : (N, 3) float
        Mesh-space normals; ``N == V`` unless ``normal_vertex`` maps each normal to its vertex.
    joint_indices, joint_weights : (V, K)
    skinning_transforms : (J, 4, 4) or (F, J, 4, 4) float
    normal_vertex : (N,) int, optional
        Vertex of each normal (faceVarying normals).

    Returns
    -------
    (N, 3) or (F, N, 3) float32
        Unit normals in skeleton space.
    """
    idx = np.asarray(joint_indices)
    sk = Skinner(np.zeros((idx.shape[0], 3)), joint_indices, joint_weights,
                 geom_bind_transform=geom_bind_transform, blend_weights=blend_weights,
                 device=device)
    return sk.skin_vectors(skinning_transforms, normals, method, kind="normal",
                           vector_vertex=normal_vertex)
