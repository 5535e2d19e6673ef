"""Tests of :mod:`instancing.io.scene_json`: a JSON scene file reads as ``json.loads`` reads it
(the reference; a UTF-8 byte order mark skipped), but for plain instance entries' matrices,
which are float64 arrays of the same numbers; malformed files raise ``json.loads``' own
errors."""

from __future__ import annotations

import json
import math
import tempfile
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given

from instancing.io.scene_json import DuplicateKeyError, read_scene_json

import fuzz_inputs as fuzz

ROOT = Path(__file__).resolve().parent.parent
#: A UTF-8 byte order mark: skipped.
BOM = b"\xef\xbb\xbf"


def same(ours, reference, path="") -> None:
    """``ours`` is ``reference`` (values and types; NaN equal to NaN), but that an instance
    entry's ``to_world`` may be a (4, 4) float64 array of the reference's numbers."""
    if isinstance(ours, np.ndarray):
        assert path.endswith("to_world") and "/instances/" in path, path
        assert ours.shape == (4, 4) and ours.dtype == np.float64, path
        numbers = np.array(reference, dtype=object)
        assert numbers.shape == (4, 4), path
        assert all(type(v) in (int, float) for v in numbers.ravel()), path
        np.testing.assert_array_equal(ours, numbers.astype(np.float64), err_msg=path)
        return
    assert type(ours) is type(reference), (path, ours, reference)
    if isinstance(ours, dict):
        assert list(ours) == list(reference) or set(ours) == set(reference), path
        for key in reference:
            same(ours[key], reference[key], f"{path}/{key}")
    elif isinstance(ours, list):
        assert len(ours) == len(reference), path
        for k, (a, b) in enumerate(zip(ours, reference)):
            same(a, b, f"{path}/{k}")
    elif isinstance(ours, float) and math.isnan(reference):
        assert math.isnan(ours), path
    else:
        assert ours == reference, path


def _refusing_repeats(pairs: list) -> dict:
    """A JSON object's dict; the first key given a second time raises DuplicateKeyError."""
    seen: dict = {}
    for key, value in pairs:
        if key in seen:
            raise DuplicateKeyError(key, [k for k, _ in pairs])
        seen[key] = value
    return seen


def read_both(text: str | bytes):
    """(ours, json.loads') values of a file holding ``text`` (json.loads refusing an object's
    repeated key, as ours does), or their exceptions."""
    with tempfile.TemporaryDirectory() as folder:
        path = Path(folder) / "scene.json"
        path.write_bytes(text.encode() if isinstance(text, str) else text)
        results = []
        for read in (read_scene_json, lambda p: json.loads(p.read_bytes().removeprefix(BOM).decode(),
                                                            object_pairs_hook=_refusing_repeats)):
            try:
                results.append(read(path))
            except ValueError as err:  # JSONDecodeError, DuplicateKeyError and UnicodeDecodeError
                results.append(err)
        return results


def check(text: str | bytes):
    ours, reference = read_both(text)
    if isinstance(reference, Exception):
        assert type(ours) is type(reference) and str(ours) == str(reference)
    else:
        assert not isinstance(ours, Exception), ours
        same(ours, reference)
    return ours


@pytest.mark.parametrize("path", sorted(p.relative_to(ROOT) for folder in ("scenes", "tests", "examples")
                                        for p in (ROOT / folder).rglob("*.json")), ids=str)
def test_bundled_scenes_read_as_json_loads_reads_them(path):
    check((ROOT / path).read_bytes())


def test_plain_entries_matrices_are_arrays_of_their_numbers():
    rng = np.random.default_rng(3)
    matrices = rng.normal(size=(50, 4, 4))
    matrices[:, 3] = [0, 0, 0, 1]
    matrices[7] = np.eye(4)  # integers in the file: 1 and 0
    entries = [{"model": "sphere", "to_world": m.tolist()} for m in matrices]
    entries[7]["to_world"] = np.eye(4, dtype=int).tolist()
    entries[8].update(id="named", material="red")
    ours = check(json.dumps({"models": {}, "instances": entries}))
    assert all(isinstance(e["to_world"], np.ndarray) for e in ours["instances"])
    np.testing.assert_array_equal([e["to_world"] for e in ours["instances"]], matrices)


ROW = [1.5, 0, 2, 3]
HOSTILE_MATRICES = [
    [ROW, [1, [2], 3, 4], ROW, ROW],          # a nested array with one number
    [ROW, [1, [], 3, 4], [1, [2, 5], 3, 4], ROW],  # nested arrays making up 16 numbers
    [ROW, ROW + [1], ROW[:3], ROW],           # ragged rows, 16 numbers
    [ROW, ROW, ROW],                          # 3 rows
    [ROW, ROW, ROW, ROW, ROW],
    [ROW * 2, ROW * 2],                       # 16 numbers in 2 rows
    [ROW, ROW, ROW, [0, 0, 0, "1"]],
    [ROW, ROW, ROW, [0, 0, 0, True]],
    [ROW, ROW, ROW, [0, 0, None, 1]],
    [ROW, ROW, ROW, 7],
    [[], [], [], []],
    [1, 2, 3, 4],
]


@pytest.mark.parametrize("matrix", HOSTILE_MATRICES, ids=range(len(HOSTILE_MATRICES)))
def test_a_matrix_that_is_not_4_rows_of_4_numbers_reads_as_written(matrix):
    plain = {"model": "sphere", "to_world": np.eye(4).tolist()}
    check(json.dumps({"instances": [plain, {"model": "sphere", "to_world": matrix}, plain]}))


@pytest.mark.parametrize("text", [
    # only Python's reader takes these: the whole file is its
    '{"instances": [{"model": "sphere", "to_world": [[NaN, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]}]}',
    '{"instances": [{"model": "sphere", "to_world": [[1e400, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]}]}',
    '{"instances": [{"model": "sphere", "to_world": [[100000000000000000000000, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]}]}',
    # repeated keys: refused, naming the key (json.loads would keep the last one)
    '{"instances": [{"model": "a", "model": "b", "to_world": [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]}]}',
    '{"instances": [{"model": "a", "to_world": [[2, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]], "to_world": 5}]}',
    '{"instances": [], "instances": [{"model": "b"}]}',
    # entries that are not plain: other keys, ids that are not strings, null values
    '{"instances": [{"id": 5, "model": "a", "to_world": [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]}]}',
    '{"instances": [{"model": null, "to_world": [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]}]}',
    '{"instances": [{"model": "a", "emitter": {"type": "area", "radiance": 1}, "to_world": [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]}]}',
    '{"instances": [{"to_world": [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]}, 3, "x", null, []]}',
    '{"instances": [{"model": "a\\u0000[[1,2,3,4],[1,2,3,4],[1,2,3,4],[1,2,3,4]]", "to_world": [[-0.0, 1e-320, 2.5e-3, -1E+2], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]}]}',
    # keys holding a NUL character (simdjson looks keys up as C strings)
    '{"instances": [{"model": "sphere"}], "\\u0000": null}',
    '{"instances": [{"model": "a", "\\u0000x": 1, "to_world": [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]}]}',
    '{"instances": [], "camera": {"\\u0000": 1}}',
    '{"instances": {"model": "a"}}', '[1, 2]', '"text"', '{}',
    # malformed: json.loads' errors, with line and column
    '{"instances": [{"model": "a",}]}', '{"instances": [', '', '\ufeff{"instances": []}',
    '\ufeff\ufeff{"instances": []}', '{"instances": []}\ufeff',
    b'{"instances": [{"model": "\xff"}]}',
])
def test_unusual_files_read_or_fail_as_json_loads_does(text):
    check(text)


@fuzz.ci_settings(200)
@given(fuzz.mutated_json())
def test_fuzzed_files_read_or_fail_as_json_loads_does(text):
    """Mutated scene files (tests/fuzz_inputs.py) read as json.loads reads them, and load or
    raise a documented error."""
    check(text)
    fuzz.load_scene_text(text, ".json")


@pytest.mark.parametrize("text, key", [
    ('{"instances": [{"model": "a", "model": "b", "to_world": [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], '
     '[0, 0, 0, 1]]}]}', "model"),
    ('{"instances": [], "camera": {"type": "perspective"}, "instances": [{"model": "sphere"}]}', "instances"),
    ('{"instances": [{"model": "sphere"}], "camera": {"type": "perspective", "fov": 30, "fov": 60}}', "fov")])
def test_a_key_given_twice_is_refused_naming_it(tmp_path, text, key):
    """A JSON object that gives a key twice (at the top, in a plain instance entry, in the
    camera) is refused by name: json.loads alone would keep the last value silently."""
    import instancing
    path = tmp_path / "scene.json"
    path.write_text(text)
    with pytest.raises(DuplicateKeyError) as caught:
        read_scene_json(path)
    assert caught.value.key == key
    with pytest.raises(instancing.SceneError, match=f"scene.json: the key '{key}' is given twice in one object"):
        instancing.load_scene(path)
