"""Skinning API: :func:`skin_points`, :func:`skin_normals` and the reusable :class:`Skinner`.

Conventions: points ``(V, 3)`` in the mesh's own space; skinning transforms ``(J, 4, 4)`` or
``(F, J, 4, 4)``, each joint's bind-relative transform (``world ∘ inverse(bind)``) in the
column-vector convention ``p' = M @ [p, 1]``; the optional geom-bind transform maps mesh space to
bind (skeleton) space before skinning. Results are float32 in skeleton space. Same meaning as
``UsdSkel.SkinPoints`` / ``UsdSkel.SkinNormals`` up to the matrix convention (USD is row-vector).
"""

import threading
from typing import Any, Literal, cast, get_args

import numpy as np
import numpy.typing as npt
import warp as wp

from ._warp import Device, resolve_device
from .cor import check_faces, rotation_centers
from .errors import InputError, Param
from .influences import Influences
from .kernels import buffers as KB
from .kernels import grid as KG
from .kernels import skin as K
from .kernels.dqmath import mat34, vec8
from .options import (
    DEFAULT_SIGN_REFERENCE,
    METHOD_NAMES,
    SIGN_REFERENCES,
    CorOptions,
    Method,
    SignReference,
)
from .shapes import as_array, frames_of
from .validation import check_finite, check_transforms, within_float32

__all__ = ["METHODS", "Skinner", "VectorKind", "skin_points", "skin_normals"]

METHODS: dict[Method, int] = dict(zip(METHOD_NAMES, (K.LBS, K.DQS, K.BLEND, K.COR)))
"""Each :data:`~dqskin.options.Method` and its kernel code."""

VectorKind = Literal["normal", "tangent"]
"""How directions transform: normals by the inverse transpose, tangents by the matrix."""



def _check_sign_reference(sign_reference):
    if sign_reference not in SIGN_REFERENCES:
        raise InputError(f"sign_reference must be one of {list(SIGN_REFERENCES)}, got "
                         f"{sign_reference!r}")
    return sign_reference


def _method_code(method):
    try:
        return int(METHODS[method])
    except KeyError:
        raise InputError(f"method must be one of {sorted(METHODS)}, got {method!r}") from None


def _transforms(name, skinning_transforms):
    x = as_array(name, skinning_transforms, None, (4, 4))
    if x.dtype.kind != "f":
        x = x.astype(np.float64)
    if x.ndim == 3:
        return x[None], False
    if x.ndim == 4:
        return x, True
    raise InputError(f"{name}: expected (J, 4, 4) or (F, J, 4, 4), got {x.shape}")


_empties: dict[tuple[Any, str], wp.array] = {}


def _empty(dtype, device):
    """A zero-length array (an absent optional input), one per dtype and device: never written."""
    key = (dtype, str(device))
    a = _empties.get(key)
    if a is None:
        a = _empties[key] = wp.empty(0, dtype=dtype, device=device)
    return a


_scratch = threading.local()


def _thread_buffers(device):
    """The work buffers (transforms, per-joint data) of every :class:`_OneCall` on this thread and
    device: each call refills them before use and they never leave it, so a one-shot call reuses
    its predecessor's instead of allocating them; and the non-owning views of callers' arrays
    with their influence layouts (by address and shape). Cleared when it holds many entries."""
    caches = getattr(_scratch, "caches", None)
    if caches is None:
        caches = _scratch.caches = {}
    cache = caches.setdefault(str(device), {})
    if len(cache) > 64:
        cache.clear()
    return cache


_BESIDE_MIN = 1 << 18
"""Point coordinates from which they are checked on another thread beside the influences."""

_SMALL_RESULT = 65536
"""Point-frames up to which :meth:`Skinner.skin` reuses its output buffer (an allocation costs
more than the copy out)."""


class Skinner:
    """A mesh's skinning data uploaded once to a device, skinned for many frames.

    Parameters
    ----------
    points : (V, 3) float
        Rest points in mesh space.
    joint_indices : (V, K) int, or dqskin.influences.Influences
        Joint of each influence, ``0 <= index < J``. Any ``K`` (1, 4, 8, ...); pad with weight 0.
        An :class:`~dqskin.influences.Influences` (already validated, e.g.
        :meth:`~dqskin.influences.Influences.concatenate`'s) with ``joint_weights=None``.
    joint_weights : (V, K) float, or None
        Influence weights, finite and non-negative; used as given (never renormalized, as UsdSkel).
    geom_bind_transform : (4, 4) float, optional
        Mesh space → bind space, column-vector convention. Identity by default.
    blend_weights : (V,) float, optional
        Per-vertex DQS fraction for ``method="blend"`` (0 = LBS, 1 = DQS).
    faces : (T, 3) int, optional
        Triangles, required for ``method="cor"``: its centers of rotation
        (:func:`dqskin.cor.rotation_centers`, bind space) are computed on its first use, from the
        rest points (not from ``points`` passed per call), and cached on disk.
    cor : dqskin.CorOptions, optional
        How the centers are computed (similarity width, subdivision, weight clustering:
        :func:`dqskin.cor.rotation_centers`); default :class:`~dqskin.options.CorOptions`.
    device : str, optional
        Warp device; CUDA when present, else CPU.
    """

    def __init__(self, points: npt.ArrayLike, joint_indices: npt.ArrayLike | Influences,
                 joint_weights: npt.ArrayLike | None, *,
                 geom_bind_transform: npt.ArrayLike | None = None,
                 blend_weights: npt.ArrayLike | None = None, faces: npt.ArrayLike | None = None,
                 cor: CorOptions | None = None, device: Device = None) -> None:
        self.device = resolve_device(device)
        pts = as_array("points", points, None, (3,))
        if pts.ndim != 2:
            raise InputError(f"points: expected (V, 3), got {pts.shape}")
        unchecked = self._unchecked  # values left to the kernels (a one-shot call's)

        def influences():  # its error is raised after one about the points
            if isinstance(joint_indices, Influences) and joint_weights is None:
                if joint_indices.vertex_count != pts.shape[0]:
                    return None, InputError(f"joint_indices: {joint_indices.vertex_count} "
                                            f"vertices for {pts.shape[0]} points")
                return joint_indices, None
            if isinstance(joint_indices, Influences):
                return None, InputError("joint_weights: expected None with joint_indices an "
                                        "Influences")
            if joint_weights is None:
                return None, InputError("joint_weights: required with joint_indices an array")
            try:
                return Influences(joint_indices, joint_weights, vertex_count=pts.shape[0],
                                  check_values=not unchecked), None
            except ValueError as exc:
                return None, exc

        # one pass over each array, the points beside the influences when large
        problem, (self.influences, error) = (
            (None, influences()) if unchecked else
            KG.beside(lambda: within_float32(pts), influences) if pts.size >= _BESIDE_MIN
            else (within_float32(pts), influences()))
        if problem:
            raise InputError(f"points: {problem} coordinates")
        if error is not None:
            raise error
        self.vertex_count = self.influences.vertex_count
        self.influence_count = self.influences.influence_count
        g = np.eye(4) if geom_bind_transform is None else check_transforms(
            "geom_bind_transform", as_array("geom_bind_transform", geom_bind_transform, np.float64,
                                            (4, 4)).reshape(1, 4, 4))[0]
        self.geom_bind_transform = g
        self._identity_bind = np.array_equal(g, np.eye(4))
        self._cache: dict[Any, Any] = {}
        self._lock = threading.Lock()
        d = self.device
        self._rest_points = pts  # mesh space; bind space (float64) only when "cor" needs it
        self.faces = None if faces is None else check_faces(faces, self.vertex_count)
        self.cor = CorOptions() if cor is None else cor
        if not isinstance(self.cor, CorOptions):
            raise InputError(Param("cor", cor), ": expected a CorOptions")
        self._centers: tuple[np.ndarray, wp.array] | None = None
        if blend_weights is None:
            self._blend = _empty(wp.float32, d)
        else:
            b = np.asarray(blend_weights, dtype=np.float32).reshape(-1)
            if b.shape != (self.vertex_count,) or not np.all((b >= 0) & (b <= 1)):
                raise InputError(f"blend_weights: expected ({self.vertex_count},) values in [0, 1]")
            self._blend = wp.array(b, dtype=wp.float32, device=d)
        self._no_centers = _empty(wp.vec4, d)
        # the rest points (1, V) and the default layout: UsdSkel's rule (built now, so that a
        # one-shot call's upload aliases)
        self._points, self._inf = self._device_mesh()
        # (COR, running sum) → the kernels' InfluenceLayout
        self._layouts: dict[tuple[bool, bool], K.InfluenceLayout] = {}

    def rotation_centers(self) -> np.ndarray:
        """(V, 3) float64 centers of rotation of ``method="cor"`` in bind space, NaN for vertices
        without one (skinned as DQS); computed once (or read from the disk cache)."""
        if self.faces is None:
            raise InputError('method "cor" needs faces (the mesh triangles): pass faces=')
        if self._centers is None:
            g = self.geom_bind_transform
            rest_bind = np.asarray(self._rest_points, np.float64) @ g[:3, :3].T + g[:3, 3]
            c = rotation_centers(rest_bind, self.faces, *self.influences.given,
                                 sigma=self.cor.sigma, subdivide=self.cor.subdivide,
                                 cluster=self.cor.cluster,
                                 device=self.device)
            c4 = np.zeros((self.vertex_count, 4), np.float32)
            ok = ~np.isnan(c[:, 0])
            c4[ok, :3], c4[ok, 3] = c[ok], 1.0
            self._centers = c, wp.array(c4, dtype=wp.vec4, device=self.device)
        return self._centers[0]

    def _device_mesh(self):
        """``(rest points (1, V) wp.vec3, default InfluenceLayout)`` on the device."""
        return (self._upload(self._rest_points[None]),
                self.influences.layout(self.device, self._layout_order, blend=self._blend,
                                       centers=self._no_centers, copy=self._copy_uploads))

    def _influences(self, code, sign_reference):
        """The kernels' :class:`~dqskin.kernels.layout.InfluenceLayout` for a method code and
        sign rule (made once for each)."""
        running = _check_sign_reference(sign_reference) == "running_sum" and code != K.LBS
        if not running and code != K.COR:  # (LBS has no sign rule)
            return self._inf
        key = (code == K.COR, running)
        layout = self._layouts.get(key)
        if layout is None:
            centers = self._no_centers
            if code == K.COR:
                self.rotation_centers()
                assert self._centers is not None
                centers = self._centers[1]
            layout = self._layouts[key] = self.influences.layout(
                self.device, "input" if running else self._layout_order, blend=self._blend,
                centers=centers, running_sum=running)
        return layout

    _unchecked = False
    """True (:class:`_OneCall`, when :func:`skin_points` allows): the values of points, indices
    and weights are checked by the packet kernel that skins them (``K.skin_points``'s ``flags``)
    instead of a host pass over each; any other launch checks them on the host first."""

    def _kernel_checks(self, code, inf, joint_count):
        """``(zeroed (1,) int32 flags array, its NumPy view)`` of a launch that checks unchecked
        inputs (the CPU's), or None (checked inputs; or checked on the host now, where no packet
        kernel runs)."""
        if not self._unchecked:
            return None
        if not K.takes_packets(code, inf.running_sum, inf.groups, joint_count,
                               self.device):
            self._check_values(joint_count)
            return None
        flags = self._cache.get(("checks",))
        if flags is None:
            a = wp.zeros(1, dtype=wp.int32, device=self.device)
            flags = self._cache[("checks",)] = a, a.numpy()
        else:
            flags[1][0] = 0
        return flags

    def _check_values(self, joint_count=None):
        """The host checks of the constructor and of the joint count (unless None), for
        unchecked inputs: ValueError naming the array and what is wrong."""
        problem = within_float32(self._rest_points)
        if problem:
            raise InputError(f"points: {problem} coordinates")
        self.influences.check_values()
        if joint_count is None:
            return
        self.influences.check_joint_count(joint_count)
        self._unchecked = False

    _reuse_output = True
    """Small results (:data:`_SMALL_RESULT`) go through one reused output buffer and leave as a
    copy (:class:`_OneCall`: a fresh output, returned as it is)."""

    _copy_uploads = True
    """False: CPU uploads alias the caller's float32 (and int32) arrays (:class:`_OneCall`)."""

    _layout_order = "weight"
    """The influence layout of the default sign rule: sorted by weight once ("weight"), or
    "input" order with the pivot searched per vertex by the kernels (:class:`_OneCall`: no
    layout pass for a single call)."""

    def _upload(self, pts, linear=False):
        """(Fp, N, 3) mesh-space rows → bind space on the device (``linear``: directions), in
        float32: the identity geom-bind transform is skipped, any other is one (Fp·N, 3) @ (3, 3)
        product."""
        x = np.asarray(pts, dtype=np.float32)
        if not self._identity_bind:
            g = self.geom_bind_transform.astype(np.float32)
            flat = x.reshape(-1, 3) @ g[:3, :3].T
            if not linear:
                flat += g[:3, 3]
            x = flat.reshape(x.shape)
        elif x.flags.c_contiguous:  # plain strides: a (1, N, 3) view of (N, 3) has a 0 first
            x = x.reshape(-1, 3).reshape(x.shape)  # stride, a non-contiguous Warp array
        copy = self._copy_uploads or not self.device.is_cpu
        return wp.array(x, dtype=wp.vec3, device=self.device, copy=copy)

    def _check_method(self, method, points=True):
        code = _method_code(method)
        if code == K.BLEND and self._blend.shape[0] == 0:
            raise InputError('method "blend" needs blend_weights')
        if code == K.COR and points and self.faces is None:
            raise InputError('method "cor" needs faces (the mesh triangles): pass faces=')
        return code

    _BUFFERS = {
        "joints": dict(affines=mat34, dqs=vec8, residuals=wp.mat33),
        "vectors": dict(linears=wp.mat33, rotations=wp.quat, normal_linears=wp.mat33,
                        normal_residuals=wp.mat33, normal_rotations=wp.quat),
        "rates": dict(affines=mat34, dqs=vec8, residuals=wp.mat33),
    }

    def _buffers(self, kind, frames, joints):
        """Per-(frame, joint) work arrays, allocated once per shape and reused across calls: a
        :class:`~dqskin.kernels.skin.Joints` ("joints"), a
        :class:`~dqskin.kernels.velocity.JointRates` ("rates") or a dict ("vectors")."""
        key = (kind, frames, joints)
        buf = self._cache.get(key)
        if buf is None:
            buf = {k: wp.empty((frames, joints), dtype=t, device=self.device)
                   for k, t in self._BUFFERS[kind].items()}
            if kind == "joints":
                flags = wp.zeros(frames, dtype=wp.int32, device=self.device)
                buf = K.joints(has_residual=flags, **buf)
                # read back each call: on the CPU a NumPy view made once (a view costs per call)
                self._cache[("has_residual", frames, joints)] = (
                    flags.numpy() if self.device.is_cpu else flags)
            elif kind == "rates":
                from .kernels import velocity as KV  # (defined on a velocity bake's first use)
                buf = KV.joint_rates(**buf)
            self._cache[key] = buf
        return buf

    def _upload_transforms(self, name, skinning_transforms):
        d = self.device
        xs = skinning_transforms
        if (type(xs) is np.ndarray and xs.dtype.kind == "f" and xs.ndim in (3, 4)
                and xs.shape[-2:] == (4, 4)):  # the common case, checked cheaply
            batched = xs.ndim == 4
            xs = xs if batched else xs[None]
        elif isinstance(xs, wp.array):
            if xs.dtype != wp.mat44 or xs.ndim != 2 or xs.device != d:
                raise InputError(f"{name}: a Warp array must be 2-D (F, J) of wp.mat44 on {d}, got "
                                 f"{xs.ndim}-D {xs.dtype} on {xs.device}")
            return xs, True  # used in place, unchecked: a non-finite entry gives NaN everywhere
        else:
            xs, batched = _transforms(name, skinning_transforms)
        if within_float32(xs):  # NaN, inf, beyond float32: one pass, no copy
            check_finite(name, xs, 1)  # then name frame and joint
        # one device buffer per argument and shape, refilled each call (no allocation)
        key = ("transforms", name) + xs.shape[:2]
        buf = self._cache.get(key)
        if buf is None:
            arr = wp.empty(xs.shape[:2], dtype=wp.mat44, device=d)
            buf = self._cache[key] = (arr, arr.numpy() if d.is_cpu else None)
        if buf[1] is not None:
            buf[1][...] = xs  # the CPU array's memory, cast to float32 in place
        else:
            buf[0].assign(np.ascontiguousarray(xs, dtype=np.float32))
        return buf[0], batched

    def _prepare(self, skinning_transforms, kind="points", derivatives=None, affines_only=False):
        """Per-joint data for ``kind`` ("points", "vectors", "derivatives" with ``derivatives``);
        ``affines_only``: only what LBS reads (the 3×4 affines of ``prep["joints"]`` and of the
        rates, the linear parts and their inverse transposes for directions)."""
        x, batched = self._upload_transforms("skinning_transforms", skinning_transforms)
        frames, joints = x.shape
        self.influences.check_joint_count(joints)
        prep = {"joints": self._buffers("joints", frames, joints)}
        if kind == "derivatives":
            xd, _ = self._upload_transforms("skinning_transform_derivatives", derivatives)
            if xd.shape != x.shape:
                raise InputError(f"skinning_transforms {x.shape} and "
                                 f"skinning_transform_derivatives {xd.shape} must have the same "
                                 "shape")
            prep["rates"] = self._buffers("rates", frames, joints)
            from .kernels import velocity as KV
            KV.prepare(xforms=x, xform_derivatives=xd, device=self.device,
                       affines_only=affines_only, **prep)
            return prep, frames, batched
        K.prepare_points(xforms=x, device=self.device, affines_only=affines_only, **prep)
        if kind == "vectors":
            vec = self._buffers("vectors", frames, joints)
            K.prepare_vectors(xforms=x, device=self.device, linears_only=affines_only, **vec)
            prep.update(vec)
        return prep, frames, batched

    def _rest(self, name, points, frames, linear=False):
        """Uploaded rest points, or ``points`` (V, 3) / (F, V, 3) replacing them."""
        if points is None:
            return self._points
        p, _ = frames_of(name, points, frames, self.vertex_count, finite=True, dtype=np.float32)
        return self._upload(p, linear)

    def _output(self, out, output_transforms, frames, normals):
        """Apply per-frame output transforms (F, 4, 4) to ``out`` (F, N) in place, on the device."""
        if output_transforms is None:
            return
        xf = check_transforms("output_transforms", as_array(
            "output_transforms", output_transforms, np.float64, (4, 4)).reshape(-1, 1, 4, 4))[:, 0]
        if xf.shape[0] not in (1, frames):
            raise InputError(f"output_transforms: expected (4, 4) or ({frames}, 4, 4), got "
                             f"{xf.shape}")
        xf = np.broadcast_to(xf, (frames, 4, 4))
        if normals:
            try:
                lin = np.linalg.inv(xf[:, :3, :3]).transpose(0, 2, 1)
            except np.linalg.LinAlgError:
                raise InputError("output_transforms: singular, normals cannot follow") from None
            xf = np.zeros((frames, 4, 4))
            xf[:, :3, :3] = lin
            xf[:, 3, 3] = 1.0
        xforms: wp.array = wp.array(xf.astype(np.float32), dtype=wp.mat44, device=self.device)
        K.transform_frames(xforms=xforms, normalize=normals, values=out, device=self.device)

    @staticmethod
    def _result(out, batched, as_warp):
        if as_warp:
            return out
        res = out.numpy()
        return res if batched else res[0]

    def skin(self, skinning_transforms: npt.ArrayLike | wp.array, method: Method = "dqs", *,
             points: npt.ArrayLike | None = None, output_transforms: npt.ArrayLike | None = None,
             sign_reference: SignReference = DEFAULT_SIGN_REFERENCE,
             as_warp: bool = False) -> np.ndarray | wp.array:
        """Skin the points for one or many frames.

        Parameters
        ----------
        skinning_transforms : (J, 4, 4) or (F, J, 4, 4) float, or wp.array2d of wp.mat44 (F, J)
            Bind-relative joint transforms, column-vector convention. A Warp array on this
            skinner's device is used in place (no copy).
        method : {"dqs", "lbs", "blend", "cor"}
        points : (V, 3) or (F, V, 3) float, optional
            Rest points replacing the uploaded ones (e.g. after blend shapes), mesh space.
        output_transforms : (4, 4) or (F, 4, 4) float, optional
            Applied to the skinned points on the device (e.g. skeleton space → prim space).
        sign_reference : {"largest_weight", "running_sum"}
            Sign rule of the rotation blends (:data:`~dqskin.options.SignReference`); LBS ignores
            it.
        as_warp : bool
            Return the device array ``wp.array2d(dtype=wp.vec3)`` of shape (F, V) without a copy.

        Returns
        -------
        (V, 3) or (F, V, 3) float32
            Skinned points in skeleton space (or where ``output_transforms`` take them); (F, V, 3)
            when the transforms have a frame axis.
        """
        with self._lock:  # the per-shape work buffers are shared between calls
            code = self._check_method(method)
            inf = self._influences(code, sign_reference)
            try:
                prep, frames, batched = self._prepare(skinning_transforms,
                                                      affines_only=code == K.LBS)
            except ValueError as exc:
                if not self._unchecked:
                    raise
                # in the host-checked order: a bad value first (as the constructor names it),
                # then the transforms and the joint count they give (index range now known)
                self._check_values()
                self._prepare(skinning_transforms, affines_only=code == K.LBS)
                raise exc
            src = self._rest("points", points, frames)
            # small results go through one reused device buffer and leave as a NumPy copy
            small = (not as_warp and frames * self.vertex_count <= _SMALL_RESULT
                     and self._reuse_output)
            out, view = self._cache.get(("out", frames), (None, None)) if small else (None, None)
            if out is None:
                out = KB.empty((frames, self.vertex_count), wp.vec3, self.device)
                if small and self.device.is_cpu:  # its NumPy view, made once
                    view = out.numpy()
                if small:
                    self._cache[("out", frames)] = out, view
            flags = self._cache[("has_residual",) + prep["joints"].dqs.shape]
            rigid = code in (K.DQS, K.COR) and not np.count_nonzero(
                flags if isinstance(flags, np.ndarray) else flags.numpy())
            checks = self._kernel_checks(code, inf, prep["joints"].affines.shape[1])
            K.skin_points(method=code, points=src, influences=inf, joints=prep["joints"],
                          rigid=rigid, out=out, device=self.device,
                          flags=None if checks is None else checks[0])
            if checks is not None and checks[1][0]:  # name the problem as the host would
                self._check_values(prep["joints"].affines.shape[1])
                raise RuntimeError("skin_points: the kernel refused inputs the host accepts")
            self._output(out, output_transforms, frames, normals=False)
            if view is not None:
                return (view if batched else view[0]).copy()
            res = self._result(out, batched, as_warp)
            return res.copy() if small else res

    def skin_vectors(self, skinning_transforms: npt.ArrayLike | wp.array, vectors: npt.ArrayLike,
                     method: Method = "dqs", *, kind: VectorKind = "normal",
                     vector_vertex: npt.ArrayLike | None = None,
                     output_transforms: npt.ArrayLike | None = None,
                     sign_reference: SignReference = DEFAULT_SIGN_REFERENCE,
                     as_warp: bool = False) -> np.ndarray | wp.array:
        """Skin normals or tangents; results are unit length. ``method="cor"`` turns directions
        as DQS does (the same rotation; its centers only move points).

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
        sign_reference : {"largest_weight", "running_sum"}
            Sign rule of the rotation blends (:data:`~dqskin.options.SignReference`).

        Returns
        -------
        (N, 3) or (F, N, 3) float32, skeleton space.
        """
        if kind not in get_args(VectorKind):
            raise InputError(f'kind must be "normal" or "tangent", got {kind!r}')
        with self._lock:
            code = self._check_method(method, points=False)
            inf = self._influences(K.DQS if code == K.COR else code, sign_reference)
            prep, frames, batched = self._prepare(skinning_transforms, "vectors",
                                                  affines_only=code == K.LBS)
            vec, _ = frames_of("vectors", vectors, frames, finite=True)
            n = vec.shape[1]
            if vector_vertex is None:
                if n != self.vertex_count:
                    raise InputError(f"vectors: {n} vectors for {self.vertex_count} points; pass "
                                     "vector_vertex for face-varying data")
                vv: np.ndarray = np.arange(n, dtype=np.int32)
            else:
                vv = np.asarray(vector_vertex, dtype=np.int64).reshape(-1)
                if vv.shape != (n,) or (n and (vv.min() < 0 or vv.max() >= self.vertex_count)):
                    raise InputError(f"vector_vertex: expected ({n},) indices into "
                                     f"{self.vertex_count} points")
            g = self.geom_bind_transform[:3, :3]
            try:
                gm = np.linalg.inv(g).T if kind == "normal" else g
            except np.linalg.LinAlgError:
                raise InputError("geom_bind_transform: singular, normals cannot follow") from None
            d = self.device
            src: wp.array = wp.array((vec @ gm.T).astype(np.float32), dtype=wp.vec3, device=d)
            if kind == "normal":
                lin, rot, res = (prep["normal_linears"], prep["normal_rotations"],
                                 prep["normal_residuals"])
            else:
                lin, rot, res = prep["linears"], prep["rotations"], prep["joints"].residuals
            out = KB.empty((frames, n), wp.vec3, d)
            K.skin_vectors(method=code, vectors=src,
                           vector_vertex=wp.array(vv.astype(np.int32), dtype=wp.int32, device=d),
                           influences=inf,
                           linears=lin, rotations=rot, residuals=res,
                           has_residual=prep["joints"].has_residual, out=out, device=d)
            if output_transforms is not None:
                xf = np.array(np.broadcast_to(as_array("output_transforms", output_transforms,
                                                       np.float64, (4, 4)), (frames, 4, 4)))
                xf[:, :3, 3] = 0.0
                self._output(out, xf, frames, normals=kind == "normal")
                if kind != "normal":  # tangents: the linear part, then unit length again
                    self._output(out, np.eye(4), frames, normals=True)
            return self._result(out, batched, as_warp)

    def skin_velocities(self, skinning_transforms: npt.ArrayLike | wp.array,
                        skinning_transform_derivatives: npt.ArrayLike | wp.array,
                        method: Method = "dqs", *, points: npt.ArrayLike | None = None,
                        point_velocities: npt.ArrayLike | None = None,
                        sign_reference: SignReference = DEFAULT_SIGN_REFERENCE,
                        as_warp: bool = False) -> np.ndarray | wp.array:
        """Velocities of the skinned points, by the chain rule (:mod:`dqskin.kernels.velocity`).

        Parameters
        ----------
        skinning_transforms, skinning_transform_derivatives : (J, 4, 4) or (F, J, 4, 4) float
            Bind-relative transforms ``A`` and ``dA/dt``, column-vector convention.
        method : {"dqs", "lbs", "blend", "cor"}
        points : (V, 3) or (F, V, 3) float, optional
            Rest points replacing the uploaded ones, mesh space.
        point_velocities : (V, 3) or (F, V, 3) float, optional
            ``d points / dt`` in mesh space (e.g. from blend shapes); zero by default.
        sign_reference : {"largest_weight", "running_sum"}
            Sign rule of the rotation blends (:data:`~dqskin.options.SignReference`).

        Returns
        -------
        (V, 3) or (F, V, 3) float32
            ``d/dt`` of the skinned points, skeleton space, per unit of time of the derivatives.
        """
        with self._lock:
            code = self._check_method(method)
            inf = self._influences(code, sign_reference)
            prep, frames, batched = self._prepare(skinning_transforms, "derivatives",
                                                  skinning_transform_derivatives,
                                                  affines_only=code == K.LBS)
            src = self._rest("points", points, frames)
            vel = (None if point_velocities is None else
                   self._rest("point_velocities", point_velocities, frames, linear=True))
            out = KB.empty((frames, self.vertex_count), wp.vec3, self.device)
            from .kernels import velocity as KV
            KV.velocities(method=code, points=src, point_velocities=vel, influences=inf,
                          out=out, device=self.device, **prep)
            return self._result(out, batched, as_warp)


def skin_points(points: npt.ArrayLike, joint_indices: npt.ArrayLike, joint_weights: npt.ArrayLike,
                skinning_transforms: npt.ArrayLike, method: Method = "dqs", *,
                geom_bind_transform: npt.ArrayLike | None = None,
                blend_weights: npt.ArrayLike | None = None, faces: npt.ArrayLike | None = None,
                sign_reference: SignReference = DEFAULT_SIGN_REFERENCE,
                device: Device = None) -> np.ndarray:
    """Skin points with LBS, DQS, a per-vertex blend or optimized centers of rotation (one call;
    see :class:`Skinner`).

    Parameters
    ----------
    points : (V, 3) float
        Rest points, mesh space.
    joint_indices : (V, K) int
    joint_weights : (V, K) float
    skinning_transforms : (J, 4, 4) or (F, J, 4, 4) float
        Bind-relative joint transforms (world ∘ inverse bind), column-vector convention.
    method : {"dqs", "lbs", "blend", "cor"}
    geom_bind_transform : (4, 4) float, optional
    blend_weights : (V,) float, optional
        DQS fraction per vertex, required for ``"blend"``.
    faces : (T, 3) int, optional
        Triangles, required for ``"cor"``.
    sign_reference : {"largest_weight", "running_sum"}
        Sign rule of the rotation blends (:data:`~dqskin.options.SignReference`).
    device : str, optional

    Returns
    -------
    (V, 3) or (F, V, 3) float32
        Skinned points in skeleton space.
    """
    sk = _OneCall(points, joint_indices, joint_weights, geom_bind_transform=geom_bind_transform,
                  blend_weights=blend_weights, faces=faces, device=device,
                  unchecked=_kernel_checkable(points, joint_indices, joint_weights, method,
                                              sign_reference, geom_bind_transform, device))
    return cast(np.ndarray, sk.skin(skinning_transforms, method, sign_reference=sign_reference))


def _kernel_checkable(points, joint_indices, joint_weights, method, sign_reference,
                      geom_bind_transform, device):
    """Whether a one-shot call may leave the checks of its values to the packet kernel
    (:attr:`Skinner._unchecked`): the caller's arrays are read in place, as they are (CPU;
    (V, 3) float32 points, (V, 4) int32 indices and float32 weights, C-contiguous; no geom-bind
    transform), by LBS or DQS (either sign rule): one host pass over each array fewer."""
    if method not in ("lbs", "dqs") or sign_reference not in SIGN_REFERENCES:
        return False
    if geom_bind_transform is not None and not np.array_equal(geom_bind_transform, np.eye(4)):
        return False
    arrays = ((points, np.float32, 3), (joint_indices, np.int32, 4),
              (joint_weights, np.float32, 4))
    if not all(isinstance(a, np.ndarray) and a.dtype == t and a.ndim == 2 and a.shape[1] == k
               and a.flags.c_contiguous for a, t, k in arrays):
        return False
    return resolve_device(device).is_cpu


def skin_normals(normals: npt.ArrayLike, joint_indices: npt.ArrayLike,
                 joint_weights: npt.ArrayLike, skinning_transforms: npt.ArrayLike,
                 method: Method = "dqs", *, geom_bind_transform: npt.ArrayLike | None = None,
                 blend_weights: npt.ArrayLike | None = None,
                 normal_vertex: npt.ArrayLike | None = None,
                 sign_reference: SignReference = DEFAULT_SIGN_REFERENCE,
                 device: Device = None) -> np.ndarray:
    """Skin normals consistently with :func:`skin_points` (inverse-transpose for LBS and scale).

    Parameters
    ----------
    normals : (N, 3) float
        Mesh-space normals; ``N == V`` unless ``normal_vertex`` maps each normal to its vertex.
    joint_indices, joint_weights : (V, K)
    skinning_transforms : (J, 4, 4) or (F, J, 4, 4) float
    normal_vertex : (N,) int, optional
        Vertex of each normal (faceVarying normals).
    sign_reference : {"largest_weight", "running_sum"}
        Sign rule of the rotation blends (:data:`~dqskin.options.SignReference`).

    Returns
    -------
    (N, 3) or (F, N, 3) float32
        Unit normals in skeleton space.
    """
    idx = np.asarray(joint_indices)
    sk = Skinner(np.zeros((idx.shape[0], 3)), joint_indices, joint_weights,
                 geom_bind_transform=geom_bind_transform, blend_weights=blend_weights,
                 device=device)
    return cast(np.ndarray, sk.skin_vectors(skinning_transforms, normals, method, kind="normal",
                                            vector_vertex=normal_vertex,
                                            sign_reference=sign_reference))


class _OneCall(Skinner):
    """The skinner of one :func:`skin_points` call: nothing outlives the call, so on the CPU the
    caller's float32 points and (V, 4k) int32/float32 influences are used in place instead of
    copied (a copy of fresh memory costs page faults comparable to skinning the points), and the
    influences stay in input order (the kernels search each vertex's pivot: cheaper than one
    layout pass when the points are skinned once)."""

    _copy_uploads = False
    _layout_order = "input"
    _reuse_output = False  # the result is the output array itself, not a copy

    def __init__(self, points, joint_indices, joint_weights, *, unchecked=False, **kwargs):
        self._unchecked = unchecked
        self._given = (points, joint_indices, joint_weights)
        super().__init__(points, joint_indices, joint_weights, **kwargs)
        self._cache = _thread_buffers(self.device)

    def _device_mesh(self):
        if not self._unchecked:
            return super()._device_mesh()
        return self._views(False)

    def _influences(self, code, sign_reference):
        if (self._unchecked and code == K.DQS
                and _check_sign_reference(sign_reference) == "running_sum"):
            return self._views(True)[1]
        return super()._influences(code, sign_reference)

    def _views(self, running):
        """With :attr:`_unchecked` (the caller's arrays read in place, as they are: CPU, (V, 3)
        float32 points, (V, 4) int32 indices and float32 weights, C-contiguous): ``(points
        (1, V), InfluenceLayout)`` of the default rule (``running``: of the running sum) from the
        thread's cache (:func:`_thread_buffers`), so that a call makes no Warp objects for its
        inputs. The first call on the same memory builds them as :class:`Skinner` does, then
        points their arrays at views that own nothing (an address, a shape and a type: one made
        for an earlier array at the same address with the same shape views this one, and keeps
        nothing alive)."""
        points, idx, wts = self._given
        addresses = points.ctypes.data, idx.ctypes.data, wts.ctypes.data
        key = ("views", *addresses, self.vertex_count, running)
        cache = _thread_buffers(self.device)  # (self._cache is set after the constructor)
        hit = cache.get(key)
        if hit is None:
            layout = (super()._influences(K.DQS, "running_sum") if running
                      else super()._device_mesh()[1])
            d, V = self.device, self.vertex_count
            layout.indices = wp.array(ptr=addresses[1], shape=(V,), dtype=wp.vec4i, device=d)
            layout.weights = wp.array(ptr=addresses[2], shape=(V,), dtype=wp.vec4, device=d)
            layout.blend = _empty(wp.float32, d)  # (LBS and DQS read none: nothing of this call)
            hit = cache[key] = (
                wp.array(ptr=addresses[0], shape=(1, V), dtype=wp.vec3, device=d), layout)
        return hit
