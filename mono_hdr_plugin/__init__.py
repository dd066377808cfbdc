"""Mono-HDR-3D: single-exposure HDR novel view synthesis as a meta-algorithm over 3D backbones."""

__version__ = "0.1.0"
