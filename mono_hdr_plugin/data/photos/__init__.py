"""What a real camera hands over, turned into what process-data needs.

exif.py       the EXIF fields process-data reads (and the simulated camera writes)
raw.py        RAW files through rawpy (LibRaw): linear demosaiced pixels and their metadata
video.py      frames from a video (imageio-ffmpeg), the blurriest ones dropped
brackets.py   bracket sets (one viewpoint, several exposures) found and merged into linear HDR
"""
