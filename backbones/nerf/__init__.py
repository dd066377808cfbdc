"""NeRF backbone of mono-hdr-3d: volume renderer, the official MLP field and a fast grid field.

Registered through the `mono_hdr.backbones` entry point as `nerf`.
"""

from backbones.nerf.backbone import NerfBackbone
from backbones.nerf.config import GridFieldConfig, MlpFieldConfig, NerfConfig

__all__ = ["NerfBackbone", "NerfConfig", "MlpFieldConfig", "GridFieldConfig"]
