"""Fuzzing the dataset loaders (hypothesis): transforms and exposure JSON of the HDR-NeRF synthetic
layout, exposures.json and the COLMAP text model of the HDR-GS layout, bent into wrong types, NaN,
Inf, empty values, huge numbers, unicode and broken text. Whatever the files hold, loading either
gives a scene or raises the project's DatasetError (which names the file): never another
exception. The default suite runs a bounded, fixed set of examples; `-m slow` many random ones."""

import copy
import json
import math
import warnings
from pathlib import Path

import pytest
from hard_scenes import write_disk_scene
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from mono_hdr_plugin.data.config import DataConfig
from mono_hdr_plugin.data.dataset import SceneData
from mono_hdr_plugin.data.errors import DatasetError
from mono_hdr_plugin.data.loading import load_scene

RUNS = [pytest.param(40, True, id="bounded"), pytest.param(400, False, id="long", marks=pytest.mark.slow)]

# Values that have broken loaders: types JSON allows, numbers at and past the float range, text that
# is a number to some parsers, unicode digits, surrogates, NUL, very long names.
AWKWARD = [
    None,
    True,
    False,
    0,
    -1,
    1,
    2**31,
    10**30,
    10**400,
    0.0,
    -0.0,
    1e-320,
    1e308,
    math.nan,
    math.inf,
    -math.inf,
    "",
    " ",
    "0.5",
    "nan",
    "inf",
    "1e999",
    "٣",
    "²",
    "\ud800",
    "a\x00b",
    "../../etc/passwd",
    "x" * 300,
    "☃.png",
    [],
    {},
    [1, 2, 3],
    [[0] * 4] * 4,
    {"frames": []},
]
# deep copies: a mutation must not change AWKWARD's lists and dicts for later examples (hypothesis
# then sees different data for the same choices and reports a flaky strategy)
scalars = (
    st.sampled_from(AWKWARD).map(copy.deepcopy)
    | st.none()
    | st.booleans()
    | st.integers()
    | st.floats(allow_nan=True, allow_infinity=True)
    | st.text(max_size=12)
)
json_values = st.recursive(
    scalars,
    lambda inner: st.lists(inner, max_size=4) | st.dictionaries(st.text(max_size=8), inner, max_size=4),
    max_leaves=12,
)
tokens = (
    st.sampled_from(
        [
            "nan",
            "inf",
            "-inf",
            "-1",
            "0",
            "1e999",
            "1e-999",
            "9" * 30,
            "",
            "☃",
            "1.5",
            "0x10",
            "PINHOLE",
            "SIMPLE_RADIAL",
            "#",
            "\t",
            "000_0.png",
        ]
    )
    | st.text(max_size=6)
    | st.integers().map(str)
    | st.floats().map(repr)
)


def fuzz_settings(examples: int, fixed: bool):
    return settings(
        max_examples=examples,
        deadline=None,
        derandomize=fixed,
        database=None,
        suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large],
    )


def loads_or_refuses(folder: Path) -> None:
    """The property: a SceneData, or a DatasetError; anything else fails the test."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        try:
            scene = load_scene(DataConfig(data=folder))
        except DatasetError:
            return
    assert isinstance(scene, SceneData)


class Dataset:
    """A dataset folder on disk and its pristine files, restored before every example."""

    def __init__(self, folder: Path, files: list[str]):
        self.folder = folder
        self.pristine = {name: (folder / name).read_bytes() for name in files}

    def restore(self) -> None:
        for name, content in self.pristine.items():
            (self.folder / name).write_bytes(content)

    def text(self, name: str) -> str:
        return self.pristine[name].decode()


@pytest.fixture(scope="module")
def synthetic(tmp_path_factory):
    folder = tmp_path_factory.mktemp("fuzz") / "synthetic"
    write_disk_scene(folder, size=8, views=4)
    return Dataset(
        folder, ["transforms_train.json", "transforms_test.json", "exposure_train.json", "exposure_test.json"]
    )


@pytest.fixture(scope="module")
def colmap(tmp_path_factory):
    folder = tmp_path_factory.mktemp("fuzz") / "colmap"
    write_disk_scene(folder, size=8, views=4, layout="hdr-gs")
    import pycolmap  # after PIL has written the images

    model = folder / "sparse" / "0"
    reconstruction = pycolmap.Reconstruction(str(model))
    for index, xyz in enumerate([(0.1, 0.2, 0.3), (-0.2, 0.1, 0.0)]):
        reconstruction.add_point3D(xyz, pycolmap.Track(), [200, 100, 50 + index])
    reconstruction.write_text(str(model))
    for binary in model.glob("*.bin"):
        binary.unlink()
    return Dataset(folder, ["sparse/0/cameras.txt", "sparse/0/images.txt", "sparse/0/points3D.txt", "exposures.json"])


def paths_of(document, prefix=()):
    """Every path (tuple of keys/indices) into a JSON document, deepest first (hypothesis prefers the
    first choices: the whole document, path (), comes last)."""
    if isinstance(document, dict):
        for key, value in document.items():
            yield from paths_of(value, (*prefix, key))
    elif isinstance(document, list):
        for index, value in enumerate(document):
            yield from paths_of(value, (*prefix, index))
    yield prefix


def mutate_json(data, document):
    """Replace, delete or insert at a random place of the document, 1 to 3 times."""
    for _ in range(data.draw(st.integers(1, 3))):
        path = data.draw(st.sampled_from(list(paths_of(document))))
        if not path:
            document = data.draw(json_values)
            continue
        *parents, last = path
        container = document
        for key in parents:
            container = container[key]
        operation = data.draw(st.sampled_from(["replace", "replace", "delete", "insert"]))
        if operation == "replace":
            container[last] = data.draw(json_values)
        elif operation == "delete":
            del container[last]
        elif isinstance(container, dict):
            container[data.draw(st.text(max_size=12))] = data.draw(json_values)
        else:
            container.insert(last, data.draw(json_values))
    return document


def encode(data, document) -> bytes:
    text = json.dumps(document, allow_nan=True)
    if data.draw(st.sampled_from([False] * 9 + [True])):  # now and then, cut the file or break its bytes
        cut = data.draw(st.integers(0, len(text)))
        return text[:cut].encode("utf-8", "surrogatepass") + data.draw(st.binary(max_size=4))
    return text.encode("utf-8", "surrogatepass")


def mutate_text_model(data, text: str) -> str:
    lines = text.splitlines()
    for _ in range(data.draw(st.integers(1, 3))):
        if not lines:
            lines.append(" ".join(data.draw(st.lists(tokens, max_size=12))))
            continue
        index = data.draw(st.integers(0, len(lines) - 1))
        operation = data.draw(
            st.sampled_from(
                [
                    "token",
                    "token",
                    "token",
                    "drop token",
                    "add token",
                    "drop line",
                    "duplicate line",
                    "random line",
                    "truncate",
                ]
            )
        )
        parts = lines[index].split(" ")
        if operation == "token":
            parts[data.draw(st.integers(0, len(parts) - 1))] = data.draw(tokens)
        elif operation == "drop token":
            del parts[data.draw(st.integers(0, len(parts) - 1))]
        elif operation == "add token":
            parts.insert(data.draw(st.integers(0, len(parts))), data.draw(tokens))
        elif operation == "drop line":
            del lines[index]
            continue
        elif operation == "duplicate line":
            lines.insert(index, lines[index])
            continue
        elif operation == "random line":
            lines.insert(index, " ".join(data.draw(st.lists(tokens, max_size=12))))
            continue
        else:
            lines = lines[:index]
            continue
        lines[index] = " ".join(parts)
    return "\n".join(lines) + "\n"


@pytest.mark.parametrize("examples,fixed", RUNS)
def test_synthetic_layout_json(synthetic, examples, fixed):
    names = list(synthetic.pristine)

    @fuzz_settings(examples, fixed)
    @given(st.data())
    def check(data):
        synthetic.restore()
        for name in data.draw(st.lists(st.sampled_from(names), min_size=1, max_size=2, unique=True)):
            document = mutate_json(data, json.loads(synthetic.text(name)))
            (synthetic.folder / name).write_bytes(encode(data, document))
        loads_or_refuses(synthetic.folder)

    try:
        check()
    finally:
        synthetic.restore()


@pytest.mark.parametrize("examples,fixed", RUNS)
def test_colmap_text_model_and_exposures(colmap, examples, fixed):
    @fuzz_settings(examples, fixed)
    @given(st.data())
    def check(data):
        colmap.restore()
        for name in data.draw(st.lists(st.sampled_from(list(colmap.pristine)), min_size=1, max_size=2, unique=True)):
            if name.endswith(".json"):
                content = encode(data, mutate_json(data, json.loads(colmap.text(name))))
            else:
                content = mutate_text_model(data, colmap.text(name)).encode("utf-8", "surrogatepass")
            (colmap.folder / name).write_bytes(content)
        loads_or_refuses(colmap.folder)

    try:
        check()
    finally:
        colmap.restore()


def test_the_pristine_datasets_load(synthetic, colmap):
    """The property is not met vacuously: unmutated, both folders load."""
    for dataset in (synthetic, colmap):
        dataset.restore()
        assert len(load_scene(DataConfig(data=dataset.folder)).train) == 2
