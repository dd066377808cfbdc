"""Benchmarks run end to end (tiny budgets), write the files they promise, resume, record failures,
and decide orderings by the documented rule."""

import dataclasses
import json

import pytest
import register_backbone  # registers "voxel-grid"
import torch

from mono_hdr_plugin.apps.bench import runs
from mono_hdr_plugin.apps.bench.curves import (
    BenchCurvesConfig,
    bench_curves,
    curve_specs,
    gt_max_fall,
    plot_curves,
    scale_spread,
)
from mono_hdr_plugin.apps.bench.paper import BenchPaperConfig, best_recipes, table_variants, tuning_trials
from mono_hdr_plugin.apps.bench.paper_report import mean_spread, ordering, orderings, seed_values, write_paper_report
from mono_hdr_plugin.apps.bench.paper_tables import Variant
from mono_hdr_plugin.apps.bench.report import label
from mono_hdr_plugin.apps.bench.runs import (
    ExecutorConfig,
    RowStore,
    RunBudget,
    RunSpec,
    execute,
    parse_override,
    set_override,
)
from mono_hdr_plugin.core.registry import get_backbone


@pytest.fixture
def steps_of_50ms(monkeypatch):
    """Every training step takes 0.05 s of the trainer's clock: time budgets become exact."""
    import mono_hdr_plugin.training.trainer as train_module

    clock = iter(0.05 * k for k in range(10**7))
    monkeypatch.setattr(train_module.time, "perf_counter", lambda: next(clock))


def finished(spec: RunSpec, hdr: float, ldr: float = 20.0) -> dict:
    """A stored row with only what the aggregation reads."""
    final = {
        "hdr_psnr": hdr,
        "ldr_psnr": ldr,
        "hdr_ssim": 0.5,
        "ldr_ssim": 0.5,
        "hdr_psnr_gt_max": hdr - 5,
        "train_seconds": 10.0,
        "steps": 100,
    }
    return {"key": spec.key, "status": "ok", "final": final, "curve": [final]}


class TestOverrides:
    @pytest.mark.parametrize(
        "text,expected",
        [
            ("backbone.field.min_resolution=24", ("backbone.field.min_resolution", 24)),
            ("hdr.alpha=0.25", ("hdr.alpha", 0.25)),
            ("backbone.field.color_activation=softplus", ("backbone.field.color_activation", "softplus")),
            ('hdr.method="no-h2l"', ("hdr.method", "no-h2l")),
            ("backbone.strategy.absgrad=true", ("backbone.strategy.absgrad", True)),
            ("backbone.background=[0, 0.5, 1]", ("backbone.background", [0, 0.5, 1])),
            ("hdr.method=a=b", ("hdr.method", "a=b")),
        ],
    )
    def test_parse(self, text, expected):
        assert parse_override(text) == expected

    @pytest.mark.parametrize("text", ["softplus", "=3", ""])
    def test_parse_refuses_text_without_a_path(self, text):
        with pytest.raises(ValueError, match="PATH=VALUE"):
            parse_override(text)

    def test_set_reaches_nested_fields(self):
        config = get_backbone("nerf").presets()["cpu"]
        set_override(config, "field.l2h_input", "activated")
        assert config.field.l2h_input == "activated"

    @pytest.mark.parametrize(
        "path,missing",
        [("field.no_such", "no_such"), ("method.l2h_input", "method"), ("field.levels.deeper", "deeper")],
    )
    def test_set_names_the_unknown_part(self, path, missing):
        config = get_backbone("nerf").presets()["cpu"]
        with pytest.raises(ValueError, match=f"has no field {missing!r}"):
            set_override(config, path, 1)


class TestOrderingRule:
    @pytest.mark.parametrize(
        "ours_a,ours_b,verdict",
        [
            ((30.0, 1.0), (20.0, 1.0), "reproduced"),  # gap 10 > spreads 2, paper's sign
            ((21.0, 1.0), (20.0, 0.5), "tie"),  # gap 1 <= spreads 1.5
            ((20.0, 1.0), (30.0, 1.0), "reversed"),  # gap 10 beyond the spreads, the other way
            ((20.2, 0.0), (20.0, 0.0), "reproduced"),  # one seed: no spread, the sign decides
        ],
    )
    def test_gap_against_spread(self, ours_a, ours_b, verdict):
        assert ordering(ours_a, ours_b, paper_a=38.0, paper_b=19.0) == verdict

    def test_orderings_skip_rows_without_paper_figure(self):
        rows = [
            {"variant": "a", "paper_hdr_psnr": 38.0, "hdr_psnr": (30.0, 0.1)},
            {"variant": "b", "paper_hdr_psnr": 19.0, "hdr_psnr": (35.0, 0.1)},
            {"variant": "c", "paper_hdr_psnr": None, "hdr_psnr": (10.0, 0.1)},
        ]
        assert orderings(rows) == [("a", "b", "reversed")]


class TestAggregation:
    def test_mean_over_exposures_then_spread_over_seeds(self, tmp_path):
        store = RowStore(tmp_path / "paper.json", {})
        variant = Variant("table1", "3DGS mono", RunSpec("gs"), seeds=(0, 1), scenes=("demo",))
        values = {(0, 0): 20.0, (0, 2): 22.0, (1, 0): 24.0, (1, 2): 26.0}  # (seed, exposure) -> HDR PSNR
        for (seed, exposure), hdr in values.items():
            store.rows[RunSpec("gs", scene="demo", exposure_index=exposure, seed=seed).key] = finished(
                RunSpec("gs", scene="demo", exposure_index=exposure, seed=seed), hdr
            )
        per_seed = seed_values(variant, store, (0, 2), "hdr_psnr")
        assert per_seed == {0: 21.0, 1: 25.0}
        mean, spread = mean_spread(per_seed)
        assert mean == 23.0 and spread == pytest.approx(2**0.5 * 2.0)  # stdev of 21 and 25

    def test_a_seed_with_a_failed_run_is_left_out(self, tmp_path):
        store = RowStore(tmp_path / "paper.json", {})
        variant = Variant("table1", "x", RunSpec("gs"), seeds=(0, 1), scenes=("demo",))
        ok = RunSpec("gs", scene="demo", seed=0)
        store.rows[ok.key] = finished(ok, 20.0)
        bad = RunSpec("gs", scene="demo", seed=1)
        store.rows[bad.key] = {"key": bad.key, "status": "failed", "error": "boom"}
        assert seed_values(variant, store, (1,), "hdr_psnr") == {0: 20.0}


class TestPaperTables:
    def test_every_paper_row_on_the_paper_backbones(self):
        variants = table_variants(BenchPaperConfig())
        by_table = {t: [v for v in variants if v.table == t] for t in ("table1", "converters", "losses", "ratios")}
        assert [len(v) for v in by_table.values()] == [4, 4, 7, 12]
        assert {v.spec.backbone for v in by_table["table1"]} == {"nerf", "gs"}
        assert {v.spec.backbone for v in variants if v.table != "table1"} == {"gs"}
        assert all(len(v.seeds) == 3 for v in by_table["table1"])

    def test_every_method_gets_the_same_number_of_trials_off_the_reported_scenes(self):
        trials = tuning_trials(BenchPaperConfig(tune_scene="demo"))
        assert set(trials) == {("NeRF", "hdr-nerf"), ("NeRF", "mono"), ("3DGS", "hdr-gs"), ("3DGS", "mono")}
        for row in ("NeRF", "3DGS"):
            assert len({len(specs) for (r, _), specs in trials.items() if r == row}) == 1, row
        gs_paths = {path for spec in trials[("3DGS", "mono")] for path, _ in spec.overrides}
        assert {"backbone.lr_sh_dc", "backbone.lr_means", "hdr.converter_lr"} <= gs_paths
        assert len(trials[("3DGS", "hdr-gs")]) == 8, "2 x 2 backbone rates times 2 converter rates"
        nerf_paths = {path for spec in trials[("NeRF", "mono")] for path, _ in spec.overrides}
        assert {"backbone.field.grid_lr", "backbone.field.mlp_lr", "hdr.converter_lr"} <= nerf_paths
        assert all(spec.scene == "demo" for specs in trials.values() for spec in specs)

    @pytest.mark.parametrize("quick", [False, True])
    def test_resolution_reaches_every_run(self, quick):
        config = BenchPaperConfig(resolution=400, quick=quick).resolved()
        runs = [spec for v in table_variants(config) for spec in v.runs(config.exposure_indices)]
        runs += [spec for specs in tuning_trials(config).values() for spec in specs] if not quick else []
        assert runs and all(spec.resolution == 400 for spec in runs)
        assert all(spec.key.endswith("|400px") for spec in runs)

    def test_trials_of_the_paper_preset_tune_its_own_fields(self):
        """The official MLP field has one learning rate and no grid: its trials must set that one
        (the grid's rates were tuned before, and setting them failed)."""
        trials = tuning_trials(BenchPaperConfig(tune_scene="demo", presets=("nerf=paper",)))
        nerf_paths = {path for spec in trials[("NeRF", "mono")] for path, _ in spec.overrides}
        assert "backbone.field.lr" in nerf_paths and "backbone.field.grid_lr" not in nerf_paths
        for spec in trials[("NeRF", "mono")]:
            config = get_backbone("nerf").presets()["paper"]
            for path, value in spec.overrides:
                if path.startswith("backbone."):
                    set_override(config, path.removeprefix("backbone."), value)
            assert config.field.lr == dict(spec.overrides)["backbone.field.lr"]

    def test_best_recipe_is_the_highest_hdr_psnr(self, tmp_path):
        store = RowStore(tmp_path / "paper.json", {})
        specs = [RunSpec("gs", overrides=(("hdr.converter_lr", lr),)) for lr in (1e-4, 1e-3, 1e-2)]
        for spec, hdr in zip(specs, (20.0, 25.0, 22.0)):
            store.rows[spec.key] = finished(spec, hdr)
        best = best_recipes({("3DGS", "mono"): specs}, store)[("3DGS", "mono")]
        assert best["overrides"] == {"hdr.converter_lr": 1e-3} and best["tune_hdr_psnr"] == 25.0

    def test_report_lists_means_spreads_paper_figures_and_plots(self, tmp_path):
        config = BenchPaperConfig(
            out=tmp_path, scenes=("demo",), exposure_indices=(1,), seeds=(0, 1), tables=("table1",)
        )
        variants = table_variants(config)
        store = RowStore(tmp_path / "paper.json", {"budget": {"seconds": 60.0, "steps": None}})
        for number, variant in enumerate(variants):
            for spec in variant.runs((1,)):
                store.rows[spec.key] = finished(spec, 20.0 + 5 * number + spec.seed)
        write_paper_report(config, variants, {}, store)
        text = (tmp_path / "paper.md").read_text()
        assert "35.30" in text and "20.50 +- 0.71" in text and "HDR PSNR demo" in text and "128 x 128 px" in text
        assert (tmp_path / "paper_table1.png").stat().st_size > 0 and (tmp_path / "paper_curves.png").is_file()


class TestPeakMemory:
    def test_a_reset_forgets_an_earlier_peak_and_sees_a_later_one(self):
        """What the sequential executor relies on for each row's own peak (64 MiB blocks are mmap-ed, so
        freeing one returns it to the kernel)."""
        block = torch.ones(16 * 2**20)  # 64 MiB of float32, written: resident
        with_block = runs.peak_memory_mib()
        del block
        if not runs.reset_peak_memory():  # no /proc/self/clear_refs here: the process's peak stands
            assert runs.peak_memory_mib() >= with_block
            return
        after_reset = runs.peak_memory_mib()
        assert after_reset < with_block - 48
        block = torch.ones(16 * 2**20)
        assert runs.peak_memory_mib() > after_reset + 48
        del block


class TestExecution:
    def test_resume_skips_finished_rows_and_failures_are_recorded(self, tmp_path, monkeypatch):
        specs = [RunSpec("voxel-grid", seed=s) for s in range(3)]
        store = RowStore(tmp_path / "rows.json", {"x": 1})
        store.add(finished(specs[0], 20.0))
        calls = []

        def fake_run(spec, budget, out, threads=None):
            calls.append(spec.seed)
            if spec.seed == 2:
                raise RuntimeError("out of memory")
            return finished(spec, 21.0)

        monkeypatch.setattr(runs, "run_row", fake_run)
        execute(
            specs, RunBudget(steps=1), RowStore(tmp_path / "rows.json", {"x": 1}), tmp_path, ExecutorConfig(retries=1)
        )
        assert calls == [1, 2, 2]  # seed 0 was done; seed 2 tried twice
        rows = json.loads((tmp_path / "rows.json").read_text())["rows"]
        assert rows[specs[2].key]["status"] == "failed" and "out of memory" in rows[specs[2].key]["error"]
        assert rows[specs[0].key]["status"] == rows[specs[1].key]["status"] == "ok"

    def test_other_settings_start_afresh_and_keep_the_earlier_file(self, tmp_path):
        RowStore(tmp_path / "rows.json", {"budget": 1}).add(finished(RunSpec("gs"), 20.0))
        assert not RowStore(tmp_path / "rows.json", {"budget": 2}).rows
        (aside,) = tmp_path.glob("rows.earlier-*.json")
        assert list(json.loads(aside.read_text())["rows"]) == [RunSpec("gs").key]

    def test_a_file_of_an_older_version_with_more_settings_resumes(self, tmp_path):
        """curves.json of earlier versions named the rows they ran among the settings."""
        RowStore(tmp_path / "rows.json", {"budget": 1, "specs": ["a"]}).add(finished(RunSpec("gs"), 20.0))
        assert list(RowStore(tmp_path / "rows.json", {"budget": 1}).rows) == [RunSpec("gs").key]

    def test_ray_missing_says_how_to_install(self, tmp_path, monkeypatch):
        monkeypatch.setitem(__import__("sys").modules, "ray", None)
        with pytest.raises(ValueError, match=r"pip install -e '\.\[distributed\]'"):
            execute(
                [RunSpec("gs")],
                RunBudget(steps=1),
                RowStore(tmp_path / "r.json", {}),
                tmp_path,
                ExecutorConfig(executor="ray"),
            )


class TestBenchCurves:
    def test_tiny_run_writes_json_table_and_plots(self, tmp_path, steps_of_50ms, monkeypatch):
        tiny = register_backbone.VoxelGridConfig(resolution=8, samples_per_ray=8)
        monkeypatch.setattr(register_backbone.VoxelGridBackbone, "presets", classmethod(lambda cls: {"tiny": tiny}))
        config = BenchCurvesConfig(
            out=tmp_path,
            backbones=("voxel-grid",),
            methods=("mono", "hdr-gs"),
            budget_seconds=0.5,
            eval_points=2,
            max_eval_views=1,
        )
        bench_curves(config)
        results = json.loads((tmp_path / "curves.json").read_text())
        assert results["facts"]["git_commit"] and len(results["rows"]) == 2
        row = next(iter(results["rows"].values()))
        assert [point["steps"] for point in row["curve"]] == [5, 10]
        assert [point["train_seconds"] for point in row["curve"]] == pytest.approx([0.25, 0.5])
        assert row["mean_step_seconds"] == pytest.approx(0.05) and row["fps_ldr_hdr"] > 0
        text = (tmp_path / "curves.md").read_text()
        assert "voxel-grid / hdr-gs" in text and "50.0" in text
        assert (tmp_path / "curves.png").stat().st_size > 0

    def test_a_second_run_of_other_rows_keeps_the_first_runs_rows(self, tmp_path, steps_of_50ms, monkeypatch):
        """A second scene or method into the same --out goes beside the first (it once replaced them)."""
        tiny = register_backbone.VoxelGridConfig(resolution=8, samples_per_ray=8)
        monkeypatch.setattr(register_backbone.VoxelGridBackbone, "presets", classmethod(lambda cls: {"tiny": tiny}))
        for method in ("mono", "hdr-gs"):
            bench_curves(
                BenchCurvesConfig(
                    out=tmp_path, backbones=("voxel-grid",), methods=(method,), budget_steps=2, eval_points=1
                )
            )
        rows = json.loads((tmp_path / "curves.json").read_text())["rows"].values()
        assert sorted(row["spec"]["method"] for row in rows) == ["hdr-gs", "mono"]
        text = (tmp_path / "curves.md").read_text()
        assert "voxel-grid / mono" in text and "voxel-grid / hdr-gs" in text

    def test_a_run_keeps_its_colour_in_every_scene(self, tmp_path, monkeypatch):
        import matplotlib.pyplot as plt

        figures = []
        monkeypatch.setattr(plt, "close", figures.append)  # keep the figure to read its lines
        point = {"train_seconds": 1.0, "hdr_psnr": 30.0, "hdr_psnr_gt_max": 30.0, "ldr_psnr": 30.0}
        rows = [
            {"spec": dataclasses.asdict(RunSpec(backbone, scene=scene)), "curve": [point]}
            for scene, backbones in (("demo", ["nerf"]), ("lamp-room", ["gs", "nerf"]))
            for backbone in backbones
        ]
        plot_curves(rows, tmp_path / "plot.png")
        axes = figures[0].axes  # a row of panels per scene, demo first
        demo_panel, lamp_room_panel = axes[0], axes[len(axes) // 2]
        nerf = label(rows[0]["spec"])
        (demo_line,) = (line for line in demo_panel.get_lines() if line.get_label() == nerf)
        (lamp_room_line,) = (line for line in lamp_room_panel.get_lines() if line.get_label() == nerf)
        assert demo_line.get_color() == lamp_room_line.get_color()

    def test_a_step_budget_ends_every_run_at_its_steps(self, tmp_path, steps_of_50ms, monkeypatch):
        tiny = register_backbone.VoxelGridConfig(resolution=8, samples_per_ray=8)
        monkeypatch.setattr(register_backbone.VoxelGridBackbone, "presets", classmethod(lambda cls: {"tiny": tiny}))
        config = BenchCurvesConfig(
            out=tmp_path, backbones=("voxel-grid",), methods=("mono",), budget_steps=6, eval_points=2, max_eval_views=1
        )
        row = next(iter(bench_curves(config)["rows"].values()))
        assert [point["steps"] for point in row["curve"]] == [3, 6]
        assert row["curve"][-1]["radiance_scale"] > 0 and row["curve"][-1]["hdr_psnr_masked"] is not None

    def test_set_overrides_every_row_and_names_it(self):
        plain = BenchCurvesConfig(backbones=("voxel-grid",), methods=("mono",))
        varied = BenchCurvesConfig(backbones=("voxel-grid",), methods=("mono",), set=("pyramid_levels=3",))
        [spec] = curve_specs(varied)
        assert spec.overrides == (("pyramid_levels", 3),)
        assert spec.key != curve_specs(plain)[0].key
        stored = json.loads(json.dumps(dataclasses.asdict(spec)))  # as a row's spec comes back from curves.json
        assert label(stored) == "voxel-grid / mono [pyramid_levels=3]"
        assert label({**stored, "resolution": 512}) == "voxel-grid / mono [pyramid_levels=3] at 512 px"

    def test_curve_summaries_by_hand(self):
        curve = [
            {"hdr_psnr_gt_max": 20.0, "radiance_scale": 9.0},
            {"hdr_psnr_gt_max": 25.0, "radiance_scale": 4.0},
            {"hdr_psnr_gt_max": 22.5, "radiance_scale": 2.0},
            {"hdr_psnr_gt_max": 24.0, "radiance_scale": 2.1},
        ]
        assert gt_max_fall(curve) == pytest.approx(2.5)  # from 25 (second point) to 22.5
        assert gt_max_fall(curve[:2]) == 0.0
        assert scale_spread(curve) == pytest.approx(0.05)  # the second half: 2.0 and 2.1
        assert gt_max_fall([{"hdr_psnr_gt_max": None}]) is None

    def test_a_row_with_its_own_threads_leaves_the_callers(self, tmp_path, steps_of_50ms, monkeypatch):
        """The sequential executor runs rows in this process: a row's --cpus-per-run must not stay
        behind (later runs, and the pinned-metrics tests after a bench test, use 2 threads)."""
        tiny = register_backbone.VoxelGridConfig(resolution=8, samples_per_ray=8)
        monkeypatch.setattr(register_backbone.VoxelGridBackbone, "presets", classmethod(lambda cls: {"tiny": tiny}))
        before = torch.get_num_threads()
        row = runs.run_row(
            RunSpec("voxel-grid"), RunBudget(steps=2, eval_points=1, max_eval_views=1), str(tmp_path), threads=1
        )
        assert row["threads"] == 1 and torch.get_num_threads() == before


@pytest.mark.slow
class TestRayExecutor:
    def test_quick_paper_on_ray_matches_sequential(self, tmp_path):
        import ray  # the slow suite installs the `distributed` extra (make test-slow)

        from mono_hdr_plugin.apps.bench.paper import bench_paper

        sequential = bench_paper(
            BenchPaperConfig(out=tmp_path / "seq", quick=True, executor=ExecutorConfig(cpus_per_run=1))
        )
        try:
            distributed = bench_paper(
                BenchPaperConfig(
                    out=tmp_path / "ray", quick=True, executor=ExecutorConfig(executor="ray", cpus_per_run=1)
                )
            )
        finally:
            ray.shutdown()
        assert sequential["rows"].keys() == distributed["rows"].keys() and len(sequential["rows"]) == 8
        for key, row in sequential["rows"].items():
            ours, theirs = row["final"], distributed["rows"][key]["final"]
            assert row["status"] == distributed["rows"][key]["status"] == "ok"
            assert [ours[m] for m in ("steps", "hdr_psnr", "ldr_psnr")] == [
                theirs[m] for m in ("steps", "hdr_psnr", "ldr_psnr")
            ], key


@pytest.mark.slow
class TestCompareBackbonesExample:
    def test_compare_runs_both_backbones(self, tmp_path):
        import compare_backbones

        results = compare_backbones.compare("demo", seconds=3.0, out=tmp_path, eval_points=1, max_eval_views=1)
        assert [r["spec"]["backbone"] for r in results] == ["nerf", "gs"]
        assert all(r["final"]["hdr_psnr"] > 0 for r in results)
        compare_backbones.plot(results, tmp_path / "plot.png")
        assert (tmp_path / "plot.png").stat().st_size > 0
