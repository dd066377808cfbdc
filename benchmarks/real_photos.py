"""Table of the real-photo runs (benchmarks/run_real_lund.sh): what process-data placed and how well,
and each training run's held-out LDR scores, as JSON and Markdown beside the runs."""

import argparse
import json
from pathlib import Path

RUN_KEYS = ("ldr_psnr", "ldr_ssim", "ldr_exposure_fitted", "steps", "train_seconds", "test_views", "hdr_warnings")


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
    for run in sorted(out.glob("camera-opt-*")):
        metrics = json.loads((run / "metrics.json").read_text())
        runs[run.name] = {key: metrics.get(key) for key in RUN_KEYS}
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
        "| run | held-out LDR PSNR (dB) | SSIM | views scored at a fitted exposure | steps | seconds |",
        "|---|---|---|---|---|---|",
    ]
    for name, run in result["runs"].items():
        lines.append(
            f"| {name} | {run['ldr_psnr']:.2f} | {run['ldr_ssim']:.3f} | {run['ldr_exposure_fitted']} | "
            f"{run['steps']} | {run['train_seconds']:.0f} |"
        )
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
