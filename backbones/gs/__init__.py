"""3D Gaussian Splatting backbone with a differentiable CPU rasteriser (C++ kernel + torch twins).

Importing this package builds nothing: the C++ extension compiles on the first render.
"""

from backbones.gs.model import GaussianBackbone, GaussianConfig
from backbones.gs.ply import export_ply, load_ply
from backbones.gs.rasterizer import ProjectedGaussians, project_gaussians, rasterize, render_gaussians
from backbones.gs.strategy import GAUSSIAN_PARAMETERS, DefaultStrategy, McmcStrategy

__all__ = [
    "GAUSSIAN_PARAMETERS",
    "DefaultStrategy",
    "GaussianBackbone",
    "GaussianConfig",
    "McmcStrategy",
    "ProjectedGaussians",
    "export_ply",
    "load_ply",
    "project_gaussians",
    "rasterize",
    "render_gaussians",
]
