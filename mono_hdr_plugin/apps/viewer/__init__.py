"""`mono-hdr view` and `mono-hdr train ... --viewer`: a live viewer in the browser (viser).

Controls: exposure (EV slider and exposure time), output (LDR through the camera response,
HDR through sRGB, filmic or mu-law, depth, error against ground truth), jump to any dataset
camera, resolution that drops while the camera moves, and saving the view as EXR + PNG.

Modules by job: `command` (ViewConfig, `mono-hdr view`), `gui` (the viser server, its controls and
one render thread per browser), `renderer` (a viewer camera and display settings in, an image out;
knows nothing of viser), `snapshots` (the models the render threads share) and `live_training`
(the training hook that publishes them, `train --viewer`).
"""
