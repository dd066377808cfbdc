"""What `tools/mutants.py` mutates: each target module, the parts of it that count, and the tests
that must kill its mutants."""

from dataclasses import dataclass


@dataclass(frozen=True)
class Target:
    """A module to mutate, the parts of it that count (qualified-name prefixes; empty: all), and
    the tests that must catch its mutants (pytest arguments, fastest and sharpest first)."""

    module: str
    path: str
    tests: tuple[str, ...]
    scopes: tuple[str, ...] = ()


WIRING = "tests/core/test_loss_wiring.py"
# test_train.py without its 150-step end-to-end run (the slowest test by far; the others cover the step)
QUICK_TRAIN_TESTS = ("tests/core/test_train.py", "-k", "not hdr_error_drops")
KNOWN_ANSWER = "tests/core/test_evaluation_known_answer.py::TestEvaluateKnownAnswer"
METHOD_TESTS = (
    "tests/core/test_methods.py",
    "tests/core/test_method_details.py",
    f"{WIRING}::test_defaults_are_the_papers",
    "tests/core/test_registry.py",
    f"{WIRING}::TestEveryLossSwitch",
    f"{WIRING}::TestWeightsByFiniteDifferences",
    KNOWN_ANSWER,
)
TRAIN_STEP_TESTS = (
    "tests/core/test_train_step.py",
    f"{WIRING}::TestEveryLossSwitch",
    f"{WIRING}::TestHdrViewRatioRows",
    f"{WIRING}::TestWeightsByFiniteDifferences",
    *QUICK_TRAIN_TESTS,
)
TARGETS = {
    "metrics": Target(
        "mono_hdr_plugin.core.metrics",
        "mono_hdr_plugin/core/metrics.py",
        ("tests/core/test_metric_values.py", "tests/core/test_metrics.py", KNOWN_ANSWER),
    ),
    "losses": Target(
        "mono_hdr_plugin.core.losses",
        "mono_hdr_plugin/core/losses.py",
        (
            "tests/core/test_metrics.py::TestLosses",
            "tests/core/test_method_details.py",
            f"{WIRING}::TestEveryLossSwitch",
        ),
    ),
    "converters": Target(
        "mono_hdr_plugin.core.converters",
        "mono_hdr_plugin/core/converters.py",
        (
            "tests/core/test_converters.py",
            "tests/core/test_method_details.py",
            "tests/core/test_methods.py",
            KNOWN_ANSWER,
        ),
    ),
    "methods": Target("mono_hdr_plugin.methods.base", "mono_hdr_plugin/methods/base.py", METHOD_TESTS),
    "methods-mono": Target("mono_hdr_plugin.methods.mono", "mono_hdr_plugin/methods/mono.py", METHOD_TESTS),
    "methods-crf": Target(
        "mono_hdr_plugin.methods.crf_baseline", "mono_hdr_plugin/methods/crf_baseline.py", METHOD_TESTS
    ),
    "methods-hdr-nerf": Target("mono_hdr_plugin.methods.hdr_nerf", "mono_hdr_plugin/methods/hdr_nerf.py", METHOD_TESTS),
    "pipeline": Target(
        "mono_hdr_plugin.training.pipeline",
        "mono_hdr_plugin/training/pipeline.py",
        (
            "tests/core/test_pipeline.py",
            "tests/core/test_train_step.py",
            f"{WIRING}::TestEveryLossSwitch",
            f"{WIRING}::TestHdrViewRatioRows",
            KNOWN_ANSWER,
            *QUICK_TRAIN_TESTS,
        ),
    ),
    "train-step": Target(
        "mono_hdr_plugin.training.trainer",
        "mono_hdr_plugin/training/trainer.py",
        TRAIN_STEP_TESTS,
        scopes=(
            "Trainer.__init__",
            "Trainer._next_view",
            "Trainer._batch",
            "Trainer._bad_tensors",
            "Trainer.train_step",
            "Trainer.evaluate",
        ),
    ),
    # the HDR view ratio the step reads (in the training config since the layer split)
    "view-ratio": Target(
        "mono_hdr_plugin.training.config",
        "mono_hdr_plugin/training/config.py",
        TRAIN_STEP_TESTS,
        scopes=("parse_view_ratio", "hdr_supervised_views"),
    ),
    "evaluation": Target(
        "mono_hdr_plugin.training.evaluation", "mono_hdr_plugin/training/evaluation.py", (KNOWN_ANSWER,)
    ),
    "rasterizer": Target(
        "backbones.gs.rasterizer",
        "backbones/gs/rasterizer.py",
        ("tests/gs/test_gs_rasterizer_api.py", "tests/gs/test_gs_rasterizer.py", "tests/gs/test_gs_edge_gradients.py"),
    ),
    # the code of 2026-12-03 on (issue 48): calibration, the HDR prior, the pyramid, bracket
    # alignment, the sky shell, the unbounded decision and the step budget of a timed run
    "calibration": Target(
        "mono_hdr_plugin.core.calibration",
        "mono_hdr_plugin/core/calibration.py",
        ("tests/core/test_calibration.py", "tests/core/test_hdr_prior.py"),
    ),
    "calibration-fit": Target(
        "mono_hdr_plugin.training.calibration",
        "mono_hdr_plugin/training/calibration.py",
        ("tests/core/test_calibration.py", "tests/core/test_hdr_prior.py", KNOWN_ANSWER),
    ),
    "hdr-prior": Target(
        "mono_hdr_plugin.training.hdr_prior",
        "mono_hdr_plugin/training/hdr_prior.py",
        ("tests/core/test_hdr_prior.py", "tests/core/test_calibration.py"),
    ),
    "pyramid": Target(
        "mono_hdr_plugin.training.pyramid",
        "mono_hdr_plugin/training/pyramid.py",
        ("tests/core/test_pyramid.py", "-k", "not automatic_pyramid_at_512_px"),
    ),
    "brackets": Target(
        "mono_hdr_plugin.data.photos.brackets",
        "mono_hdr_plugin/data/photos/brackets.py",
        ("tests/process_data/test_brackets.py",),
        scopes=(
            "spread_stops",
            "check_exposures_differ",
            "brightness_order",
            "alignment_view",
            "lines_up",
            "_ratio_spread",
            "aligned_members",
            "estimate_relative_exposures",
        ),
    ),
    "sky-gaussians": Target(
        "backbones.gs.sky_gaussians", "backbones/gs/sky_gaussians.py", ("tests/gs/test_sky_gaussians.py",)
    ),
    "unbounded-nerf": Target(
        "backbones.nerf.backbone",
        "backbones/nerf/backbone.py",
        ("tests/nerf/test_unbounded.py",),
        scopes=("unbounded_choices",),
    ),
    "unbounded-gs": Target(
        "backbones.gs.sky", "backbones/gs/sky.py", ("tests/gs/test_gs_sky.py",), scopes=("uses_environment",)
    ),
    "run-length": Target(
        "mono_hdr_plugin.training.trainer",
        "mono_hdr_plugin/training/trainer.py",
        (
            "tests/hard_cases/test_bad_input_commands.py::test_max_seconds_alone_is_not_cut_at_the_default_steps",
            "tests/gs/test_gs_training.py",
            "-k",
            "max_seconds or stops_on_time or budget_schedule",
        ),
        scopes=("Trainer._update_run_length",),
    ),
}
