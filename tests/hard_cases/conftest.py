"""Fixtures of the hard-case tests: one thread, fixed seeds, a tiny dataset written to disk."""

import pytest
import torch
from hard_scenes import write_disk_scene


@pytest.fixture(autouse=True)
def _seed_and_one_thread():
    """Seeded and single-threaded: the tensors are tiny, and on a shared 2-core machine a second
    thread's synchronisation costs more than it gains (measured 10x slower)."""
    torch.manual_seed(0)
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


@pytest.fixture(scope="session")
def disk_scene(tmp_path_factory):
    """A 16 px scene with 6 views at five exposures, in the HDR-NeRF synthetic layout."""
    folder = tmp_path_factory.mktemp("disk-scene") / "scene"
    write_disk_scene(folder)
    return folder
