"""Session fixtures: the textured scene rendered once into a temporary cache, and its photos."""

from fractions import Fraction

import pytest
from process_data_photos import PhotoShoot, noise_texture, shoot, textured_scene


@pytest.fixture(scope="session")
def texture(tmp_path_factory):
    return noise_texture(tmp_path_factory.mktemp("texture") / "noise.png")


@pytest.fixture(scope="session")
def small_shoot(studio_cache, texture, tmp_path_factory) -> PhotoShoot:
    """16 views at 192 px, exposures cycling 1/60, 1/30, 1/15 s."""
    scene = textured_scene(texture, views=16, resolution=192)
    return shoot(scene, tmp_path_factory.mktemp("photos"), [Fraction(1, 60), Fraction(1, 30), Fraction(1, 15)])
