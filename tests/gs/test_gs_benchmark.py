"""`mono-hdr bench raster`: registered like every plugin, runs on a tiny scene, and the backbone
layer stays below the methods (the HDR branch is timed with L2H-CC from core)."""

import json
import subprocess
import sys

import torch

from backbones.gs import benchmark
from mono_hdr_plugin.core.converters import L2HColorConverter
from mono_hdr_plugin.core.registry import BENCHMARKS
from mono_hdr_plugin.methods.base import MethodConfig
from mono_hdr_plugin.methods.mono import MonoHDR


def test_registered_as_raster():
    assert BENCHMARKS.get("raster") is benchmark.BenchRasterConfig


def test_tiny_run_writes_the_table(tmp_path):
    records = benchmark.bench_raster(tmp_path, sizes=((300, 16, 16),), repeats=1, with_torch_twin=False)
    written = json.loads((tmp_path / "raster.json").read_text())
    assert len(records) == len(written) == 1
    assert written[0]["gaussians"] == 300 and written[0]["fps_ldr_hdr"] > 0 and written[0]["hdr_render_cost"] > 0


def test_importing_it_loads_no_method():
    code = (
        "import sys, backbones.gs.benchmark; "
        "print(sorted(m for m in sys.modules if m.startswith(('mono_hdr_plugin.methods', 'mono_hdr_plugin.training'))))"
    )
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert result.stdout.strip() == "[]"


def test_the_timed_hdr_render_is_what_mono_hdr_renders():
    """The benchmark's HDR pass does MonoHDR's eval-mode work: L2H-CC, then one 6-channel composite."""
    torch.manual_seed(0)
    method = MonoHDR(MethodConfig(), "l1_dssim").eval()
    l2h = L2HColorConverter()
    l2h.load_state_dict(method.l2h.state_dict())
    colors = torch.rand(50, 3)
    weights = torch.rand(8, 50)
    features = type(
        "Features",
        (),
        {"colors": colors, "l2h_inputs": None, "composite": staticmethod(lambda values: weights @ values)},
    )()
    with torch.no_grad():
        expected = method(features, 1.0)
        image = features.composite(torch.cat([colors, l2h(colors)], dim=-1))
    torch.testing.assert_close(image[..., 3:], expected.hdr, rtol=0, atol=0)
    torch.testing.assert_close(image[..., :3], expected.ldr, rtol=0, atol=0)
