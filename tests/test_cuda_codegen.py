"""Every kernel module of ``dqskin.kernels`` compiles for CUDA (PTX for sm_75 and sm_90) — checked
without a GPU, so a CUDA code-generation error fails CI even on CPU-only machines."""

import importlib

import pytest
import warp as wp

MODULES = ("fk", "skin", "velocity", "metrics", "render", "cor", "layout")


@pytest.mark.parametrize("name", MODULES)
def test_kernel_module_compiles_for_cuda(name, tmp_path):
    module = importlib.import_module(f"dqskin.kernels.{name}")
    paths = wp.compile_aot_module(module, arch=[75, 90], use_ptx=True, module_dir=tmp_path)
    ptx = sorted(p.name for p in paths if p.suffix == ".ptx")
    assert any(".sm75." in p for p in ptx) and any(".sm90." in p for p in ptx), ptx
    assert all(p.stat().st_size > 1000 for p in paths)
