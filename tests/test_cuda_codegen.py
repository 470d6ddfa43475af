"""Every kernel module of ``dqskin.kernels`` compiles for CUDA (PTX for sm_75 and sm_90) — checked
without a GPU, so a CUDA code-generation error fails CI even on CPU-only machines."""

import importlib
import importlib.util
import pkgutil

import pytest
import warp as wp

import dqskin.kernels

# every module that defines a kernel: a new kernel module is covered without editing this list
MODULES = tuple(m.name for m in pkgutil.iter_modules(dqskin.kernels.__path__)
                if "@wp.kernel" in (importlib.util.find_spec(f"dqskin.kernels.{m.name}")
                                    .loader.get_source(f"dqskin.kernels.{m.name}") or ""))


def test_every_kernel_module_is_listed():
    known = {"fk", "skin", "velocity", "metrics", "render", "cor", "layout", "bone_heat"}
    assert known <= set(MODULES)


def _warp_modules(name):
    """The Warp modules of the kernel module ``name``: its own and those its kernels were put in
    by name (``wp.kernel(module="dqskin.kernels.skin.lbs")``: one per skinning method, so that
    a process loads only the kernels of the methods it uses)."""
    from warp._src.context import user_modules
    full = importlib.import_module(f"dqskin.kernels.{name}").__name__
    return sorted(m for m in user_modules if m == full or m.startswith(full + "."))


def test_skinning_kernels_are_one_warp_module_per_method():
    from dqskin.kernels import skin
    for spec in skin.SKIN_POINTS_KERNELS._specs:  # a method's kernels are defined on first use
        skin.SKIN_POINTS_KERNELS[(spec[0], spec[1], False, spec[2], spec[3])]
    names = _warp_modules("skin")
    assert names == ["dqskin.kernels.skin"] + [f"dqskin.kernels.skin.{m}"
                                               for m in ("blend", "cor", "dqs", "lbs")]


@pytest.mark.parametrize("name", MODULES)
def test_kernel_module_compiles_for_cuda(name, tmp_path):
    for warp_module in _warp_modules(name):
        paths = wp.compile_aot_module(warp_module, arch=[75, 90], use_ptx=True,
                                      module_dir=tmp_path / warp_module)
        ptx = sorted(p.name for p in paths if p.suffix == ".ptx")
        assert any(".sm75." in p for p in ptx) and any(".sm90." in p for p in ptx), \
            (warp_module, ptx)
        assert all(p.stat().st_size > 1000 for p in paths), warp_module
