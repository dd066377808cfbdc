"""Fixtures of the Gaussian tests; the scenes themselves live in gs_scenes.py."""

import pytest
from gs_scenes import make_camera


@pytest.fixture
def camera():
    return make_camera()
