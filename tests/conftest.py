"""Shared fixtures: the example voxel-grid backbone and its tiny synthetic capture."""

import sys
from pathlib import Path

import pytest
import torch

EXAMPLES = Path(__file__).resolve().parents[1] / "examples"
if str(EXAMPLES) not in sys.path:
    sys.path.insert(0, str(EXAMPLES))

torch.set_num_threads(2)


@pytest.fixture(scope="session")
def voxel_scene():
    """A 16 x 16 px HDR voxel scene photographed at one exposure (train/test alternate)."""
    import register_backbone

    return register_backbone.make_capture(size=16, views=8)


@pytest.fixture(scope="session")
def voxel_backbone_config():
    import register_backbone

    return register_backbone.VoxelGridConfig(resolution=12, samples_per_ray=24)
