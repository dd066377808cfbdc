"""A tiny demo scene rendered once per test session into a temporary cache."""

from dataclasses import replace

import pytest

from mono_hdr_plugin.studio.scenes import SCENES


@pytest.fixture(scope="session")
def studio_cache(tmp_path_factory):
    """Point the render cache at a session folder, so tests never touch the user's cache."""
    folder = tmp_path_factory.mktemp("studio-cache")
    with pytest.MonkeyPatch.context() as patch:
        patch.setenv("MONO_HDR_CACHE", str(folder))
        yield folder


@pytest.fixture(scope="session")
def tiny_demo(studio_cache):
    """The demo scene at 24x24, 4 samples per pixel, 10 views: renders in about a second."""
    demo = SCENES["demo"]
    return replace(demo, resolution=(24, 24), spp=4, rig=replace(demo.rig, views=10))
