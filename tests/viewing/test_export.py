"""Exports: the standard 3DGS PLY with its converters, and NeRF point clouds, read back by the
project's own loaders."""

import hashlib
import json

import numpy as np
import pytest
import torch
from conftest import train_model
from plyfile import PlyData

from backbones.gs import GaussianBackbone, GaussianConfig, load_ply
from backbones.nerf import GridFieldConfig, NerfConfig
from mono_hdr_plugin.apps.cli import main
from mono_hdr_plugin.apps.export import (
    converters_paths,
    export_splats,
    load_converters,
    load_point_cloud,
    point_cloud,
    points_from_depth,
    write_point_cloud,
)
from mono_hdr_plugin.core.calibration import RadianceCalibration
from mono_hdr_plugin.core.cameras import Camera
from mono_hdr_plugin.training.pipeline import Pipeline

# The vertex properties of a degree-3 3DGS PLY, in the order the reference implementation writes them.
STANDARD_3DGS = (
    ["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"]
    + [f"f_rest_{i}" for i in range(45)]
    + ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"]
)

# sha256 of the HDR recipe each method's export has written since the recipes were written (the text
# now lives in the method: MonoHDR.hdr_recipe, CrfBaseline.hdr_recipe).
RECIPE_SHA256 = {
    "mono": "3229a2004e9d46d25c15bdf8e92f16fccefbd765cecd91f6f12936bd0b4210bf",
    "hdr-gs": "bcf7749a32dbb1774664068586e636b6f2c6a27cf1a12721771de97596385eed",
}


@pytest.fixture(scope="module", params=["mono", "hdr-gs"])
def gaussians(request, tmp_path_factory, voxel_scene):
    config = GaussianConfig(random_init_points=400)
    return train_model(tmp_path_factory.mktemp("gs"), voxel_scene, "gs", config, method=request.param, steps=8)[1]


class TestSplatExport:
    def test_standard_ply_and_converters_round_trip(self, gaussians, voxel_scene, tmp_path):
        path = tmp_path / "model.ply"
        written = export_splats(gaussians, path)
        weights, description = converters_paths(path)
        assert written == [path, weights, description]
        assert list(PlyData.read(str(path))["vertex"].data.dtype.names) == STANDARD_3DGS

        loaded = GaussianBackbone(gaussians.backbone.config, voxel_scene.scene_info())
        loaded.load_gaussians(load_ply(path))
        loaded.active_sh_degree = loaded.config.sh_degree  # a PLY holds every SH band; viewers evaluate them all
        method = load_converters(path)
        info = json.loads(description.read_text())
        pipeline = Pipeline("gs", loaded.eval(), method)
        pipeline.calibration = RadianceCalibration.from_state(info["radiance_calibration"])
        assert pipeline.calibration == gaussians.pipeline.calibration and pipeline.calibration.fitted
        for view in voxel_scene.test:
            original = gaussians.pipeline.render(view.camera, 0.5)
            again = pipeline.render(view.camera, 0.5)
            torch.testing.assert_close(again.hdr, original.hdr, rtol=1e-5, atol=1e-6)
            torch.testing.assert_close(again.ldr, original.ldr, rtol=1e-5, atol=1e-6)

        assert info["method"] == gaussians.method.config.method and info["ply"] == "model.ply"
        assert info["display_scale"] == pytest.approx(gaussians.exposure.display_scale)
        with np.load(weights) as arrays:
            assert {name: list(arrays[name].shape) for name in arrays.files} == info["arrays"]

    def test_the_recipe_is_the_methods_own_and_unchanged(self, gaussians, tmp_path):
        path = tmp_path / "model.ply"
        export_splats(gaussians, path)
        recipe = json.loads(converters_paths(path)[1].read_text())["hdr_recipe"]
        assert recipe == gaussians.method.hdr_recipe
        assert hashlib.sha256(recipe.encode()).hexdigest() == RECIPE_SHA256[gaussians.method.config.method]

    def test_a_description_written_before_method_options_loads(self, gaussians, tmp_path):
        """Before methods had options of their own, method_config held HDR-NeRF's flags flat, for every method."""
        path = tmp_path / "model.ply"
        export_splats(gaussians, path)
        description = converters_paths(path)[1]
        info = json.loads(description.read_text())
        old = {key: value for key, value in info["method_config"].items() if key != "options"}
        old.update(unit_exposure_weight=0.5, unit_exposure_value=0.5, crf_warmup_steps=500)
        description.write_text(json.dumps({**info, "method_config": old}))
        method = load_converters(path)
        assert type(method) is type(gaussians.method) and method.config == gaussians.method.config

    def test_converters_must_be_beside_the_ply(self, tmp_path):
        with pytest.raises(FileNotFoundError, match="model.converters.npz"):
            load_converters(tmp_path / "model.ply")

    def test_a_foreign_description_is_refused(self, gaussians, tmp_path):
        path = tmp_path / "model.ply"
        export_splats(gaussians, path)
        _, description = converters_paths(path)
        description.write_text(json.dumps({"format": "something else", "version": 1}))
        with pytest.raises(ValueError, match="is not a version 2"):
            load_converters(path)


class TestPointCloud:
    def test_points_lie_on_the_surface_the_depth_describes(self):
        """A camera at the origin facing +z sees the plane z = 3: a ray at angle theta ends at 3 / cos(theta)."""
        camera = Camera(torch.eye(4), fx=8.0, fy=8.0, cx=4.0, cy=4.0, width=8, height=8)
        origins, directions = (t.reshape(-1, 3) for t in camera.rays())
        alpha = torch.full((64,), 0.8)
        alpha[5] = 0.1
        depth = alpha * 3.0 / directions[:, 2]  # expected distance = alpha * distance to the surface
        points, rays = points_from_depth(origins, directions, depth, alpha, min_alpha=0.5)
        assert 5 not in rays.tolist() and len(rays) == 63
        torch.testing.assert_close(points[:, 2], torch.full((63,), 3.0))

    def test_nerf_point_cloud_round_trips(self, tmp_path, voxel_scene):
        config = NerfConfig(
            field=GridFieldConfig(
                levels=2,
                min_resolution=4,
                max_resolution=8,
                hidden_width=16,
                min_step=0.125,
                max_samples_per_ray=16,
                occupancy_resolution=8,
                occupancy_update_every=2,
                rays_per_step=64,
                samples_per_step=512,
            )
        )
        _, model = train_model(tmp_path, voxel_scene, "nerf", config, steps=6)
        points, colours, hdr = point_cloud(model, min_alpha=0.0)
        assert points.shape == (4 * 16 * 16, 3)  # four training views, every ray kept at min_alpha 0
        path = write_point_cloud(tmp_path / "cloud.ply", points, colours, hdr)
        loaded_points, loaded_colours, loaded_hdr = load_point_cloud(path)
        torch.testing.assert_close(loaded_points, points)
        torch.testing.assert_close(loaded_hdr, hdr.float())
        torch.testing.assert_close(loaded_colours, torch.round(colours * 255) / 255, atol=1e-6, rtol=0)
        assert set(PlyData.read(str(path))["vertex"].data.dtype.names) >= {"x", "y", "z", "red", "green", "blue"}
        fewer, _, _ = point_cloud(model, min_alpha=0.0, max_points=100)
        assert fewer.shape == (100, 3)

    def test_a_backbone_without_depth_is_refused(self, voxel_mono):
        with pytest.raises(ValueError, match="renders no depth"):
            point_cloud(voxel_mono)

    def test_not_a_point_cloud(self, tmp_path):
        (tmp_path / "x.ply").write_text("ply\nformat ascii 1.0\nelement face 0\nend_header\n")
        with pytest.raises(ValueError, match="not a point cloud"):
            load_point_cloud(tmp_path / "x.ply")


class TestExportCommand:
    def test_voxel_grid_has_no_surface_to_export(self, tmp_path, demo_voxel_checkpoint):
        with pytest.raises(ValueError, match="'voxel-grid' backbone renders no depth"):
            main(["export", "--checkpoint", str(demo_voxel_checkpoint), "--out", str(tmp_path / "m.ply")])
        assert not (tmp_path / "m.ply").exists()

    def test_out_must_be_a_ply(self, tmp_path):
        with pytest.raises(ValueError, match="--out must name a .ply"):
            main(["export", "--checkpoint", str(tmp_path / "x.pt"), "--out", str(tmp_path / "m.obj")])
