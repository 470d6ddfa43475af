"""Writers: what a bake writes, one module per output, each owning its ``SUFFIXES``.

:mod:`.usd_cache` (USD point caches, one layer), :mod:`.usd_clips` (USD value clips: clip
layers, manifest, top level; :func:`~.usd_clips.flatten`), :mod:`.npz`, :mod:`.mesh_files` (one
trimesh file per frame) and :mod:`.usd_rig` (a scene written as a UsdSkel rig). Every writer goes
through :class:`dqskin.files.atomic.atomic_path`. Importing this package imports none of them.
"""

__all__ = ["CACHE_EXTENSIONS"]

CACHE_EXTENSIONS = (".usda", ".usdc", ".usd")
"""Suffixes of the USD caches :mod:`.usd_cache` writes (``.usd`` is binary crate); here, so
that an output's kind is known without importing USD."""
