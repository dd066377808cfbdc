"""The viewer's render function, its model snapshots during training, and the live server."""

import urllib.request

import pytest
import torch
from conftest import train_model

from mono_hdr_plugin.apps.camera_paths import ViewerCamera, viewer_from_camera
from mono_hdr_plugin.apps.display import to_uint8
from mono_hdr_plugin.apps.viewer.gui import Viewer
from mono_hdr_plugin.apps.viewer.live_training import SnapshotPublisher
from mono_hdr_plugin.apps.viewer.renderer import ViewerRenderer, letterbox
from mono_hdr_plugin.apps.viewer.snapshots import ModelSnapshots
from mono_hdr_plugin.core.colour import srgb_encode
from mono_hdr_plugin.core.metrics import hdr_metrics
from mono_hdr_plugin.training.pipeline import RenderCancelled

# A browser camera: 10 degrees above the rig's plane, a wide 4:3 canvas.
BROWSER = ViewerCamera(wxyz=(0.2, -0.1, 0.6, 0.77), position=(0.0, -2.8, 0.9), fov=0.9, aspect=4 / 3)


def browser_camera(scene) -> ViewerCamera:
    """The camera a browser would send after orbiting to the second test view, at 4:3."""
    view = viewer_from_camera(scene.test[1].camera)
    return ViewerCamera(view.wxyz, view.position, view.fov, 4 / 3)


def reference(model, camera, exposure):
    """The pipeline's own whole-image render, independent of the viewer's code."""
    return model.pipeline.render(camera, exposure)


def renderer_of(model) -> ViewerRenderer:
    return ViewerRenderer(ModelSnapshots(model.pipeline, model.step, copy_model=False), model.scene)


class TestRenderFunction:
    @pytest.mark.parametrize("output", ["ldr", "hdr-srgb", "hdr-filmic", "hdr-mulaw", "depth"])
    def test_image_has_the_requested_size(self, voxel_mono, output):
        shown = renderer_of(voxel_mono).render(browser_camera(voxel_mono.scene), 18, output, 0.0)
        assert shown.image.shape == (18, 24, 3) and shown.image.dtype.name == "uint8"

    def test_render_is_the_backbone_seen_from_the_viewer_camera(self, voxel_mono):
        renderer = renderer_of(voxel_mono)
        camera = browser_camera(voxel_mono.scene)
        shown = renderer.render(camera, 12, "hdr-srgb", 1.5)
        expected = reference(voxel_mono, renderer.camera(camera, 12), 0.5)
        scale = voxel_mono.exposure.display_scale * 2**1.5
        assert (shown.image.astype(int) - to_uint8(srgb_encode(expected.hdr * scale)).astype(int)).__abs__().max() <= 1

    def test_exposure_scales_the_hdr_exactly(self, voxel_mono):
        """One stop more doubles the linear display value of every pixel (below white)."""
        renderer = renderer_of(voxel_mono)
        camera = browser_camera(voxel_mono.scene)
        darker = renderer.render(camera, 12, "hdr-srgb", -4.0).frame
        brighter = renderer.render(camera, 12, "hdr-srgb", -3.0, cached=darker)
        assert brighter.frame is darker  # an exposure change re-displays, it does not re-render
        linear = darker.hdr * voxel_mono.exposure.display_scale * 2.0**-4.0
        assert (to_uint8(srgb_encode(2.0 * linear)) == brighter.image).all()

    def test_mono_ldr_at_ev0_is_its_ldr_branch(self, voxel_mono):
        renderer = renderer_of(voxel_mono)
        camera = browser_camera(voxel_mono.scene)
        shown = renderer.render(camera, 12, "ldr", 0.0)
        expected = reference(voxel_mono, renderer.camera(camera, 12), 0.5).ldr
        assert (
            torch.from_numpy(shown.image).int() - torch.from_numpy(to_uint8(expected.clamp(0, 1))).int()
        ).abs().max() == 0

    def test_learned_camera_response_follows_the_exposure(self, voxel_crf):
        """HDR-NeRF's LDR at t is its CRF applied at t: the viewer re-renders at each exposure."""
        renderer = renderer_of(voxel_crf)
        camera = browser_camera(voxel_crf.scene)
        images = {}
        for ev in (-2.0, 2.0):
            shown = renderer.render(camera, 12, "ldr", ev)
            exposure = 0.5 * 2**ev
            assert shown.frame.exposure == exposure
            expected = reference(voxel_crf, renderer.camera(camera, 12), exposure).ldr
            assert (
                torch.from_numpy(shown.image).int() - torch.from_numpy(to_uint8(expected.clamp(0, 1))).int()
            ).abs().max() == 0
            images[ev] = shown.image
        assert (images[2.0] != images[-2.0]).any()

    def test_error_against_ground_truth_at_a_dataset_camera(self, voxel_mono):
        renderer = renderer_of(voxel_mono)
        view = voxel_mono.scene.test[1]
        at_view = viewer_from_camera(view.camera)
        shown = renderer.render(at_view, 16, "error-hdr", 0.0)
        expected = hdr_metrics(reference(voxel_mono, view.camera, 0.5).hdr, view.hdr)
        assert f"HDR PSNR {expected['hdr_psnr']:.2f} dB" in shown.note and view.stem in shown.note
        assert shown.image.shape == (16, 16, 3)
        assert "LDR PSNR" in renderer.render(at_view, 16, "error-ldr", 0.0).note

    def test_error_away_from_the_dataset_asks_to_go_to_a_camera(self, voxel_mono):
        shown = renderer_of(voxel_mono).render(BROWSER, 12, "error-hdr", 0.0)
        assert "go to a dataset camera" in shown.note and shown.image.shape == (12, 16, 3)

    def test_letterbox_keeps_the_image_and_pads_to_the_aspect(self):
        image = torch.randint(0, 255, (10, 10, 3), dtype=torch.uint8).numpy()
        boxed = letterbox(image, 2.0)
        assert boxed.shape == (10, 20, 3) and (boxed[:, 5:15] == image).all() and (boxed[:, :5] == 40).all()

    def test_a_moving_camera_cancels_the_render(self, voxel_mono):
        with pytest.raises(RenderCancelled):
            voxel_mono.pipeline.render(voxel_mono.scene.test[0].camera, 0.5, cancelled=lambda: True)


class TestSnapshots:
    def test_a_snapshot_does_not_change_with_the_live_model(self, voxel_mono):
        pipeline, backbone = voxel_mono.pipeline, voxel_mono.backbone
        snapshots = ModelSnapshots(pipeline, step=3)
        camera = voxel_mono.scene.test[0].camera
        before = snapshots.latest().pipeline.render(camera, 0.5).hdr
        saved = backbone.color_logits.detach().clone()
        with torch.no_grad():
            backbone.color_logits.add_(1.0)
        try:
            after = snapshots.latest().pipeline.render(camera, 0.5).hdr
            assert torch.equal(before, after)
            snapshots.publish(pipeline, step=4)
            assert snapshots.latest().version == 1 and snapshots.latest().step == 4
            assert not torch.equal(snapshots.latest().pipeline.render(camera, 0.5).hdr, before)
        finally:
            with torch.no_grad():
                backbone.color_logits.copy_(saved)

    def test_training_with_a_watching_viewer_learns_the_same_model(self, tmp_path, voxel_scene, voxel_backbone_config):
        """The publisher copies the model while someone watches; training itself is unchanged."""
        plain, _ = train_model(tmp_path / "plain", voxel_scene, "voxel-grid", voxel_backbone_config, steps=6)
        from mono_hdr_plugin.training.trainer import Trainer

        watched = Trainer(plain.config, "voxel-grid", voxel_scene)
        watched.config.out = tmp_path / "watched"
        snapshots = ModelSnapshots(watched.pipeline, 0)
        published = []
        watched.train(extra_hooks=[SnapshotPublisher(snapshots, lambda: True, published.append, min_interval=0.0)])
        assert published[-1] == 6 and snapshots.latest().step == 6
        for name, value in plain.backbone.state_dict().items():
            torch.testing.assert_close(watched.backbone.state_dict()[name], value, rtol=0, atol=0)
        torch.testing.assert_close(snapshots.latest().pipeline.backbone.color_logits, watched.backbone.color_logits)

    def test_nobody_watching_costs_no_copy(self, voxel_mono):
        snapshots = ModelSnapshots(voxel_mono.pipeline, 0)
        publisher = SnapshotPublisher(snapshots, lambda: False, lambda step: None, min_interval=0.0)

        class Step:
            pipeline, step = voxel_mono.pipeline, 9

        publisher.after_step(Step(), {})
        assert snapshots.latest().version == 0


class TestLiveServer:
    def test_serves_the_page_on_localhost_and_stops(self, voxel_mono, tmp_path):
        viewer = Viewer(renderer_of(voxel_mono), port=0, out=tmp_path)
        try:
            assert viewer.url.startswith("http://127.0.0.1:")
            page = urllib.request.urlopen(viewer.url, timeout=10).read()
            assert b"<html" in page.lower()
            assert len(viewer.renderer.views) == 8  # every train and test camera can be jumped to
        finally:
            viewer.stop()
        with pytest.raises(OSError):
            urllib.request.urlopen(viewer.url, timeout=2)
