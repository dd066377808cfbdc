"""Plant known bugs one at a time, run the default-suite tests that should catch them, report.

    .venv/bin/python tools/planted_bugs.py                   # every bug (about 10 minutes, 2 cores)
    .venv/bin/python tools/planted_bugs.py --only h2l-detached kernel-clamped-x-sign

Each bug is one edit of the source in this checkout, reverted afterwards (also on Ctrl-C or a
crash). A C++ edit is built in a scratch extension folder, so the normal build stays valid.
A bug counts as caught when at least one of its tests fails; the Markdown table printed at the
end is the one docs/testing.md keeps. Do not edit the checkout while it runs.
"""

import argparse
import os
import re
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


@dataclass(frozen=True)
class PlantedBug:
    name: str
    kind: str
    what: str
    path: str
    old: str
    new: str
    tests: tuple[str, ...]


METRIC_TESTS = (
    "tests/core/test_metric_values.py",
    "tests/core/test_metrics.py",
    "tests/core/test_evaluation_known_answer.py",
)
EVALUATION_TESTS = ("tests/core/test_evaluation_known_answer.py",)
WIRING_TESTS = ("tests/core/test_loss_wiring.py", "tests/core/test_methods.py", "tests/core/test_train.py")
KERNEL_TESTS = ("tests/gs/test_gs_edge_gradients.py", "tests/gs/test_gs_rasterizer.py")
ROUND_TRIP_TESTS = ("tests/core/test_round_trip.py",)

BUGS = (
    # the numbers the README reports
    PlantedBug(
        "mu-5001",
        "reported numbers",
        "mu-law constant 5000 -> 5001",
        "mono_hdr_plugin/core/metrics.py",
        "MU = 5000.0",
        "MU = 5001.0",
        METRIC_TESTS,
    ),
    PlantedBug(
        "hdr-ssim-against-itself",
        "reported numbers",
        "HDR SSIM of the prediction against itself",
        "mono_hdr_plugin/core/metrics.py",
        "ssim(pred.double(), gt.double())",
        "ssim(pred.double(), pred.double())",
        METRIC_TESTS,
    ),
    PlantedBug(
        "gt-max-by-prediction",
        "reported numbers",
        "gt_max normalisation divides by the prediction's max",
        "mono_hdr_plugin/core/metrics.py",
        'gt_max = gt_hdr.max()\n    if normalisation == "own_max":',
        'gt_max = pred_hdr.max()\n    if normalisation == "own_max":',
        METRIC_TESTS,
    ),
    PlantedBug(
        "gt-not-quantised",
        "reported numbers",
        "own_max ground truth not quantised to 8 bits",
        "mono_hdr_plugin/core/metrics.py",
        "torch.round(normalise_hdr(gt_hdr) * 255.0) / 255.0",
        "normalise_hdr(gt_hdr)",
        METRIC_TESTS,
    ),
    PlantedBug(
        "ssim-sigma",
        "reported numbers",
        "SSIM window sigma 1.5 -> 2.0",
        "mono_hdr_plugin/core/metrics.py",
        "SSIM_SIGMA = 1.5",
        "SSIM_SIGMA = 2.0",
        METRIC_TESTS,
    ),
    PlantedBug(
        "psnr-20log",
        "reported numbers",
        "PSNR as 20 log10 instead of 10 log10",
        "mono_hdr_plugin/core/metrics.py",
        "10.0 * math.log10(data_range**2 / mse)",
        "20.0 * math.log10(data_range**2 / mse)",
        METRIC_TESTS,
    ),
    PlantedBug(
        "evaluate-swapped",
        "reported numbers",
        "evaluate passes HDR ground truth and prediction swapped",
        "mono_hdr_plugin/training/evaluation.py",
        "row.update(hdr_metrics(output.hdr, view.hdr))",
        "row.update(hdr_metrics(view.hdr, output.hdr))",
        EVALUATION_TESTS,
    ),
    PlantedBug(
        "headline-over-views",
        "reported numbers",
        "headline LDR PSNR averaged over views, not exposures",
        "mono_hdr_plugin/training/evaluation.py",
        '"ldr_psnr": _mean([by_exposure["ldr_psnr"][e] for e in headline]),',
        '"ldr_psnr": _mean([row["ldr_psnr"] for row in rows if row["exposure"] in headline]),',
        EVALUATION_TESTS,
    ),
    PlantedBug(
        "no-exposure-filter",
        "reported numbers",
        "Mono-HDR scored at exposures it never trained at",
        "mono_hdr_plugin/training/evaluation.py",
        "if pipeline.renders_any_exposure or v.exposure in train_exposures",
        "if True",
        EVALUATION_TESTS,
    ),
    PlantedBug(
        "hdr-every-exposure",
        "reported numbers",
        "HDR scored at every exposure of a camera, not once",
        "mono_hdr_plugin/training/evaluation.py",
        "hdr_views = {id(v) for v in first if v.hdr",
        "hdr_views = {id(v) for v in views if v.hdr",
        EVALUATION_TESTS,
    ),
    PlantedBug(
        "max-views-list-order",
        "reported numbers",
        "max_eval_views takes cameras in list order",
        "mono_hdr_plugin/training/evaluation.py",
        "view_ids = set(sorted({v.view_id for v in views})[:max_eval_views])",
        "view_ids = set(list(dict.fromkeys(v.view_id for v in views))[:max_eval_views])",
        EVALUATION_TESTS,
    ),
    # the loss reaching the parameters
    PlantedBug(
        "h2l-detached",
        "loss wiring",
        "H2L term detached (logged loss unchanged, no gradient)",
        "mono_hdr_plugin/methods/mono.py",
        'terms["h2l"] = self.beta * self._loss(output.ldr_from_hdr, targets.ldr)',
        'terms["h2l"] = self.beta * self._loss(output.ldr_from_hdr.detach(), targets.ldr)',
        WIRING_TESTS,
    ),
    PlantedBug(
        "h2l-weight-is-alpha",
        "loss wiring",
        "H2L weight replaced by the HDR weight",
        "mono_hdr_plugin/methods/mono.py",
        'terms["h2l"] = self.beta * self._loss(',
        'terms["h2l"] = self.config.alpha * self._loss(',
        WIRING_TESTS,
    ),
    PlantedBug(
        "hdr-render-detached",
        "loss wiring",
        "HDR render detached before H2L-CC (no loop gradient to L2H-CC)",
        "mono_hdr_plugin/methods/mono.py",
        "self.h2l(normalise_hdr(hdr))",
        "self.h2l(normalise_hdr(hdr.detach()))",
        WIRING_TESTS,
    ),
    PlantedBug(
        "hdr-target-unnormalised",
        "loss wiring",
        "L_hdr compares against the linear HDR ground truth",
        "mono_hdr_plugin/methods/base.py",
        "normalise_hdr(output.hdr), normalise_hdr(targets.hdr))",
        "normalise_hdr(output.hdr), targets.hdr)",
        WIRING_TESTS,
    ),
    PlantedBug(
        "h2l-not-optimised",
        "loss wiring",
        "H2L-CC left out of the optimiser (the official NeRF code's bug)",
        "mono_hdr_plugin/methods/base.py",
        'return [{"name": "method", "params": list(self.parameters()), "lr": lr}]',
        'return [{"name": "method", "params": [p for n, p in self.named_parameters() if "h2l" not in n], "lr": lr}]',
        WIRING_TESTS,
    ),
    PlantedBug(
        "hdr-only-row-keeps-ldr",
        "loss wiring",
        "the 0:1 (HDR only) ratio row keeps the LDR loss",
        "mono_hdr_plugin/training/trainer.py",
        "if ldr_share == 0:",
        "if ldr_share < 0:",
        WIRING_TESTS,
    ),
    PlantedBug(
        "hdr-to-every-view",
        "loss wiring",
        "HDR ground truth given to views the ratio excludes",
        "mono_hdr_plugin/training/batches.py",
        "hdr = view.hdr if use_hdr else None",
        "hdr = view.hdr",
        WIRING_TESTS,
    ),
    PlantedBug(
        "unit-exposure-weight",
        "loss wiring",
        "HDR-NeRF unit-exposure weight ignored",
        "mono_hdr_plugin/methods/hdr_nerf.py",
        'terms["unit_exposure"] = self.options.unit_exposure_weight * torch.mean(',
        'terms["unit_exposure"] = 0.5 * torch.mean(',
        WIRING_TESTS,
    ),
    # the kernel's edge branches
    PlantedBug(
        "kernel-clamped-x-sign",
        "kernel edge",
        "sign of the clamped-x term in the projection backward",
        "backbones/gs/csrc/gs_raster.cpp",
        "if (p.clamped_x) vt[2] += v_txc * p.lim_x;",
        "if (p.clamped_x) vt[2] -= v_txc * p.lim_x;",
        KERNEL_TESTS,
    ),
    PlantedBug(
        "kernel-clamped-y-sign",
        "kernel edge",
        "sign of the clamped-y term in the projection backward",
        "backbones/gs/csrc/gs_raster.cpp",
        "if (p.clamped_y) vt[2] += v_tyc * p.lim_y;",
        "if (p.clamped_y) vt[2] -= v_tyc * p.lim_y;",
        KERNEL_TESTS,
    ),
    PlantedBug(
        "kernel-clamp-ignored-in-backward",
        "kernel edge",
        "backward treats clamped Gaussians as unclamped",
        "backbones/gs/csrc/gs_raster.cpp",
        "if (p.clamped_x) vt[2] += v_txc * p.lim_x; else vt[0] += v_txc;",
        "vt[0] += v_txc;",
        KERNEL_TESTS,
    ),
    PlantedBug(
        "kernel-depth-jacobian",
        "kernel edge",
        "factor 2 dropped in dJ/dz of the projection backward",
        "backbones/gs/csrc/gs_raster.cpp",
        "+ 2.f * k.fx * p.txc / tz3 * vJ[2]",
        "+ k.fx * p.txc / tz3 * vJ[2]",
        KERNEL_TESTS,
    ),
    # state that shapes a render surviving save and load
    PlantedBug(
        "gs-sh-degree-lost",
        "saved state",
        "a loaded 3DGS model renders with SH degree 0",
        "backbones/gs/model.py",
        'self.active_sh_degree = int(state["active_sh_degree"])',
        "self.active_sh_degree = 0",
        ROUND_TRIP_TESTS,
    ),
    PlantedBug(
        "nerf-density-grid-lost",
        "saved state",
        "the NeRF occupancy grid is not saved",
        "backbones/nerf/fields.py",
        'self.register_buffer("occupied", torch.ones(shape, dtype=torch.bool))',
        'self.register_buffer("occupied", torch.ones(shape, dtype=torch.bool), persistent=False)',
        ROUND_TRIP_TESTS,
    ),
    # HDR without HDR views (docs/method.md, "HDR without HDR views")
    PlantedBug(
        "l2h-heads-unsigned",
        "hdr without hdr views",
        "L2H-CC's head weights not signed by their unit's direction (falling units can lower the HDR)",
        "mono_hdr_plugin/core/converters.py",
        "self.direction[:, None] * self.heads.weight.abs()",
        "self.heads.weight.abs()",
        ("tests/core/test_converters.py",),
    ),
    PlantedBug(
        "prior-times-exposure",
        "hdr without hdr views",
        "L_prior's radiance multiplied by the relative exposure instead of divided",
        "mono_hdr_plugin/training/hdr_prior.py",
        "return decode(photo, response) / relative_exposure",
        "return decode(photo, response) * relative_exposure",
        ("tests/core/test_hdr_prior.py",),
    ),
    PlantedBug(
        "prior-on-clipped-channels",
        "hdr without hdr views",
        "L_prior also pulls clipped channels to the clip level",
        "mono_hdr_plugin/methods/base.py",
        "exposed = well_exposed_channels(targets.ldr)",
        "exposed = torch.ones_like(targets.ldr, dtype=torch.bool)",
        ("tests/core/test_hdr_prior.py", "tests/core/test_loss_wiring.py"),
    ),
    PlantedBug(
        "calibration-reads-unused-truth",
        "hdr without hdr views",
        "the radiance calibration reads HDR ground truth that training was not given",
        "mono_hdr_plugin/training/calibration.py",
        "truth = view.hdr[rows, cols] if readable[index] and view.hdr is not None else None",
        "truth = view.hdr[rows, cols] if view.hdr is not None else None",
        ("tests/core/test_hdr_prior.py", "tests/core/test_calibration.py"),
    ),
)


def run_bug(bug: PlantedBug, python: str) -> tuple[bool, str, float]:
    """Plant, run its tests, revert. Returns (caught, first failing test or the reason, seconds)."""
    path = ROOT / bug.path
    original = path.read_text()
    if original.count(bug.old) != 1:
        return False, f"NOT PLANTED: the text to replace occurs {original.count(bug.old)} times in {bug.path}", 0.0
    env = dict(os.environ)
    scratch = None
    if bug.path.endswith(".cpp"):
        scratch = tempfile.mkdtemp(prefix="planted-kernel-")
        env["TORCH_EXTENSIONS_DIR"] = scratch
    started = time.perf_counter()
    try:
        path.write_text(original.replace(bug.old, bug.new))
        result = subprocess.run(
            [python, "-m", "pytest", "-q", "-x", "-p", "no:cacheprovider", *bug.tests],
            cwd=ROOT,
            env=env,
            capture_output=True,
            text=True,
        )
    finally:
        path.write_text(original)
    seconds = time.perf_counter() - started
    failed = re.findall(r"^(?:FAILED|ERROR) (\S+)", result.stdout, flags=re.MULTILINE)
    if result.returncode == 0:
        return False, "every test passed", seconds
    if not failed:
        return False, f"pytest exited {result.returncode} without a failing test:\n{result.stdout[-2000:]}", seconds
    return True, failed[0], seconds


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--only", nargs="*", help="names of the bugs to plant (default: all)")
    args = parser.parse_args()
    bugs = [bug for bug in BUGS if not args.only or bug.name in args.only]
    unknown = set(args.only or ()) - {bug.name for bug in BUGS}
    if unknown:
        parser.error(f"unknown bug(s) {sorted(unknown)}; known: {', '.join(bug.name for bug in BUGS)}")
    rows, missed = [], 0
    for bug in bugs:
        caught, detail, seconds = run_bug(bug, sys.executable)
        missed += not caught
        print(f"{'caught' if caught else 'MISSED'}  {bug.name}  ({seconds:.0f} s): {detail}", flush=True)
        rows.append(f"| {bug.kind} | {bug.what} | `{bug.path}` | {'caught: `' + detail + '`' if caught else detail} |")
    print("\n| kind | planted bug | file | result |\n|---|---|---|---|")
    print("\n".join(rows))
    print(f"\n{len(bugs) - missed} of {len(bugs)} planted bugs caught")
    return 1 if missed else 0


if __name__ == "__main__":
    sys.exit(main())
