"""Offscreen renderer: Warp ray casting against a ``wp.Mesh`` BVH, no display or OpenGL.

Images are ``(H, W, 3)`` (or ``(H, W, 4)`` with ``transparent=True``) ``uint8`` arrays, row 0 at the
top. A :class:`MeshRenderer` uploads a triangle mesh once and, for later frames with the same
topology, moves the points and refits the BVH instead of rebuilding it. Shading is Lambert with a
camera-attached key light plus ambient and rim terms (see :class:`Shading`); an optional per-vertex
scalar is shown as a heat map through a Matplotlib colour map, interpolated barycentrically. Each
image is rendered at ``supersample``× the size and box-filtered down (anti-aliasing).

Cameras (:class:`Camera`) use world units and the column-vector convention of the package; frame
one camera from the bounds of every frame and method you compare so the images line up.
"""

import os
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt
import warp as wp

from .._warp import Device, resolve_device
from ..errors import InputError
from ..files.atomic import atomic_path
from ..kernels import render as KR
from ..progress import progress_bar
from ..topology import check_faces, incidence
from .defaults import VIEWS

__all__ = ["ADAPTIVE_DEPTH_JUMP", "ADAPTIVE_NORMAL_ANGLE", "VIEWS", "Camera", "MeshRenderer",
           "Shading", "add_colorbar", "colormap_lut", "render", "save_png", "side_by_side"]


ADAPTIVE_DEPTH_JUMP = 0.01
"""Adaptive anti-aliasing: relative depth difference between neighbouring centre rays that marks
an edge (1% of the nearer hit's distance)."""

ADAPTIVE_NORMAL_ANGLE = 25.0
"""Adaptive anti-aliasing: angle in degrees between neighbouring centre rays' shading normals that
marks an edge (a crease or an occlusion)."""

_UP = {"Y": np.array([0.0, 1.0, 0.0]), "Z": np.array([0.0, 0.0, 1.0])}
# Direction from the target to the eye, per up axis: Y-up characters face +Z (USD, glTF);
# Z-up characters face -Y (Blender).
_FRONT = {"Y": np.array([0.0, 0.0, 1.0]), "Z": np.array([0.0, -1.0, 0.0])}
_THREE_QUARTER_AZIMUTH = np.radians(45.0)
_THREE_QUARTER_ELEVATION = np.radians(20.0)


def _vec3(name: str, x: npt.ArrayLike) -> np.ndarray:
    a = np.asarray(x, dtype=np.float64)
    if a.shape != (3,) or not np.all(np.isfinite(a)):
        raise InputError(f"{name}: expected 3 finite numbers, got {np.asarray(x).tolist()!r}")
    return a


def _up_axis(up_axis: str) -> str:
    if up_axis not in _UP:
        raise InputError(f'up_axis must be "Y" or "Z", got {up_axis!r}')
    return up_axis


def _view_direction(view: str | npt.ArrayLike, up_axis: str) -> np.ndarray:
    """Unit vector from the target to the eye for a named view or an explicit (3,) direction.

    ``front`` looks at the character's front, ``side`` from its left-hand side (+X),
    ``three_quarter`` from 45° between the two, raised 20° above the horizon.
    """
    up = _UP[_up_axis(up_axis)]
    front = _FRONT[up_axis]
    if isinstance(view, str):
        if view == "front":
            return front.copy()
        if view == "side":
            return np.array([1.0, 0.0, 0.0])
        if view == "three_quarter":
            horizontal = (np.cos(_THREE_QUARTER_AZIMUTH) * front
                          + np.sin(_THREE_QUARTER_AZIMUTH) * np.array([1.0, 0.0, 0.0]))
            return (np.cos(_THREE_QUARTER_ELEVATION) * horizontal
                    + np.sin(_THREE_QUARTER_ELEVATION) * up)
        raise InputError(f"view must be one of {VIEWS} or a 3-vector, got {view!r}")
    d = _vec3("view", view)
    n = np.linalg.norm(d)
    if n == 0:
        raise InputError("view: direction has zero length")
    return d / n


@dataclass(frozen=True, eq=False)
class Camera:
    """A pinhole (``fov``) or orthographic (``fov=None``, ``ortho_height``) camera.

    Attributes
    ----------
    eye, target : (3,) float64
        World positions of the eye and of the point looked at.
    up : (3,) float64
        Approximate up direction (made orthogonal to the view direction).
    fov : float or None
        Vertical field of view in degrees; None for an orthographic projection.
    ortho_height : float or None
        Orthographic only: world-space height covered by the full image.

    The horizontal extent follows from the image aspect ratio ``width / height``. Pixel ``(x, y)``
    (x right, y down, integer at pixel corners) sees normalized device coordinates
    ``(2x/W − 1, 1 − 2y/H)``.
    """

    eye: np.ndarray
    target: np.ndarray
    up: np.ndarray = field(default_factory=lambda: np.array([0.0, 1.0, 0.0]))
    fov: float | None = 30.0
    ortho_height: float | None = None

    def __post_init__(self) -> None:
        for name in ("eye", "target", "up"):
            object.__setattr__(self, name, _vec3(name, getattr(self, name)))
        if self.fov is None:
            if self.ortho_height is None or not self.ortho_height > 0:
                raise InputError("ortho_height: an orthographic camera (fov=None) needs a "
                                 "positive ortho_height")
        elif not 0 < self.fov < 180:
            raise InputError(f"fov: expected degrees in (0, 180), got {self.fov!r}")
        forward = self.target - self.eye
        if np.linalg.norm(forward) == 0:
            raise InputError("eye and target coincide")
        if np.linalg.norm(np.cross(forward, self.up)) <= 1e-9 * np.linalg.norm(forward):
            raise InputError("up: parallel to the view direction")

    @property
    def orthographic(self) -> bool:
        return self.fov is None

    def basis(self) -> np.ndarray:
        """Orthonormal ``(forward, right, up)`` (3, 3) float64 rows, right-handed screen axes."""
        forward = self.target - self.eye
        forward = forward / np.linalg.norm(forward)
        right = np.cross(forward, self.up)
        right /= np.linalg.norm(right)
        return np.stack([forward, right, np.cross(right, forward)])

    def half_extents(self, aspect: float) -> tuple[float, float]:
        """``(half_w, half_h)``: tangents of the half field of view, or orthographic half sizes."""
        if self.fov is None:  # orthographic
            assert self.ortho_height is not None  # (__post_init__ requires it)
            half_h = 0.5 * self.ortho_height
        else:
            half_h = float(np.tan(np.radians(self.fov) / 2))
        return half_h * aspect, half_h

    def project(self, points: npt.ArrayLike, width: int, height: int) -> np.ndarray:
        """Pixel coordinates of world points.

        Parameters
        ----------
        points : (N, 3) float
        width, height : int
            Image size in pixels.

        Returns
        -------
        (N, 2) float64
            ``(x, y)``: x to the right, y down, integer values at pixel corners.
        """
        p = np.asarray(points, dtype=np.float64).reshape(-1, 3) - self.eye
        forward, right, up = self.basis()
        half_w, half_h = self.half_extents(width / height)
        depth = p @ forward if not self.orthographic else 1.0
        x = (p @ right) / depth / half_w
        y = (p @ up) / depth / half_h
        return np.stack([(x + 1) * width / 2, (1 - y) * height / 2], axis=-1)

    @classmethod
    def frame(cls, bounds_min: npt.ArrayLike, bounds_max: npt.ArrayLike,
              view: str | npt.ArrayLike = "front", *, up_axis: str = "Y", fov: float | None = 30.0,
              aspect: float = 1.0, margin: float = 1.05) -> "Camera":
        """A camera that sees the whole box ``[bounds_min, bounds_max]``.

        Parameters
        ----------
        bounds_min, bounds_max : (3,) float
            World bounds; take them over every frame and method compared, so that the images of
            one comparison share one camera and line up.
        view : {"front", "side", "three_quarter"} or (3,) float
            Named view (see :func:`_view_direction`) or the direction from the target to the eye.
        up_axis : {"Y", "Z"}
        fov : float or None
            Vertical field of view in degrees; None for orthographic.
        aspect : float
            Image ``width / height`` the camera will render.
        margin : float
            Extra room around the box, as a factor on its projected half extents.

        The target is the box centre. In perspective the eye distance is the smallest one for
        which all eight corners project inside the image (shrunk by ``margin``).
        """
        lo, hi = _vec3("bounds_min", bounds_min), _vec3("bounds_max", bounds_max)
        if np.any(hi < lo):
            raise InputError("bounds_max: below bounds_min")
        center = 0.5 * (lo + hi)
        back = _view_direction(view, up_axis)
        up = _UP[up_axis]
        corners = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1])
                            for z in (lo[2], hi[2])]) - center
        probe = cls(center + back, center, up, fov=fov, ortho_height=1.0)
        _, right, cam_up = probe.basis()
        x, y, z = np.abs(corners @ right), np.abs(corners @ cam_up), corners @ back
        radius = max(float(np.linalg.norm(hi - lo)) / 2, 1e-6)
        if fov is None:
            height = 2 * margin * max(y.max(), x.max() / aspect, 1e-6)
            return cls(center + back * 2 * radius, center, up, fov=None, ortho_height=height)
        half_w, half_h = probe.half_extents(aspect)
        distance = float(np.max(z + margin * np.maximum(x / half_w, y / half_h)))
        return cls(center + back * max(distance, 1e-6), center, up, fov=fov)

    @classmethod
    def frame_point(cls, center: npt.ArrayLike, radius: float, view: str | npt.ArrayLike = "front",
                    *, up_axis: str = "Y", fov: float | None = 30.0,
                    aspect: float = 1.0) -> "Camera":
        """A close-up: the sphere ``(center, radius)`` (e.g. around one joint) just fills the image.

        Parameters as in :meth:`frame`; ``radius`` > 0 in world units.
        """
        c = _vec3("center", center)
        if not radius > 0:
            raise InputError(f"radius: expected > 0, got {radius!r}")
        back = _view_direction(view, up_axis)
        up = _UP[up_axis]
        if fov is None:
            return cls(c + back * 2 * radius, c, up, fov=None,
                       ortho_height=2 * radius * max(1.0, 1.0 / aspect))
        half = np.radians(fov) / 2
        half = min(half, np.arctan(np.tan(half) * aspect))
        return cls(c + back * radius / np.sin(half), c, up, fov=fov)

    def _params(self, aspect: float) -> KR.CameraParams:
        forward, right, up = self.basis()
        half_w, half_h = self.half_extents(aspect)
        p = KR.CameraParams()
        p.eye, p.forward, p.right, p.up = (wp.vec3(*map(float, v))
                                           for v in (self.eye, forward, right, up))
        p.half_w, p.half_h = float(half_w), float(half_h)
        p.orthographic = int(self.orthographic)
        return p


@dataclass(frozen=True)
class Shading:
    """Colours (linear RGB in [0, 1]) and lights.

    ``light`` is the key-light direction in camera axes ``(right, up, toward the viewer)``; it is
    normalized, so the default comes from the upper left, in front. A surface point with unit
    normal ``n`` (flipped to face the viewer) and unit direction ``v`` to the eye gets
    ``albedo·(ambient + diffuse·max(n·l, 0)) + rim·(1 − max(n·v, 0))^rim_power``, clamped to
    [0, 1]; ``lit=False`` shows the albedo alone (exact heat-map colours). ``smooth`` interpolates
    area-weighted vertex normals; otherwise faces are flat.
    """

    base_color: tuple[float, float, float] = (0.78, 0.78, 0.80)
    background: tuple[float, float, float] = (1.0, 1.0, 1.0)
    light: tuple[float, float, float] = (-0.4, 0.6, 1.0)
    ambient: float = 0.25
    diffuse: float = 0.75
    rim: float = 0.25
    rim_power: float = 3.0
    lit: bool = True
    smooth: bool = True
    nan_color: tuple[float, float, float] = (0.5, 0.5, 0.5)

    def light_world(self, camera: Camera) -> np.ndarray:
        """Unit world direction from the surface to the key light, (3,) float64."""
        forward, right, up = camera.basis()
        lr, lu, lb = _vec3("light", self.light)
        d = lr * right + lu * up - lb * forward
        n = np.linalg.norm(d)
        if n == 0:
            raise InputError("light: direction has zero length")
        return d / n

    def _params(self, camera: Camera) -> KR.ShadingParams:
        p = KR.ShadingParams()
        p.light = wp.vec3(*map(float, self.light_world(camera)))
        p.base_color = wp.vec3(*map(float, _vec3("base_color", self.base_color)))
        p.background = wp.vec3(*map(float, _vec3("background", self.background)))
        p.ambient, p.diffuse = float(self.ambient), float(self.diffuse)
        p.rim, p.rim_power = float(self.rim), float(self.rim_power)
        p.lit, p.smooth = int(bool(self.lit)), int(bool(self.smooth))
        return p


def colormap_lut(colormap: str = "viridis", size: int = 256) -> np.ndarray:
    """RGB samples of a Matplotlib colour map at ``linspace(0, 1, size)``.

    Returns
    -------
    (size, 3) float32, linear in [0, 1].
    """
    import matplotlib

    try:
        cmap = matplotlib.colormaps[colormap]
    except KeyError:
        raise InputError(f"colormap: unknown Matplotlib colour map {colormap!r}") from None
    return cmap(np.linspace(0.0, 1.0, size))[:, :3].astype(np.float32)


def _check_mesh(points: npt.ArrayLike, faces: npt.ArrayLike) -> tuple[np.ndarray, np.ndarray]:
    pts = np.asarray(points, dtype=np.float64)
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise InputError(f"points: expected (V, 3), got {pts.shape}")
    if pts.shape[0] == 0:
        raise InputError("points: mesh has no points")
    if not np.all(np.isfinite(pts)):
        raise InputError("points: NaN or infinite coordinate")
    return pts.astype(np.float32), check_faces(faces, pts.shape[0])


class MeshRenderer:
    """A triangle mesh on a Warp device, ray cast from any camera.

    Parameters
    ----------
    points : (V, 3) float
        World positions.
    faces : (T, 3) int
        Triangles, indices into ``points``; T ≥ 1.
    device : str, optional
        Warp device; CUDA when present, else CPU.

    The ``wp.Mesh`` (BVH) is built once; :meth:`update` moves the points and refits it.
    """

    def __init__(self, points: npt.ArrayLike, faces: npt.ArrayLike, *,
                 device: Device = None) -> None:
        self.device = resolve_device(device)
        pts, f = _check_mesh(points, faces)
        d = self.device
        self.vertex_count, self.face_count = pts.shape[0], f.shape[0]
        self._faces: wp.array = wp.array(f.reshape(-1), dtype=wp.int32, device=d)
        offsets, vf = incidence(f, pts.shape[0])
        self._vf_offsets: wp.array = wp.array(offsets, dtype=wp.int32, device=d)
        self._vf_faces: wp.array = wp.array(vf, dtype=wp.int32, device=d)
        self._normals = wp.empty(pts.shape[0], dtype=wp.vec3, device=d)
        self.mesh = wp.Mesh(wp.array(pts, dtype=wp.vec3, device=d), self._faces)
        self._luts: dict[str, wp.array] = {}
        self._update_normals()

    def _update_normals(self) -> None:
        KR.vertex_normals(points=self.mesh.points, faces=self._faces, vf_offsets=self._vf_offsets,
                         vf_faces=self._vf_faces, out=self._normals, device=self.device)

    def update(self, points: npt.ArrayLike) -> None:
        """Move the vertices (same topology) and refit the BVH.

        Parameters
        ----------
        points : (V, 3) float
            New world positions, same V as at construction.
        """
        pts = np.asarray(points, dtype=np.float64)
        if pts.shape != (self.vertex_count, 3):
            raise InputError(f"points: expected ({self.vertex_count}, 3), got {pts.shape}")
        if not np.all(np.isfinite(pts)):
            raise InputError("points: NaN or infinite coordinate")
        self.mesh.points.assign(pts.astype(np.float32))
        self.mesh.refit()
        self._update_normals()

    def _lut(self, colormap: str) -> wp.array:
        if colormap not in self._luts:
            self._luts[colormap] = wp.array(colormap_lut(colormap), dtype=wp.vec3,
                                            device=self.device)
        return self._luts[colormap]

    def render(self, camera: Camera, *, width: int = 512, height: int = 512, supersample: int = 2,
               scalars: npt.ArrayLike | None = None,
               scalar_range: tuple[float, float] | None = None, colormap: str = "viridis",
               shading: Shading | None = None, transparent: bool = False, adaptive: bool = False,
               second_layer: dict[str, Any] | None = None
               ) -> np.ndarray | tuple[np.ndarray, np.ndarray]:
        """Ray cast the current mesh.

        Parameters
        ----------
        camera : Camera
        width, height : int
            Output size in pixels.
        supersample : int
            Rays per pixel along each axis (``supersample²`` per pixel), box-filtered.
        scalars : (V,) float, optional
            Per-vertex values shown as a heat map (interpolated barycentrically); NaN shows
            ``shading.nan_color``.
        scalar_range : (float, float), optional
            Values mapped to the ends of the colour map (clamped beyond); default the finite
            min and max of ``scalars``.
        colormap : str
            Matplotlib colour-map name.
        shading : Shading, optional
        transparent : bool
            Return RGBA with the background transparent (straight alpha).
        adaptive : bool
            Adaptive anti-aliasing: one ray through each pixel's centre, and the full
            ``supersample²`` rays only for pixels on an edge — where a 4-neighbour's centre ray
            hits and this one misses (or the reverse), lands more than
            :data:`ADAPTIVE_DEPTH_JUMP` deeper or nearer, or sees a normal more than
            :data:`ADAPTIVE_NORMAL_ANGLE` degrees apart. Silhouettes and occlusion edges come out
            as with full super-sampling at a fraction of the rays; smooth shading inside a
            surface is sampled once per pixel, and features thinner than a pixel that no centre
            ray hits are missed.
        second_layer : dict, optional
            A second image from the same rays, e.g. a heat map of the same pose: keys
            ``scalars``, ``scalar_range``, ``colormap``, ``shading`` as above (its
            ``background`` too; the first image's normals decide the adaptive edges).

        Returns
        -------
        (height, width, 3) uint8, or (height, width, 4) when ``transparent``; a pair of them
        with ``second_layer``.
        """
        shading = Shading() if shading is None else shading
        for name, v in (("width", width), ("height", height), ("supersample", supersample)):
            if int(v) != v or v < 1:
                raise InputError(f"{name}: expected a positive integer, got {v!r}")
        width, height, s = int(width), int(height), int(supersample)
        d = self.device
        layer_a = self._layer(camera, scalars, scalar_range, colormap, shading, "")
        layers = 1 if second_layer is None else 2
        layer_b = layer_a
        if second_layer is not None:
            extra = dict(second_layer)
            unknown = set(extra) - {"scalars", "scalar_range", "colormap", "shading"}
            if unknown:
                raise InputError(f"second_layer: unknown keys {sorted(unknown)}")
            layer_b = self._layer(camera, extra.get("scalars"), extra.get("scalar_range"),
                                  extra.get("colormap", "viridis"),
                                  extra.get("shading") or Shading(), "second_layer: ")
        n = width * height
        outs = [wp.empty((height, width, 4), dtype=wp.uint8, device=d) for _ in range(layers)]
        common = dict(mesh=self.mesh.id, faces=self._faces, normals=self._normals,
                      camera=camera._params(width / height), layer_a=layer_a, layer_b=layer_b,
                      layers=layers, device=d)
        if adaptive:
            def scratch(dtype, used=True):
                return wp.empty(n if used else 1, dtype=dtype, device=d)

            KR.render_adaptive(factor=s, transparent=transparent,
                              depth_jump=ADAPTIVE_DEPTH_JUMP,
                              normal_cos=float(np.cos(np.radians(ADAPTIVE_NORMAL_ANGLE))),
                              centres_a=scratch(wp.vec4), centres_b=scratch(wp.vec4, layers > 1),
                              depth=scratch(float), facing=scratch(wp.vec3), out_a=outs[0],
                              out_b=outs[-1] if layers > 1 else wp.empty((1, 1, 4),
                                                                         dtype=wp.uint8,
                                                                         device=d),
                              **common)
        else:
            sw, sh = width * s, height * s
            samples = [wp.empty(sw * sh, dtype=wp.vec4, device=d) for _ in range(layers)]
            KR.render(width=sw, height=sh, out_a=samples[0],
                     out_b=samples[-1] if layers > 1 else wp.empty(1, dtype=wp.vec4, device=d),
                     depth=wp.empty(sw * sh, dtype=float, device=d),
                     facing=wp.empty(sw * sh, dtype=wp.vec3, device=d), **common)
            for sample, out in zip(samples, outs):
                KR.downsample(samples=sample, factor=s, transparent=transparent, out=out,
                             device=d)
        images = [o.numpy() for o in outs]
        images = [img if transparent else img[..., :3].copy() for img in images]
        if second_layer is not None:
            return images[0], images[-1]
        return images[0]

    def _layer(self, camera: Camera, scalars: npt.ArrayLike | None,
               scalar_range: tuple[float, float] | None, colormap: str, shading: Shading,
               where: str) -> KR.Layer:
        """A :class:`dqskin.kernels.render.Layer`: constant colour or heat map, lit."""
        layer = KR.Layer()
        layer.lut = self._lut(colormap)
        layer.scalar_min, layer.scalar_scale = 0.0, 0.0
        if scalars is None:
            layer.scalars = wp.zeros(0, dtype=wp.float32, device=self.device)
        else:
            sv = np.asarray(scalars, dtype=np.float64).reshape(-1)
            if sv.shape != (self.vertex_count,):
                raise InputError(f"{where}scalars: expected ({self.vertex_count},), got "
                                 f"{np.shape(scalars)}")
            lo, hi = _scalar_range(sv, scalar_range)
            layer.scalar_min, layer.scalar_scale = lo, 1.0 / (hi - lo) if hi > lo else 0.0
            layer.scalars = wp.array(sv.astype(np.float32), dtype=wp.float32, device=self.device)
        layer.nan_color = wp.vec3(*map(float, _vec3("nan_color", shading.nan_color)))
        layer.shading = shading._params(camera)
        return layer


    def render_frames(self, frames: npt.ArrayLike, camera: Camera, *,
                      scalars: npt.ArrayLike | None = None, progress: bool = False,
                      **kwargs: Any) -> np.ndarray:
        """Render a sequence of poses of this mesh, refitting between frames.

        Parameters
        ----------
        frames : (F, V, 3) float
            World positions per frame.
        camera : Camera
            One camera for all frames.
        scalars : (V,) or (F, V) float, optional
            Heat-map values, fixed or per frame. Pass ``scalar_range`` to keep colours comparable
            across frames (the default range is per frame).
        progress : bool
            A progress bar on stderr (drawn only when stderr is a terminal:
            :func:`dqskin.progress.progress_bar`).
        **kwargs
            As :meth:`render`.

        Returns
        -------
        (F, H, W, 3 or 4) uint8
        """
        pts = np.asarray(frames, dtype=np.float64)
        if pts.ndim != 3 or pts.shape[1:] != (self.vertex_count, 3):
            raise InputError(f"frames: expected (F, {self.vertex_count}, 3), got {pts.shape}")
        sv = None if scalars is None else np.asarray(scalars, dtype=np.float64)
        if sv is not None and sv.shape not in ((self.vertex_count,),
                                               (pts.shape[0], self.vertex_count)):
            raise InputError(f"scalars: expected ({self.vertex_count},) or "
                             f"({pts.shape[0]}, {self.vertex_count}), got {sv.shape}")
        indices = progress_bar(range(pts.shape[0]), enabled=progress, desc="render",
                               unit="frame")
        images: list[np.ndarray | tuple[np.ndarray, np.ndarray]] = []
        for i in indices:
            self.update(pts[i])
            frame_scalars = None if sv is None else (sv if sv.ndim == 1 else sv[i])
            images.append(self.render(camera, scalars=frame_scalars, **kwargs))
        return np.stack(images)


def _scalar_range(values: np.ndarray, scalar_range: Iterable[float] | None) -> tuple[float, float]:
    if scalar_range is not None:
        lo, hi = (float(v) for v in scalar_range)
        if not (np.isfinite(lo) and np.isfinite(hi)) or hi < lo:
            raise InputError(f"scalar_range: expected finite (low, high) with low <= high, got "
                             f"{tuple(scalar_range)!r}")
        return lo, hi
    finite = values[np.isfinite(values)]
    if finite.size == 0:
        return 0.0, 1.0
    return float(finite.min()), float(finite.max())


def render(points: npt.ArrayLike, faces: npt.ArrayLike, camera: Camera, *, device: Device = None,
           **kwargs: Any) -> np.ndarray | tuple[np.ndarray, np.ndarray]:
    """Render one mesh once (see :meth:`MeshRenderer.render` for the keyword arguments).

    Parameters
    ----------
    points : (V, 3) float
    faces : (T, 3) int
    camera : Camera

    Returns
    -------
    (H, W, 3) uint8, or (H, W, 4) when ``transparent=True``.
    """
    return MeshRenderer(points, faces, device=device).render(camera, **kwargs)


def _as_image(name: str, image: npt.ArrayLike) -> np.ndarray:
    a = np.asarray(image)
    if a.dtype != np.uint8 or not (a.ndim == 2 or (a.ndim == 3 and a.shape[2] in (3, 4))):
        raise InputError(f"{name}: expected a uint8 (H, W), (H, W, 3) or (H, W, 4) image, got "
                         f"{a.dtype} {a.shape}")
    return a


def _font(size: float | None) -> Any:
    from PIL import ImageFont

    return ImageFont.load_default(size=size)


def _rgb_bytes(name: str, color: npt.ArrayLike) -> tuple[int, ...]:
    c = _vec3(name, color)
    return tuple(int(round(v * 255)) for v in np.clip(c, 0, 1))


def add_colorbar(image: npt.ArrayLike, scalar_range: tuple[float, float], colormap: str = "viridis",
                 *, label: str | None = None, ticks: int = 5,
                 background: npt.ArrayLike = (1.0, 1.0, 1.0),
                 text_color: npt.ArrayLike = (0.0, 0.0, 0.0),
                 font_size: int | None = None) -> np.ndarray:
    """Append a vertical colour bar with tick labels to the right of an image.

    Parameters
    ----------
    image : (H, W, 3) or (H, W, 4) uint8
    scalar_range : (float, float)
        The values at the bottom and top of the bar (the renderer's ``scalar_range``).
    colormap : str
    label : str, optional
        Written above the bar.
    ticks : int
        Number of evenly spaced tick labels (≥ 2).

    Returns
    -------
    (H, W + bar panel width, C) uint8, same channel count as ``image``.
    """
    from PIL import Image, ImageDraw

    img = _as_image("image", image)
    if img.ndim == 2:
        img = np.repeat(img[..., None], 3, axis=2)
    lo, hi = _scalar_range(np.zeros(0), scalar_range)
    if int(ticks) != ticks or ticks < 2:
        raise InputError(f"ticks: expected an integer >= 2, got {ticks!r}")
    h, w, c = img.shape
    size = font_size or max(10, h // 36)
    font = _font(size)
    label_h = int(1.6 * size) if label else 0
    top, bottom = label_h + size, size
    bar_h, bar_w = max(h - top - bottom, 2), max(size, w // 30)
    labels = [f"{v:.3g}" for v in np.linspace(lo, hi, int(ticks))]
    text_w = max(int(np.ceil(font.getlength(t))) for t in labels)
    panel_w = size + bar_w + size // 2 + text_w + size
    if label:
        panel_w = max(panel_w, int(np.ceil(font.getlength(label))) + 2 * size)
    bg = _rgb_bytes("background", background) + ((255,) if c == 4 else ())
    panel = Image.new("RGBA" if c == 4 else "RGB", (panel_w, h), bg)
    ramp = colormap_lut(colormap, bar_h)[::-1]
    strip = (np.repeat(ramp[:, None, :], bar_w, axis=1) * 255 + 0.5).astype(np.uint8)
    if c == 4:
        strip = np.concatenate([strip, np.full(strip.shape[:2] + (1,), 255, np.uint8)], axis=2)
    panel.paste(Image.fromarray(strip), (size, top))
    draw = ImageDraw.Draw(panel)
    ink = _rgb_bytes("text_color", text_color)
    for i, text in enumerate(labels):
        y = top + bar_h - 1 - i * (bar_h - 1) / (len(labels) - 1)
        draw.line([(size + bar_w, y), (size + bar_w + size // 3, y)], fill=ink)
        draw.text((size + bar_w + size // 2, y), text, fill=ink, font=font, anchor="lm")
    if label:
        draw.text((panel_w // 2, size // 2 + label_h // 2), label, fill=ink, font=font,
                  anchor="mm")
    return np.concatenate([img, np.asarray(panel)], axis=1)


def side_by_side(images: Sequence[npt.ArrayLike], labels: Sequence[str] | None = None, *,
                 pad: int = 8, background: npt.ArrayLike = (1.0, 1.0, 1.0),
                 text_color: npt.ArrayLike = (0.0, 0.0, 0.0),
                 font_size: int | None = None) -> np.ndarray:
    """Compose images in one row, each with an optional text label above it.

    Parameters
    ----------
    images : sequence of (H, W, 3|4) or (H, W) uint8
        RGBA images are composited over ``background``; heights may differ (top-aligned).
    labels : sequence of str, optional
        One per image.
    pad : int
        Pixels between and around the images.

    Returns
    -------
    (H', W', 3) uint8
    """
    from PIL import Image, ImageDraw

    imgs = [_as_image(f"images[{i}]", im) for i, im in enumerate(images)]
    if not imgs:
        raise InputError("images: nothing to compose")
    if labels is not None and len(labels) != len(imgs):
        raise InputError(f"labels: expected {len(imgs)} labels, got {len(labels)}")
    bg = np.array(_rgb_bytes("background", background), dtype=np.float64)
    rgb = []
    for im in imgs:
        if im.ndim == 2:
            im = np.repeat(im[..., None], 3, axis=2)
        if im.shape[2] == 4:
            a = im[..., 3:4] / 255.0
            im = (im[..., :3] * a + bg * (1 - a) + 0.5).astype(np.uint8)
        rgb.append(im)
    size = font_size or max(12, max(im.shape[0] for im in rgb) // 24)
    label_h = int(size * 1.6) if labels else 0
    width = pad + sum(im.shape[1] + pad for im in rgb)
    height = 2 * pad + label_h + max(im.shape[0] for im in rgb)
    canvas = Image.new("RGB", (width, height), tuple(int(v) for v in bg))
    draw = ImageDraw.Draw(canvas)
    font = _font(size) if labels else None
    ink = _rgb_bytes("text_color", text_color)
    x = pad
    for i, im in enumerate(rgb):
        canvas.paste(Image.fromarray(im), (x, pad + label_h))
        if labels:
            draw.text((x + im.shape[1] // 2, pad + label_h // 2), str(labels[i]), fill=ink,
                      font=font, anchor="mm")
        x += im.shape[1] + pad
    return np.asarray(canvas)


def save_png(path: str | os.PathLike, image: npt.ArrayLike) -> Path:
    """Write an image as PNG atomically (temporary file in the same folder, then ``os.replace``).

    Parameters
    ----------
    path : str or Path
    image : (H, W), (H, W, 3) or (H, W, 4) uint8

    Returns
    -------
    Path
    """
    from PIL import Image

    img = _as_image("image", image)
    path = Path(path)
    with atomic_path(path) as tmp:
        Image.fromarray(img).save(tmp, format="PNG", compress_level=3)  # faster than the default 6
    return path
