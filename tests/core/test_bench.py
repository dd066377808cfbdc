"""Benchmarks run end to end (tiny budgets) and write the files they promise."""

import json

import pytest

import register_backbone  # noqa: F401 - registers "voxel-grid"
from mono_hdr_plugin.bench import (BenchCurvesConfig, BenchPaperConfig, bench_curves, ordering_agreement, paper_specs,
                                   write_paper_report)


class TestOrderingAgreement:
    def test_counts_agreeing_pairs(self):
        rows = [{"variant": "a", "hdr_psnr": 30.0, "paper_hdr_psnr": 38.0},
                {"variant": "b", "hdr_psnr": 20.0, "paper_hdr_psnr": 19.0},
                {"variant": "c", "hdr_psnr": 35.0, "paper_hdr_psnr": 33.0},
                {"variant": "d", "hdr_psnr": 25.0, "paper_hdr_psnr": None}]
        agree, total, disagreements = ordering_agreement(rows)
        assert (agree, total) == (2, 3) and disagreements == ["a vs c"]


class TestPaperSpecs:
    def test_every_paper_row_present(self):
        tables = paper_specs(BenchPaperConfig())
        assert [v for v, _, _ in tables["losses"]] == ["ldr", "hdr", "h2l", "ldr+hdr", "ldr+h2l", "hdr+h2l",
                                                        "ldr+hdr+h2l"]
        assert len(tables["ratios"]) == 12 and len(tables["converters"]) == 4 and len(tables["table1"]) == 4
        assert {spec.backbone for _, spec, _ in tables["table1"]} == {"nerf", "gs"}

    def test_report_lists_paper_figures(self, tmp_path):
        row = {"backbone": "gs", "variant": "mono", "hdr_psnr": 20.0, "hdr_ssim": 0.5, "ldr_psnr": 25.0,
               "ldr_ssim": 0.8, "train_seconds": 10.0, "steps": 100, "scene": "demo", "paper_hdr_psnr": 38.57}
        results = {"scene": "demo", "exposure_indices": [1], "facts": {"git_commit": "abc"}, "table1": [row]}
        write_paper_report(results, tmp_path)
        text = (tmp_path / "paper.md").read_text()
        assert "38.57" in text and "20.00" in text


class TestBenchCurves:
    def test_tiny_run_writes_json_table_and_plots(self, tmp_path, monkeypatch):
        import mono_hdr_plugin.train as train_module

        clock = iter(0.05 * k for k in range(10**6))  # every training step takes 0.05 s
        monkeypatch.setattr(train_module.time, "perf_counter", lambda: next(clock))
        config = BenchCurvesConfig(out=tmp_path, backbones=("voxel-grid",), methods=("mono", "hdr-gs"),
                                   budget_seconds=1.0, eval_points=2, max_eval_views=1)
        bench_curves(config)
        results = json.loads((tmp_path / "curves.json").read_text())
        assert results["facts"]["git_commit"] and len(results["runs"]) == 2
        run = results["runs"][0]
        assert [point["steps"] for point in run["curve"]] == [10, 20]
        assert [point["train_seconds"] for point in run["curve"]] == pytest.approx([0.5, 1.0])
        assert run["fps_ldr"] > 0 and run["fps_ldr_hdr"] > 0 and run["peak_memory_mib"] > 0
        for name in ("curves.md", "curves.png", "pareto.png"):
            assert (tmp_path / name).stat().st_size > 0


@pytest.mark.slow
class TestCompareBackbonesExample:
    def test_compare_runs_both_backbones(self, tmp_path):
        import compare_backbones

        results = compare_backbones.compare("demo", seconds=3.0, out=tmp_path, eval_points=1, max_eval_views=1)
        assert [r["backbone"] for r in results] == ["nerf", "gs"]
        assert all(r["curve"][-1]["hdr_psnr"] > 0 for r in results)
        compare_backbones.plot(results, tmp_path / "plot.png")
        assert (tmp_path / "plot.png").stat().st_size > 0
