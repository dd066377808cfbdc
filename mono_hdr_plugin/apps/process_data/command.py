"""`mono-hdr process-data`: the stages in order, in a scratch folder beside --out renamed into place
at the end, so a failed run never leaves a half-written dataset."""

import tempfile
from pathlib import Path

from rich.console import Console

from mono_hdr_plugin.apps.process_data.brackets import bracket_response, find_bracket_plans, mark_views
from mono_hdr_plugin.apps.process_data.config import ProcessDataConfig, check_config
from mono_hdr_plugin.apps.process_data.exposures import exposure_warnings, photo_records, read_exposure_csv
from mono_hdr_plugin.apps.process_data.layout import install, write_dataset
from mono_hdr_plugin.apps.process_data.photos import find_inputs, stage_photos
from mono_hdr_plugin.apps.process_data.report import ProcessReport, print_report
from mono_hdr_plugin.apps.process_data.sfm import (
    camera_groups,
    check_registered,
    gps_rms_metres,
    mark_registered,
    run_sfm,
)
from mono_hdr_plugin.data.io import utf8_path, write_json
from mono_hdr_plugin.data.layouts.hdr_gs import REPORT_FILE


def process_data(config: ProcessDataConfig, console: Console | None = None) -> ProcessReport:
    """Build the dataset at config.out from config.images or config.video; see the package docstring."""
    console = console or Console(quiet=True)
    check_config(config)
    csv_table = read_exposure_csv(config.exposure_csv) if config.exposure_csv else {}
    config.out.parent.mkdir(parents=True, exist_ok=True)
    with (
        tempfile.TemporaryDirectory(prefix=f".{config.out.name}.", dir=config.out.parent) as scratch,
        utf8_path(scratch) as reachable,  # COLMAP works in it: a UTF-8 path, whatever --out's folder is called
    ):
        work, dataset = reachable / "work", reachable / "dataset"
        (work / "input").mkdir(parents=True)
        report = build_dataset(config, csv_table, work, dataset, console)
        write_json(dataset / REPORT_FILE, report.to_json())
        install(dataset, config.out, config.overwrite)
    return report


def build_dataset(
    config: ProcessDataConfig, csv_table: dict[str, float], work: Path, dataset: Path, console: Console
) -> ProcessReport:
    """Photos and exposures, poses, brackets, the layout in `dataset` (scratch files in `work`); the report."""
    sources, ignored, video = find_inputs(config, work / "frames", console)
    staged, sizes = stage_photos(sources, work, config.raw_response, console)
    photos, reference = photo_records(staged, csv_table, config.exposure, config.exposure_csv)
    cameras = camera_groups(config.camera_model, staged, sizes)
    reconstruction = run_sfm(config, work / "input", cameras, work, console)
    mark_registered(photos, reconstruction.model)
    plans, bracket_notes = find_bracket_plans(config, photos, staged, reconstruction.model, console)
    merged = {photos[i].source for plan in plans for i in plan.members}
    notes = check_registered(config, photos, reconstruction, merged=merged)
    response, response_source, response_notes = bracket_response(plans, staged, config.raw_response, console)
    hdr_views = mark_views(photos, plans)
    report = write_dataset(
        config, reconstruction, photos, staged, plans, hdr_views, response, response_source, work, dataset, console
    )
    report.reference_iso, report.reference_f_number = reference["iso"], reference["f_number"]
    report.mapper, report.mapper_attempts = reconstruction.mapper, reconstruction.attempts
    report.gps_rms_m = gps_rms_metres(reconstruction.model, staged)
    report.response, report.ignored, report.video = response_source, ignored, video
    report.warnings = notes + bracket_notes + response_notes + exposure_warnings(photos, reference)
    return report


def process_data_command(config: ProcessDataConfig) -> None:
    """`mono-hdr process-data`: run it and print the report."""
    console = Console()
    print_report(process_data(config, console), console)
