"""`mono-hdr bench cost`: resized views keep their geometry, a row measures what it says, the report's ratios."""

import json

import pytest
import register_backbone  # registers "voxel-grid"
import torch

from mono_hdr_plugin.apps.bench import cost
from mono_hdr_plugin.apps.bench.cost import (
    BenchCostConfig,
    bench_cost,
    cost_row,
    held_mib,
    resized_scene,
    resized_view,
    write_cost_report,
)
from mono_hdr_plugin.apps.bench.runs import RowStore
from mono_hdr_plugin.core.cameras import Camera, look_at
from mono_hdr_plugin.data.dataset import View


class TestResizedView:
    @pytest.mark.parametrize("side", [24, 40])
    def test_camera_projects_to_the_scaled_pixel_and_images_keep_their_values(self, side):
        camera = Camera(look_at(torch.tensor([0.5, -3.0, 1.0]), torch.zeros(3)), 20.0, 21.0, 8.3, 7.8, 16, 16)
        image = torch.full((16, 16, 3), 0.25)
        hdr = torch.full((16, 16, 3), 300.0)
        bigger = resized_view(View(camera, image, 0.5, 0, "v", hdr=hdr), side)
        assert (bigger.camera.width, bigger.camera.height) == (side, side)
        assert bigger.image.shape == bigger.hdr.shape == (side, side, 3)
        torch.testing.assert_close(bigger.image, torch.full((side, side, 3), 0.25))
        torch.testing.assert_close(bigger.hdr, torch.full((side, side, 3), 300.0))
        points = torch.tensor([[0.1, 0.2, 0.3], [-0.4, 0.1, -0.2]])
        torch.testing.assert_close(
            bigger.camera.project(points)[0], camera.project(points)[0] * side / 16, atol=1e-4, rtol=0
        )


class TestResizedScene:
    def test_views_repeat_in_order_each_with_its_own_tensors(self, voxel_scene):
        scene = resized_scene(voxel_scene, 32, train_views=len(voxel_scene.train) * 2 + 1)
        assert [v.name for v in scene.train] == [v.name for v in (voxel_scene.train * 3)[: len(scene.train)]]
        assert len({v.image.data_ptr() for v in scene.train}) == len(scene.train)
        assert len(scene.test) == 1
        images = len(scene.train) + len(scene.test)
        with_hdr = sum(v.hdr is not None for v in scene.train + scene.test)
        assert held_mib(scene) == pytest.approx((images + with_hdr) * 32 * 32 * 3 * 4 / 2**20)


@pytest.fixture
def steps_of_50ms(monkeypatch):
    """Every training step takes 0.05 s of the trainer's clock."""
    import mono_hdr_plugin.training.trainer as train_module

    clock = iter(0.05 * k for k in range(10**7))
    monkeypatch.setattr(train_module.time, "perf_counter", lambda: next(clock))


class TestCostRow:
    def test_a_row_measures_its_steps_data_and_peaks(self, tmp_path, voxel_scene, steps_of_50ms, monkeypatch):
        tiny = register_backbone.VoxelGridConfig(resolution=8, samples_per_ray=8)
        monkeypatch.setattr(register_backbone.VoxelGridBackbone, "presets", classmethod(lambda cls: {"tiny": tiny}))
        monkeypatch.setattr(cost, "cached_scene", lambda name, exposure_index: voxel_scene)
        caller_threads = torch.get_num_threads()
        config = BenchCostConfig(out=tmp_path, warmup_steps=1, timed_steps=3, threads=1)
        try:
            row = cost_row("voxel-grid", 24, 5, config)
        finally:
            torch.set_num_threads(caller_threads)
        assert row["key"] == "voxel-grid|24px|5views" and row["threads"] == 1
        assert row["ms_per_step"] == pytest.approx(50.0)
        assert row["data_mib"] == pytest.approx(held_mib(resized_scene(voxel_scene, 24, 5)))
        peaks = [row["peak_mib"][phase] for phase in ("data", "training", "render", "evaluation")]
        assert peaks == sorted(peaks) and peaks[0] > 0

    def test_region_pixels_train_the_row_on_crops(self, tmp_path, voxel_scene, monkeypatch):
        tiny = register_backbone.VoxelGridConfig(resolution=8, samples_per_ray=8)
        monkeypatch.setattr(register_backbone.VoxelGridBackbone, "presets", classmethod(lambda cls: {"tiny": tiny}))
        monkeypatch.setattr(cost, "cached_scene", lambda name, exposure_index: voxel_scene)
        sizes = []
        original = cost.build_run

        def recording(*args, **kwargs):
            trainer = original(*args, **kwargs)
            forward = trainer.pipeline.forward

            def recorded(camera, *rest, **options):
                sizes.append(camera.output_shape)
                return forward(camera, *rest, **options)

            trainer.pipeline.forward = recorded
            return trainer

        monkeypatch.setattr(cost, "build_run", recording)
        caller_threads = torch.get_num_threads()
        config = BenchCostConfig(out=tmp_path, warmup_steps=0, timed_steps=2, threads=1, region_pixels=144)
        try:
            cost_row("voxel-grid", 24, 5, config)
        finally:
            torch.set_num_threads(caller_threads)
        assert sizes[:2] == [(12, 12), (12, 12)]  # 144 of the 24 x 24 pixels a step


def measured(backbone: str, side: int, views: int, ms: float) -> dict:
    return {
        "key": f"{backbone}|{side}px|{views}views",
        "backbone": backbone,
        "side": side,
        "train_views": views,
        "status": "ok",
        "ms_per_step": ms,
        "render_seconds": 0.5,
        "evaluate_seconds": 1.0,
        "data_mib": 10.0,
        "peak_mib": {"data": 100.0, "training": 200.0, "render": 210.0, "evaluation": 220.0},
        "backbone_statistics": {"gaussians": 1000},
    }


class TestCostReport:
    def test_ratios_against_the_smallest_side_and_the_fewest_views(self, tmp_path):
        store = RowStore(tmp_path / "cost.json", {})
        for row in (measured("gs", 128, 18, 50.0), measured("gs", 256, 18, 150.0), measured("gs", 256, 108, 300.0)):
            store.add(row)
        store.add({"key": "gs|512px|18views", "status": "failed", "error": "MemoryError()"})
        write_cost_report(store, tmp_path)
        header, _, *lines = (tmp_path / "cost.md").read_text().splitlines()
        assert header == "Training steps on whole images."
        lines = lines[2:]
        cells = [[cell.strip() for cell in line.strip("|").split("|")] for line in lines]
        assert [row[:7] for row in cells] == [
            ["gs", "128", "18", "50", "1.00", "1.0", "1.00"],
            ["gs", "256", "18", "150", "3.00", "4.0", "1.00"],
            ["gs", "256", "108", "300", "1.00", "1.0", "2.00"],
        ]
        assert all(row[7] == "1000" for row in cells)  # the Gaussians the step times were taken at
        assert (tmp_path / "cost.png").stat().st_size > 0


@pytest.mark.slow
def test_each_row_runs_in_its_own_process_and_a_rerun_resumes(tmp_path):
    config = BenchCostConfig(out=tmp_path, backbones=("gs",), sizes=(32,), views=(2, 3), warmup_steps=1, timed_steps=1)
    first = bench_cost(config)["rows"]
    assert sorted(first) == ["gs|32px|2views", "gs|32px|3views"]
    assert all(row["status"] == "ok" and row["ms_per_step"] > 0 for row in first.values())
    stored = json.loads((tmp_path / "cost.json").read_text())["rows"]
    assert bench_cost(config)["rows"] == stored  # nothing measured again
