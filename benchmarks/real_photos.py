"""Table of the real-photo runs (benchmarks/run_real_lund.sh): what process-data placed and how well,
and each training run's held-out LDR scores, as JSON and Markdown beside the runs."""

import argparse
import json
from pathlib import Path

from mono_hdr_plugin.training.evaluation import RADIANCE_KEYS

RUN_KEYS = (
    "backbone",
    "method",
    "ldr_psnr",
    "ldr_ssim",
    "ldr_psnr_appearance_fitted",
    "ldr_ssim_appearance_fitted",
    "appearance_protocol",
    "ldr_exposure_fitted",
    "steps",
    "train_seconds",
    "test_views",
    "hdr_basis",
    "hdr_warnings",
    *RADIANCE_KEYS,
)
RUNS = ("baseline", "white-balance", "camera-opt", "nerf", "hdr-gs", "prior-1")
"""The runs of benchmarks/run_real_lund.sh, in the order the table lists them."""


def summary(out: Path) -> dict:
    report = json.loads((out / "process_data.json").read_text())
    timing = out / "process_data_time.json"
    placement = {
        "photos": len(report["photos"]),
        "placed": sum(photo["registered"] for photo in report["photos"]),
        "mapper": report["mapper"],
        "placed_by_each_mapper": {attempt["mapper"]: attempt["placed"] for attempt in report["mapper_attempts"]},
        "mean_reprojection_error_px": round(report["mean_reprojection_error"], 3),
        "gps_rms_m": None if report["gps_rms_m"] is None else round(report["gps_rms_m"], 2),
        "seconds": json.loads(timing.read_text())["process_data_seconds"] if timing.is_file() else None,
    }
    runs = {}
    for name in RUNS:
        if (out / name / "metrics.json").is_file():
            metrics = json.loads((out / name / "metrics.json").read_text())
            runs[name] = {key: metrics.get(key) for key in RUN_KEYS}
    return {"process_data": placement, "runs": runs}


def markdown(result: dict) -> str:
    placement = result["process_data"]
    lines = [
        "# opensfm_lund: folder to trained model",
        "",
        f"process-data placed {placement['placed']} of {placement['photos']} photos with the "
        f"{placement['mapper']} mapper (placed by each: {placement['placed_by_each_mapper']}), mean reprojection "
        f"error {placement['mean_reprojection_error_px']} px, camera centres {placement['gps_rms_m']} m RMS from the "
        f"photos' GPS after a similarity fit"
        + (f", in {placement['seconds']:.0f} s" if placement["seconds"] else "")
        + ".",
        "",
        "Held-out LDR scores of the 4 held-out photos (every 8th): as given (at the exposure fitted to the whole "
        "photo and the mean white balance), and with the held-out protocol (exposure, white balance and, where "
        "training refined poses, the pose fitted on the left half of each photo; PSNR / SSIM of the right half).",
        "",
        "| run | backbone / method | as given: PSNR (dB) | SSIM | held-out protocol: PSNR (dB) | SSIM | steps "
        "| seconds |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for name, run in result["runs"].items():
        lines.append(
            f"| {name} | {run['backbone']} / {run['method']} | {run['ldr_psnr']:.2f} | {run['ldr_ssim']:.3f} | "
            f"{run['ldr_psnr_appearance_fitted']:.2f} | {run['ldr_ssim_appearance_fitted']:.3f} | "
            f"{run['steps']} | {run['train_seconds']:.0f} |"
        )
    lines += [
        "",
        "The HDR (no HDR views: it rests on the sRGB response and the exposure ratios), per channel r / g / b over "
        "the well-exposed values: rank correlation and log-log slope against the linearised test photo, and "
        "against the model's own LDR render of it (the HDR branch alone; method.md, 'Scores without ground truth').",
        "",
        "| run | rank, photo | slope, photo | rank, own LDR | slope, own LDR |",
        "|---|---|---|---|---|",
    ]
    for name, run in result["runs"].items():
        cells = [
            " / ".join(
                "-" if run.get(f"{against}{score}_{c}") is None else f"{run[f'{against}{score}_{c}']:.2f}"
                for c in "rgb"
            )
            for against in ("hdr_", "hdr_own_ldr_")
            for score in ("rank_correlation", "log_slope")
        ]
        lines.append(f"| {name} | " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--out", type=Path, required=True)
    out = parser.parse_args().out
    result = summary(out)
    (out / "summary.json").write_text(json.dumps(result, indent=2) + "\n")
    (out / "summary.md").write_text(markdown(result))
    print(markdown(result))


if __name__ == "__main__":
    main()
