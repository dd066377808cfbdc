"""Session fixtures: the textured scene rendered once into a temporary cache, and its photos."""

from fractions import Fraction

import pytest

from process_data_photos import PhotoShoot, noise_texture, shoot, textured_scene


@pytest.fixture(scope="session")
def render_cache(tmp_path_factory):
    """Point the studio render cache at a session folder, so tests never touch the user's cache."""
    folder = tmp_path_factory.mktemp("render-cache")
    with pytest.MonkeyPatch.context() as patch:
        patch.setenv("MONO_HDR_CACHE", str(folder))
        yield folder


@pytest.fixture(scope="session")
def texture(tmp_path_factory):
    return noise_texture(tmp_path_factory.mktemp("texture") / "noise.png")


@pytest.fixture(scope="session")
def small_shoot(render_cache, texture, tmp_path_factory) -> PhotoShoot:
    """16 views at 192 px, exposures cycling 1/60, 1/30, 1/15 s."""
    scene = textured_scene(texture, views=16, resolution=192)
    return shoot(scene, tmp_path_factory.mktemp("photos"), [Fraction(1, 60), Fraction(1, 30), Fraction(1, 15)])
