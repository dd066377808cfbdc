"""Structure from motion on real photos: `opensfm_lund`, a phone walking straight down a street.

Every pair of a forward walk moves along the viewing axis with 1-3 degrees of parallax, so COLMAP's
incremental mapper finds no initial pair it accepts (16 degrees, under 95 % forward motion) and
places next to nothing; `--mapper auto` goes on to the forward-motion start and the global mapper.
The photos' EXIF GPS is an independent check of the placed cameras.
"""

import shutil

import pytest
from helpers import real_photos

from mono_hdr_plugin.apps.process_data import ProcessDataConfig, process_data

STREET_MIDDLE = [f"{index:02d}.jpg" for index in range(8, 16)]
"""Eight neighbouring photos, about 50 m of street."""


def attempts(report) -> dict[str, int]:
    return {attempt.mapper: attempt.placed for attempt in report.mapper_attempts}


class TestForwardWalk:
    def test_eight_photos_of_a_street(self, tmp_path):
        photos = tmp_path / "photos"
        photos.mkdir()
        for name in STREET_MIDDLE:
            shutil.copy(real_photos("opensfm_lund") / "images" / name, photos / name)
        report = process_data(ProcessDataConfig(images=photos, out=tmp_path / "d", num_threads=2))
        assert len(report.registered) == 8 and report.failed == []
        # the default incremental mapper is tried first and cannot start on forward motion
        assert attempts(report)["incremental"] < 3 and report.mapper != "incremental"
        assert report.mean_reprojection_error < 1.0
        assert report.gps_rms_m is not None and report.gps_rms_m < 10.0

    @pytest.mark.slow
    def test_whole_street(self, tmp_path):
        report = process_data(
            ProcessDataConfig(images=real_photos("opensfm_lund") / "images", out=tmp_path / "d", num_threads=2)
        )
        assert len(report.registered) >= 27
        assert report.mean_reprojection_error < 1.0
        assert report.gps_rms_m is not None and report.gps_rms_m < 10.0
