"""Every numeric flag of every built-in config is checked before any work is done, by one mechanism
(`validation.check_flags` over each dataclass's `flag_rules` table): NaN and Inf are refused
everywhere, rates, sizes and exposures must be positive, weights non-negative. These tests walk the
configs themselves, so a new flag without a rule, or a rule for a flag that is gone, fails here."""

import dataclasses
import math
import re
import typing

import pytest
import register_backbone

from backbones.gs.benchmark import BenchRasterConfig
from mono_hdr_plugin.apps.bench.curves import BenchCurvesConfig
from mono_hdr_plugin.apps.bench.paper import BenchPaperConfig
from mono_hdr_plugin.apps.cli import EvalConfig, main
from mono_hdr_plugin.apps.export import ExportConfig
from mono_hdr_plugin.apps.render import RenderConfig
from mono_hdr_plugin.apps.studio.commands import SynthConfig
from mono_hdr_plugin.apps.viewer.command import ViewConfig
from mono_hdr_plugin.core.registry import BACKBONES
from mono_hdr_plugin.core.validation import FlagError, check_flags, rules_of
from mono_hdr_plugin.training.config import check_train_config, train_config_for

BUILT_IN = ("gs", "nerf", "voxel-grid")
TRAIN_CONFIGS = (*BUILT_IN, "hdr-nerf")


def default_configs() -> dict[str, object]:
    configs = {
        name: train_config_for(BACKBONES.get(name).config_class)(backbone=BACKBONES.get(name).config_class())
        for name in BUILT_IN
    }
    configs["hdr-nerf"] = train_config_for(register_backbone.VoxelGridConfig, "hdr-nerf")()  # a method's own flags
    configs.update(
        eval=EvalConfig(checkpoint="x.pt"),
        render=RenderConfig(checkpoint="x.pt"),
        synth=SynthConfig(),
        view=ViewConfig(checkpoint="x.pt"),
        export=ExportConfig(checkpoint="x.pt"),
        bench_curves=BenchCurvesConfig(),
        bench_paper=BenchPaperConfig(),
        bench_raster=BenchRasterConfig(),
    )
    return configs


def integer_type(annotation) -> bool:
    return annotation is int or int in typing.get_args(annotation)


def numeric_type(annotation) -> bool:
    """int or float, possibly Optional or a tuple of them (bool is not numeric)."""
    if annotation in (int, float):
        return True
    arguments = [a for a in typing.get_args(annotation) if a is not type(None) and a is not Ellipsis]
    return bool(arguments) and all(numeric_type(a) for a in arguments)


def leaves(config, path=()):
    """(path, field, owning dataclass) of every field, walking nested configs independently of
    validation.iter_flags."""
    hints = typing.get_type_hints(type(config))
    for field in dataclasses.fields(config):
        value = getattr(config, field.name)
        if dataclasses.is_dataclass(value):
            yield from leaves(value, (*path, field.name))
        else:
            yield (*path, field.name), hints[field.name], config


def numeric_leaves():
    for name, config in default_configs().items():
        for path, annotation, _owner in leaves(config):
            if numeric_type(annotation):
                yield pytest.param(name, path, integer_type(annotation), id=f"{name}:{'.'.join(path)}")


def owner_of(config, path):
    """The (nested) dataclass holding the field at `path`."""
    for part in path[:-1]:
        config = getattr(config, part)
    return config


def check(name, config):
    return check_train_config(config) if name in TRAIN_CONFIGS else check_flags(config)


@pytest.mark.parametrize("name,path,integer", list(numeric_leaves()))
def test_every_numeric_flag_has_a_rule_and_refuses_nan_and_out_of_range(name, path, integer):
    configs = default_configs()
    config = configs[name]
    owner = type(owner_of(config, path))
    rule = rules_of(owner).get(path[-1])
    assert rule is not None, f"{owner.__name__}.{path[-1]} has no entry in flag_rules"
    check(name, config)  # the defaults pass
    default = getattr(owner_of(config, path), path[-1])
    bad_values = [] if integer else [math.nan, math.inf]
    if rule.low is not None:
        bad_values.append(rule.low if rule.low_open else rule.low - 1)
    if rule.high is not None:
        bad_values.append(rule.high if rule.high_open else rule.high + 1)
    flag_name = path[-1].replace("_", "-")
    for bad in bad_values:
        config = default_configs()[name]
        bad = int(bad) if integer else float(bad)
        owner_object = owner_of(config, path)  # object.__setattr__: some configs are frozen (ExecutorConfig)
        object.__setattr__(
            owner_object, path[-1], tuple([bad] * max(1, len(default))) if isinstance(default, tuple) else bad
        )
        with pytest.raises(FlagError, match=rf"^--(\S+\.)?{flag_name} must be .*, got {re.escape(str(bad))}"):
            check(name, config)


def test_no_rule_names_a_field_that_is_not_there():
    classes = set()
    for config in default_configs().values():
        stack = [config]
        while stack:
            current = stack.pop()
            classes.add(type(current))
            stack += [
                getattr(current, f.name)
                for f in dataclasses.fields(current)
                if dataclasses.is_dataclass(getattr(current, f.name))
            ]
    for cls in classes:
        names = {f.name for f in dataclasses.fields(cls)}
        assert set(rules_of(cls)) <= names, f"{cls.__name__}: rules for {set(rules_of(cls)) - names}"


@pytest.mark.parametrize(
    "argv,message",
    [
        (["train", "voxel-grid", "--backbone.lr", "nan"], "--backbone.lr must be a positive number, got nan"),
        (["train", "gs", "--backbone.lr-means", "inf"], "--backbone.lr-means must be a positive number, got inf"),
        (
            ["train", "nerf", "--backbone.field.grid-lr", "0"],
            r"--backbone.field.grid-lr must be a positive number, got 0.0",
        ),
        (["train", "voxel-grid", "--hidden", "0"], "--hidden must be an integer >= 1, got 0"),
        (["train", "voxel-grid", "--alpha", "nan"], r"--alpha must be a number in \[0, 1000000\], got nan"),
        (["train", "voxel-grid", "--beta", "-0.1"], r"--beta must be a number in \[0, 1000000\], got -0.1"),
        (["train", "voxel-grid", "--converter-lr", "-1e400"], "--converter-lr must be a positive number, got -inf"),
        (
            ["train", "voxel-grid", "--hdr-log-weight", "1e300"],
            r"--hdr-log-weight must be .*\[0, 1000000\], got 1e\+300",
        ),
        (
            ["train", "voxel-grid", "--resolution", "100000"],
            r"--resolution must be an integer in \[11, 4096\], got 100000",
        ),
        (["train", "voxel-grid", "--resolution", "10"], r"--resolution must be an integer in \[11, 4096\], got 10"),
        (["bench", "cost", "--sizes", "128", "100000"], r"--sizes must be an integer in \[16, 4096\], got 100000"),
        (
            ["train", "voxel-grid", "--method", "hdr-nerf", "--unit-exposure-value", "1"],
            r"--unit-exposure-value must be a number in \(0, 1\), got 1.0",
        ),
        (["train", "voxel-grid", "--fixed-exposure", "0"], "--fixed-exposure must be a positive number, got 0.0"),
        (["train", "voxel-grid", "--max-seconds", "nan"], "--max-seconds must be a positive number, got nan"),
        (
            ["render", "--checkpoint", "x.pt", "--exposures", "1", "nan"],
            "--exposures must be a positive number, got nan",
        ),
        (["bench", "curves", "--eval-points", "0"], "--eval-points must be an integer >= 1, got 0"),
        (["bench", "paper", "--executor", "cluster"], "--executor must be one of sequential, ray, got 'cluster'"),
        (["bench", "raster", "--repeats", "0"], "--repeats must be an integer >= 1, got 0"),
    ],
)
def test_the_command_line_refuses_before_any_work_naming_the_flag(argv, message, tmp_path, monkeypatch):
    """As the issue found them: a NaN learning rate or loss weight, `--hidden 0`; spelled as typed."""
    import mono_hdr_plugin.data.loading as loading

    monkeypatch.chdir(tmp_path)  # nothing may be written: the default --out would land here
    monkeypatch.setattr(loading, "load_scene", lambda config: pytest.fail("the data was loaded first"))
    with pytest.raises(FlagError, match=f"^{message}$"):
        main([*argv, "--scene", "demo"] if argv[0] == "train" else argv)
    assert list(tmp_path.iterdir()) == []
