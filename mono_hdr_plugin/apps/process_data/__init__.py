"""`mono-hdr process-data`: your photos (or a video) -> an HDR-GS dataset the trainer reads.

    photos/IMG_0001.jpg ...   ->   out/images/000_0.png ...     one LDR photo per viewpoint: upright,
    (JPEG, PNG, TIFF, RAW,                                       undistorted, downscaled
     or --video clip.mp4)          out/exr/005.exr ...          linear HDR of every bracketed viewpoint
                                   out/sparse/0/*.bin           COLMAP model of those images (PINHOLE)
                                   out/exposures.json           {image name: seconds, null when unknown}
                                   out/splits.json              the images held out for testing
                                   out/camera_response.json     code value -> linear exposure, when known
                                   out/process_data.json        what happened, which photo became what

The stages, each a module taking and returning plain records (records.py), run in order by command.py:

    config      ProcessDataConfig, its flag rules and the checks before any photo is read
    photos      the photos (or video frames), read upright, copied for structure from motion, one camera
    exposures   each photo's exposure: EXIF (ISO and aperture folded in when they vary), CSV, --exposure
    sfm         poses by structure from motion (pycolmap on the CPU over every photo)
    brackets    photos of one viewpoint at several exposures, planned and merged into linear HDR views
    layout      the HDR-GS files in a scratch folder beside --out, renamed into place at the end
    report      what happened: OUT/process_data.json and the printed table
"""

from mono_hdr_plugin.apps.process_data.command import process_data, process_data_command
from mono_hdr_plugin.apps.process_data.config import ProcessDataConfig

__all__ = ["ProcessDataConfig", "process_data", "process_data_command"]
