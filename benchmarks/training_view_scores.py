"""Scores of a trained model on some of its own training views, beside its held-out scores: whether a
low held-out figure is the model not fitting its photos (training views low too) or not generalising
from them (training views high). Same scoring as `mono-hdr eval` (LDR PSNR / SSIM, and without HDR
views the HDR's rank correlation and log slope against the photo), appearance protocol off: a
training view's exposure and white balance are the ones training learned.

    python benchmarks/training_view_scores.py --checkpoint RUN/checkpoints/latest.pt --out FILE.json
"""

import argparse
import dataclasses
import json
from pathlib import Path

from mono_hdr_plugin.training.evaluation import evaluate
from mono_hdr_plugin.training.trained import load_trained_model

KEYS = ("ldr_psnr", "ldr_ssim", *(f"hdr_{score}_{c}" for score in ("rank_correlation", "log_slope") for c in "rgb"))


def training_view_scores(checkpoint: Path, every: int) -> dict:
    model = load_trained_model(checkpoint)
    picked = model.scene.train[::every]
    metrics = evaluate(model.pipeline, dataclasses.replace(model.scene, test=picked), eval_appearance="off")
    rows = [{"view": row["view"], **{key: row[key] for key in KEYS if key in row}} for row in metrics["views"]]
    return {"checkpoint": str(checkpoint), "steps": model.step, "views": rows}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--checkpoint", type=Path, required=True)
    parser.add_argument("--every", type=int, default=4, help="score every Nth training view")
    parser.add_argument("--out", type=Path, required=True)
    args = parser.parse_args()
    result = training_view_scores(args.checkpoint, args.every)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(result, indent=2) + "\n")
    for row in result["views"]:
        print(row["view"], *(f"{key} {row[key]:.3f}" for key in KEYS if key in row))


if __name__ == "__main__":
    main()
