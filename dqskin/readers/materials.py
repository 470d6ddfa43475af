"""Each mesh's base-colour material as its source file describes it, for the per-frame files
(:mod:`dqskin.writers.mesh_files`) to carry.

What is read: glTF ``pbrMetallicRoughness.baseColorFactor`` and ``baseColorTexture`` (its image
embedded in a buffer view, a ``data:`` URI or a file beside the asset); USD the bound material's
``UsdPreviewSurface`` ``diffuseColor`` (and ``opacity``), a value or a ``UsdUVTexture``'s
``file`` (a file beside the stage or inside its ``.usdz`` package, read through USD's asset
resolver). Anything else (other shading models, a texture that cannot be read) leaves the mesh
without a material: materials travel with the frames when they can, and never stop a bake.
A reader of another format adds its own function to :func:`base_colors`.
"""

import re
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from ..scene import Scene

__all__ = ["MAX_IMAGE_BYTES", "BaseColor", "base_colors"]

MAX_IMAGE_BYTES = 64 << 20
"""Largest texture image carried into per-frame files (a larger one is left out)."""

_SUFFIXES = {b"\x89PNG": ".png", b"\xff\xd8\xff": ".jpg"}


@dataclass(frozen=True)
class BaseColor:
    """A mesh's base colour.

    Attributes
    ----------
    name : str
        The material's name in its file (a valid identifier).
    factor : tuple of 4 float
        Linear RGBA multiplier (glTF ``baseColorFactor``; USD ``diffuseColor`` and
        ``opacity``).
    image : bytes or None
        The texture image file's bytes (PNG or JPEG), or None.
    """

    name: str
    factor: tuple[float, float, float, float] = (1.0, 1.0, 1.0, 1.0)
    image: bytes | None = None

    @property
    def image_suffix(self) -> str:
        """``.png`` or ``.jpg``: the image's own format."""
        head = (self.image or b"")[:4]
        return next((s for magic, s in _SUFFIXES.items() if head.startswith(magic)), ".png")


def _image(data: bytes | None) -> bytes | None:
    """``data`` when it is a PNG or JPEG image of at most :data:`MAX_IMAGE_BYTES`."""
    if not data or len(data) > MAX_IMAGE_BYTES:
        return None
    return data if any(data.startswith(m) for m in _SUFFIXES) else None


def _identifier(name: object, fallback: str) -> str:
    text = re.sub(r"[^A-Za-z0-9_]", "_", str(name or "")).strip("_")
    return text or fallback


def base_colors(scene: "Scene") -> dict[str, BaseColor]:
    """The base-colour material of each mesh of ``scene`` that has one, by ``Mesh.name``, read
    from ``scene.path`` (glTF or USD; other formats: none)."""
    from . import format_of, gltf, usd
    fmt = format_of(scene.path)
    names = [m.name for m in scene.meshes]
    try:
        if fmt is gltf:
            return _gltf_colors(scene.path, names)
        if fmt is usd:
            return _usd_colors(scene.path, names)
    except (OSError, ValueError, KeyError, IndexError, TypeError, AttributeError):
        return {}  # a material that cannot be read does not stop a bake
    return {}


def _gltf_colors(path: str, names: list[str]) -> dict[str, BaseColor]:
    import base64

    from .gltf import _Reader, mesh_primitives
    r = _Reader(path)
    raw = r.raw
    materials, textures = raw.get("materials") or [], raw.get("textures") or []
    images, views = raw.get("images") or [], raw.get("bufferViews") or []

    def image(index: int) -> bytes | None:
        img = images[index]
        if img.get("bufferView") is not None:
            view = views[img["bufferView"]]
            start = int(view.get("byteOffset", 0))
            buf = r._buffer(int(view["buffer"]))
            end = start + int(view["byteLength"])
            return bytes(buf[start:end]) if 0 <= start <= end <= len(buf) else None
        uri = img.get("uri")
        if not isinstance(uri, str):
            return None
        if uri.startswith("data:"):
            return base64.b64decode(uri.partition(",")[2], validate=True)
        return r._read_external(f"images[{index}].uri", uri)

    out: dict[str, BaseColor] = {}
    cache: dict[int, BaseColor] = {}
    for name, mesh_index, k in mesh_primitives(r):
        if name not in names:
            continue
        index = raw["meshes"][mesh_index]["primitives"][k].get("material")
        if not isinstance(index, int) or not 0 <= index < len(materials):
            continue
        if index not in cache:
            mat = materials[index]
            pbr = mat.get("pbrMetallicRoughness") or {}
            f = [float(x) for x in pbr.get("baseColorFactor", (1, 1, 1, 1))]
            tex = (pbr.get("baseColorTexture") or {}).get("index")
            source = textures[tex].get("source") if isinstance(tex, int) else None
            picture = _image(image(source)) if isinstance(source, int) else None
            cache[index] = BaseColor(_identifier(mat.get("name"), f"material{index}"),
                                     (f[0], f[1], f[2], f[3]) if len(f) == 4 else
                                     (1.0, 1.0, 1.0, 1.0), picture)
        out[name] = cache[index]
    return out


def _usd_colors(path: str, names: list[str]) -> dict[str, BaseColor]:
    from pxr import Ar, UsdShade

    from .usd_layers import open_stage
    stage = open_stage(path)  # (every file it reads checked: no FIFO among its layers)
    if stage is None:
        return {}
    out: dict[str, BaseColor] = {}
    for name in names:
        prim = stage.GetPrimAtPath(name)
        if not prim:
            continue
        material = UsdShade.MaterialBindingAPI(prim).ComputeBoundMaterial()[0]
        if not material:
            continue
        shader = material.ComputeSurfaceSource()[0]
        if not shader or shader.GetIdAttr().Get() != "UsdPreviewSurface":
            continue
        color: Any = (1.0, 1.0, 1.0)
        picture = None
        diffuse = shader.GetInput("diffuseColor")
        if diffuse and diffuse.HasConnectedSource():
            texture = UsdShade.Shader(diffuse.GetConnectedSource()[0].GetPrim())
            file = texture.GetInput("file") if texture else None
            asset = file.Get() if file else None
            resolved = getattr(asset, "resolvedPath", "")
            if resolved:
                handle = Ar.GetResolver().OpenAsset(Ar.ResolvedPath(resolved))
                if handle is not None and handle.GetSize() <= MAX_IMAGE_BYTES:
                    picture = _image(bytes(handle.GetBuffer()))
            scale = texture.GetInput("scale") if texture else None
            if scale and scale.Get() is not None:
                color = tuple(scale.Get())[:3]
        elif diffuse and diffuse.Get() is not None:
            color = tuple(diffuse.Get())
        opacity = shader.GetInput("opacity")
        alpha = float(opacity.Get()) if opacity and not opacity.HasConnectedSource() and \
            opacity.Get() is not None else 1.0
        r, g, b = (float(x) for x in color)
        out[name] = BaseColor(_identifier(material.GetPrim().GetName(), "material"),
                              (r, g, b, alpha), picture)
    return out
