"""HDR-GS: the CRF baseline as it is (tone mapper per Gaussian, HDR rasterises exp(ln E))."""

from mono_hdr_plugin.methods.base import register_method
from mono_hdr_plugin.methods.crf_baseline import CrfBaseline


@register_method("hdr-gs")
class HdrGsBaseline(CrfBaseline):
    """HDR-GS: the shared baseline (tone mapper per Gaussian, HDR rasterises exp(ln E)) and nothing else."""
