"""The three ablations of Mono-HDR (the paper's converter table). They share one module because
each is MonoHDR with one part swapped or removed: a class attribute and a docstring."""

from mono_hdr_plugin.core.converters import PlainH2L, PlainL2H
from mono_hdr_plugin.methods.base import register_method
from mono_hdr_plugin.methods.mono import MonoHDR


@register_method("mlp-l2h")
class MonoHdrPlainL2H(MonoHDR):
    """Ablation: a plain MLP of the same width instead of L2H-CC."""

    l2h_class = PlainL2H


@register_method("mlp-h2l")
class MonoHdrPlainH2L(MonoHDR):
    """Ablation: a plain MLP of the same width instead of H2L-CC."""

    h2l_class = PlainH2L


@register_method("no-h2l")
class MonoHdrOpenLoop(MonoHDR):
    """Ablation: no H2L-CC, so no closed loop (and no L_h2l)."""

    h2l_class = None
