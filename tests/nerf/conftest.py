"""Fixtures of the NeRF backbone tests."""

import pytest
import torch
from nerf_scenes import orbit_camera

from mono_hdr_plugin.core.backbone import SceneInfo


@pytest.fixture
def scene() -> SceneInfo:
    """The box [-1, 1]^3 seen by two cameras."""
    return SceneInfo(
        bounds_min=-torch.ones(3),
        bounds_max=torch.ones(3),
        train_cameras=[orbit_camera(), orbit_camera(eye=(-3.0, 1.0, 0.5))],
    )


@pytest.fixture(autouse=True)
def _seed_and_one_thread():
    """Seeded, single-threaded: these tensors are tiny, and on a shared 2-core machine a second
    thread's synchronisation cost dominates (measured 10x slower)."""
    torch.manual_seed(0)
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)
