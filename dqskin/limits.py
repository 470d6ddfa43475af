"""Limits on what an input may make dqskin allocate or compute, checked before anything is
allocated: one mechanism for every limit.

Each limit is a keyword parameter of the functions that apply it, its default a constant here (or
beside the function), and a flag of the command line; beyond it a :class:`~dqskin.errors.LimitError`
names the input, what it asks for, the limit and the parameter that raises it (the CLI spells it
as its flag). ``max_frames`` (:data:`dqskin.times.MAX_FRAMES`, ``--max-frames``) is one of them.

* ``max_input_gib`` (:data:`MAX_INPUT_GIB`, ``--max-input-gib``): the largest array an input
  file may ask for before its data is seen (an ``.npz`` array's header, a glTF primitive's morph
  targets, a BVH's frames × channels), in GiB (2³⁰ bytes).
* ``max_vertices`` (:data:`MAX_RIG_VERTICES`, ``--max-vertices``): vertices of a mesh given
  automatic weights (the bone-heat Laplacian takes about 2.6 kB a vertex).
"""

from .errors import LimitError, Param

__all__ = ["MAX_INPUT_GIB", "MAX_RIG_VERTICES", "check_bytes", "check_vertices"]

MAX_INPUT_GIB = 2.0
"""Default ``max_input_gib``: GiB one array of an input may take."""

MAX_RIG_VERTICES = 1_000_000
"""Default ``max_vertices``: vertices of a mesh given automatic weights."""

_GIB = 1 << 30


def check_bytes(nbytes: int, what: str, max_input_gib: float = MAX_INPUT_GIB) -> None:
    """LimitError when ``nbytes`` (what the input ``what`` asks to allocate: "FILE: FIELD")
    exceed ``max_input_gib`` GiB."""
    if nbytes > max_input_gib * _GIB:
        raise LimitError(f"{what}: needs {nbytes / _GIB:.3g} GiB, more than the limit of "
                         f"{max_input_gib:g} GiB; raise ", Param("max_input_gib"),
                         " to allow more")


def check_vertices(count: int, what: str, max_vertices: int = MAX_RIG_VERTICES) -> None:
    """LimitError when a mesh ``what`` of ``count`` vertices exceeds ``max_vertices`` (automatic
    weights)."""
    if count > max_vertices:
        raise LimitError(f"{what}: {count:,} vertices, more than the limit of {max_vertices:,} "
                         "for automatic weights; raise ", Param("max_vertices"),
                         " to allow more (or decimate the mesh)")
