"""Initialisation from geometry: studio surface points, the same points through a written HDR-GS
dataset (COLMAP points3D), and random points in the bounds when a scene has none."""

import torch

from backbones.gs import GaussianBackbone, GaussianConfig, McmcStrategy
from backbones.gs.sh import sh_to_rgb
from mono_hdr_plugin.apps.studio.commands import SynthConfig, synth
from mono_hdr_plugin.data.config import DataConfig
from mono_hdr_plugin.data.loading import load_scene


def backbone_for(scene, **config) -> GaussianBackbone:
    torch.manual_seed(0)
    return GaussianBackbone(GaussianConfig(**config), scene.scene_info())


class TestInitialisationFromPoints:
    def test_studio_scene_starts_on_its_surface_points(self):
        scene = load_scene(DataConfig(scene="demo"))
        assert scene.points is not None and len(scene.points) > 100
        backbone = backbone_for(scene)
        torch.testing.assert_close(backbone.means.detach(), scene.points)
        torch.testing.assert_close(sh_to_rgb(backbone.sh_dc.detach()[:, 0]), scene.point_colors, rtol=0, atol=1e-6)
        # surface points, not a cloud: each lies on a surface some training camera sees
        distances = torch.cdist(scene.points[:200], scene.points).topk(2, largest=False).values[:, 1]
        assert distances.median() < 0.05 * (scene.bounds_max - scene.bounds_min).norm()

    def test_synthesised_hdr_gs_dataset_initialises_the_same_way(self, tmp_path):
        """`mono-hdr synth --layout hdr-gs` writes the studio's points into sparse/0/points3D."""
        folder = synth(SynthConfig(scene="demo", out=tmp_path / "demo-hdr-gs", layout="hdr-gs"))
        assert (folder / "sparse" / "0" / "points3D.bin").is_file()
        studio, written = load_scene(DataConfig(scene="demo")), load_scene(DataConfig(data=folder))
        assert written.points.shape == studio.points.shape
        a, b = backbone_for(studio), backbone_for(written)
        torch.testing.assert_close(b.means, a.means, rtol=0, atol=1e-5)
        # COLMAP stores 8-bit colours
        torch.testing.assert_close(
            sh_to_rgb(b.sh_dc.detach()), sh_to_rgb(a.sh_dc.detach()), rtol=0, atol=0.5 / 255 + 1e-6
        )
        torch.testing.assert_close(b.log_scales, a.log_scales, rtol=0, atol=1e-4)

    def test_budget_smaller_than_the_points_keeps_a_subset(self):
        scene = load_scene(DataConfig(scene="demo"))
        backbone = backbone_for(scene, strategy=McmcStrategy(max_gaussians=50))
        assert backbone.num_gaussians == 50
        assert (backbone.means.detach()[:, None, :] == scene.points[None]).all(-1).any(1).all()

    def test_no_points_means_random_inside_the_bounds(self):
        scene = load_scene(DataConfig(scene="demo"))
        scene.points = scene.point_colors = None
        backbone = backbone_for(scene, random_init_points=300)
        assert backbone.num_gaussians == 300
        means = backbone.means.detach()
        assert ((means >= scene.bounds_min) & (means <= scene.bounds_max)).all()
