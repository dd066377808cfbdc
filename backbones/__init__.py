"""Built-in backbones of mono-hdr-3d (NeRF, 3D Gaussian Splatting).

The import name `backbones` is shared with an unrelated PyPI package; nothing in the
project imports it implicitly: the registry loads these through the `mono_hdr.backbones`
entry points.
"""
