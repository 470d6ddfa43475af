"""What a skinning run is asked for: one frozen, typed value passed whole from the CLI down.

:class:`SkinOptions` holds every knob of the engine (method, sign rule, interpolation, which
outputs, the space they are reported in, the device, the centers-of-rotation settings
:class:`CorOptions`), each default written here once. :meth:`dqskin.Scene.skin`,
:func:`dqskin.bake`, :func:`dqskin.report.compare.run_compare`, :class:`dqskin.Crowd` and the
clip workers (:mod:`dqskin.distributed`) take it; keyword arguments of those entry points build
or override one (:meth:`SkinOptions.build`). It is hashable, comparable and picklable (a clip
bake sends it to its Dask workers); :meth:`SkinOptions.replace` derives another.
"""

import dataclasses
import math
import numbers
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, Literal, cast, get_args

from .errors import InputError, Param
from .spaces import SPACES, Space

if TYPE_CHECKING:
    from .readers.usd import RigidPrim
    from .scene import Mesh

__all__ = ["DEFAULT_INTERP", "DEFAULT_SIGN_REFERENCE", "INTERPOLATIONS", "METHOD_NAMES", "SIGMA",
           "SIGN_REFERENCES", "SPACES", "CorOptions", "Interpolation", "Method", "SignReference",
           "SkinOptions", "Space", "split_changes"]

Method = Literal["lbs", "dqs", "blend", "cor"]
"""Skinning methods: linear blend, dual quaternion, per-vertex blend of the two, optimized centers
of rotation (:mod:`dqskin.cor`; needs the mesh's faces)."""

METHOD_NAMES: tuple[Method, ...] = get_args(Method)
"""Every :data:`Method`, in order (:data:`dqskin.skinning.METHODS` maps each to its kernel
code)."""

SignReference = Literal["largest_weight", "running_sum"]
"""How DQS (and the rotation blends of "blend" and "cor") pick each joint quaternion's sign:
against the vertex's largest-weight joint (UsdSkel; first on ties), or against the running sum of
the blend so far, influences in their input order, a zero sum flipping nothing (Blender's
Preserve Volume)."""

SIGN_REFERENCES: tuple[SignReference, ...] = get_args(SignReference)
"""Every :data:`SignReference`, in order."""

DEFAULT_SIGN_REFERENCE: SignReference = "largest_weight"
"""The sign rule of every call that does not name one: UsdSkel's."""

Interpolation = Literal["trs", "sclerp", "dlb", "spline", "catmull-rom"]
"""Pose interpolation between keys (:mod:`dqskin.animation`)."""

INTERPOLATIONS: tuple[Interpolation, ...] = get_args(Interpolation)
"""Every :data:`Interpolation`, in order."""

DEFAULT_INTERP: Interpolation = "trs"
"""The interpolation of every call that does not name one: the asset's own sampler (what glTF
and USD players show)."""

SIGMA = 0.1
"""Width of the centers-of-rotation similarity kernel (Le & Hodgins' value; :mod:`dqskin.cor`)."""


def _choice(name: str, value: object, choices: tuple[str, ...], none: bool = False) -> None:
    if (value is None and none) or (isinstance(value, str) and value in choices):
        return
    raise InputError(Param(name, value), f": expected one of {list(choices)}"
                     + (" or None" if none else ""))


@dataclass(frozen=True, kw_only=True)
class CorOptions:
    """How ``method="cor"`` computes each mesh's centers of rotation
    (:func:`dqskin.cor.rotation_centers`).

    Attributes
    ----------
    sigma : float
        Similarity width, > 0 (:data:`SIGMA`).
    subdivide : float or None
        Subdivide triangles to this weight distance (> 0) for the integral; None: one term per
        triangle.
    cluster : float, "auto" or None
        Cluster the weights on a grid of this step (> 0), "auto" for large meshes only, None for
        exact centers.
    """

    sigma: float = SIGMA
    subdivide: float | None = None
    cluster: float | str | None = "auto"

    def __post_init__(self) -> None:
        for name, none in (("sigma", False), ("subdivide", True), ("cluster", True)):
            v = getattr(self, name)
            if (v is None and none) or (name == "cluster" and v == "auto"):
                continue
            if isinstance(v, bool) or not isinstance(v, numbers.Real) or not math.isfinite(v) \
                    or v <= 0:
                raise InputError(Param(f"cor.{name}", v), ": expected a finite number > 0"
                                 + ("" if not none else " or None")
                                 + (' or "auto"' if name == "cluster" else ""))
            object.__setattr__(self, name, float(v))


@dataclass(frozen=True, kw_only=True)
class SkinOptions:
    """Everything that decides what skinning produces, besides the data.

    Attributes
    ----------
    method : {"lbs", "dqs", "blend", "cor"} or None
        None: each mesh's own ``skinning_method``.
    sign_reference : {"largest_weight", "running_sum"}
        Sign rule of the rotation blends (:data:`SignReference`).
    interp : str
        Joint interpolation between keys (:data:`INTERPOLATIONS`).
    normals, tangents, velocities : bool
        Also skin the rest normals, the rest tangents (directions only; the handedness stays
        ``mesh.tangents[:, 3]``), and compute point velocities (length units per second, the
        analytic joint motion of :mod:`dqskin.motion` through every time-varying input).
    blend_shapes : bool
        Apply each mesh's ``deformer`` (blend shapes, morph targets, animated points); False
        skins the bind points.
    space : {"local", "skeleton", "world"}
        Where results are reported (:data:`Space`).
    device : str or None
        Warp device ("cpu", "cuda:0"); None: CUDA when present, else the CPU.
    cor : CorOptions
        Centers of rotation of ``method="cor"``.

    Raises
    ------
    dqskin.errors.InputError
        A field out of its range, naming it.
    """

    method: Method | None = None
    sign_reference: SignReference = DEFAULT_SIGN_REFERENCE
    interp: Interpolation = DEFAULT_INTERP
    normals: bool = False
    tangents: bool = False
    velocities: bool = False
    blend_shapes: bool = True
    space: Space = "local"
    device: str | None = None
    cor: CorOptions = field(default_factory=CorOptions)

    def __post_init__(self) -> None:
        _choice("method", self.method, METHOD_NAMES, none=True)
        _choice("sign_reference", self.sign_reference, SIGN_REFERENCES)
        _choice("interp", self.interp, INTERPOLATIONS)
        _choice("space", self.space, SPACES)
        for name in ("normals", "tangents", "velocities", "blend_shapes"):
            v = getattr(self, name)
            if not isinstance(v, bool):
                if not is_numpy_bool(v):
                    raise InputError(Param(name, v), ": expected True or False")
                object.__setattr__(self, name, bool(v))
        if self.device is not None:
            object.__setattr__(self, "device", str(self.device))  # (a wp.Device: its name)
        if not isinstance(self.cor, CorOptions):
            raise InputError(Param("cor", self.cor), ": expected a CorOptions")

    @classmethod
    def build(cls, options: "SkinOptions | None" = None, **changes: Any) -> "SkinOptions":
        """``options`` (default: every default) with the fields in ``changes`` replaced.
        TypeError for an unknown field, as Python's for an unknown keyword."""
        base = cls() if options is None else options
        if not isinstance(base, SkinOptions):
            raise InputError(Param("options", base), ": expected a SkinOptions or None")
        return dataclasses.replace(base, **changes) if changes else base

    @classmethod
    def baking(cls, **changes: Any) -> "SkinOptions":
        """The options of a bake (:func:`dqskin.bake`, ``dqskin skin``): normals and velocities
        on, world space (a USD cache holds local points whose prims place them there), then
        ``changes``."""
        return cls.build(cls(normals=True, velocities=True, space="world"), **changes)

    def replace(self, **changes: Any) -> "SkinOptions":
        """A copy with ``changes`` (:meth:`build` on this one)."""
        return self.build(self, **changes)

    def method_of(self, mesh: "Mesh | RigidPrim") -> Method:
        """The method ``mesh`` is skinned with: :attr:`method`, else the mesh's own."""
        return cast(Method, self.method or mesh.skinning_method)

    def plan(self) -> dict[str, Any]:
        """The fields that change a clip bake's samples, as recorded in its plan (and key): the
        method, interpolation, sign rule, normals and velocities, and the blend-shape and
        centers-of-rotation settings when they are not the defaults (so the keys of bakes with
        the defaults stay as they were)."""
        out: dict[str, Any] = dict(method=self.method, interp=self.interp,
                                   sign_reference=self.sign_reference, normals=self.normals,
                                   velocities=self.velocities)
        if not self.blend_shapes:
            out["blend_shapes"] = False
        if self.cor != CorOptions():
            out["cor"] = dataclasses.asdict(self.cor)
        return out


def is_numpy_bool(v: object) -> bool:
    """Whether ``v`` is NumPy's bool scalar (its type is named ``bool`` in NumPy 2, ``bool_``
    before), told without importing NumPy."""
    t = type(v)
    return t.__module__ == "numpy" and t.__name__ in ("bool", "bool_")


def split_changes(function: str, changes: dict[str, Any], *kinds: type) -> list[dict[str, Any]]:
    """``changes`` (keyword arguments of ``function``) split by the dataclass among ``kinds``
    that has each as a field: one dict per kind. TypeError, as Python's, for a keyword no kind
    has."""
    names = [{f.name for f in dataclasses.fields(k)} for k in kinds]
    unknown = sorted(set(changes).difference(*names))
    if unknown:
        raise TypeError(f"{function}() got an unexpected keyword argument {unknown[0]!r}")
    return [{k: v for k, v in changes.items() if k in n} for n in names]
