"""Reading a JSON scene file: the value ``json.loads`` gives, fast for scenes of many instances.

A scene of 100 000 instances placed by matrices holds 1.6 million numbers, and ``json.loads``
spends most of its time making a Python float of each. Here simdjson parses the document; a
plain instance entry (at most an ``id``, a ``model`` and a ``material``, all strings, and one
``to_world`` matrix of 4 rows of 4 numbers) is read key by key, its matrix handed over as
float64 values without Python floats (the entries' matrices are rows of one array); every
other value is converted as ``json.loads`` converts it. A document simdjson refuses (malformed,
or JSON only to Python's reader: ``NaN``, integers beyond 64 bits) is read by ``json.loads``,
so that values and errors (with line and column) are exactly its. A UTF-8 byte order mark
(which some editors write) is skipped. An object that gives a key twice is refused
(:class:`DuplicateKeyError`; ``json.loads`` would keep the last value silently).
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np
import simdjson

_BYTE_ORDER_MARK = b"\xef\xbb\xbf"
#: A 4x4 matrix's minified JSON with its numbers' characters deleted.
_SKELETON = b"[[,,,],[,,,],[,,,],[,,,]]"
_NUMBER_CHARACTERS = b"0123456789.eE+-"
#: The keys of a plain entry besides ``to_world``; their values are strings.
_NAMES = ("id", "model", "material")


class DuplicateKeyError(ValueError):
    """A JSON object that gives one key twice: ``key``, and the object's ``keys`` in order."""

    def __init__(self, key: str, keys: list[str]):
        super().__init__(key, keys)
        self.key, self.keys = key, keys


def _object(pairs: list[tuple[str, Any]]) -> dict:
    """A JSON object's dict, refusing a repeated key (``json.loads``' object hook)."""
    data = dict(pairs)
    if len(data) != len(pairs):
        keys = [key for key, _ in pairs]
        raise DuplicateKeyError(next(key for k, key in enumerate(keys) if key in keys[:k]), keys)
    return data


def _loads(text: str | bytes) -> Any:
    """``json.loads`` with repeated keys refused."""
    return json.loads(text, object_pairs_hook=_object)


def read_scene_json(path: Path) -> Any:
    """The JSON document in ``path``: ``json.loads``' value of its text (without a byte order
    mark), except that plain instance entries' ``to_world`` matrices are (4, 4) float64 arrays.

    Raises:
        json.JSONDecodeError: malformed JSON.
        DuplicateKeyError: an object gives a key twice.
        UnicodeDecodeError: not UTF-8 text.
    """
    text = path.read_bytes().removeprefix(_BYTE_ORDER_MARK)
    if text.startswith(_BYTE_ORDER_MARK):  # (simdjson would skip a second one)
        return _loads(text.decode("utf-8"))
    parser = simdjson.Parser()
    try:
        document = parser.parse(text)
    except (ValueError, RuntimeError):  # (UnicodeDecodeError included; RuntimeError: big integers)
        return _loads(text.decode("utf-8"))
    if type(document) is not simdjson.Object:
        return _python(document)
    keys = list(document.keys())
    if any("\0" in key for key in keys):
        # (simdjson looks keys up as C strings: one holding a NUL character is not found.)
        return _loads(text.decode("utf-8"))
    instances = document.get("instances")
    matrices_ok = True
    data = {}
    for key in keys:
        if key == "instances" and type(instances) is simdjson.Array:
            data[key], matrices_ok = _instances(instances)
        else:
            data[key] = _python(document[key])
    if len(set(keys)) != len(keys) or not matrices_ok:
        # Repeated keys (refused there, with the key named) or a matrix that is not 4 rows of
        # 4 numbers.
        return _loads(text.decode("utf-8"))
    return data


def _python(value: Any) -> Any:
    """A simdjson value as ``json.loads`` gives it."""
    if type(value) is simdjson.Object or type(value) is simdjson.Array:
        return _loads(value.mini)
    return value


def _instances(array: simdjson.Array) -> tuple[list, bool]:
    """The instance entries, and whether every matrix read as plain is 4 rows of 4 numbers."""
    entries, plain, buffers, shapes = [], [], [], []
    for item in array:
        # (Looking up a key an object lacks costs simdjson an exception: only present
        # keys are read.)
        matrix = item.get("to_world") if type(item) is simdjson.Object else None
        entry = None
        if type(matrix) is simdjson.Array and len(matrix) == 4:
            count = len(item)
            entry = {}
            for key in ("model",) if count == 2 else item.keys():
                value = item.get(key)
                if key != "to_world":
                    if key not in _NAMES or type(value) is not str:
                        entry = None
                        break
                    entry[key] = value
            try:
                if entry is not None and len(entry) + 1 == count:
                    buffers.append(matrix.as_buffer(of_type="d"))
                    shapes.append(matrix.mini)
                    plain.append(len(entries))
                else:
                    entry = None
            except TypeError:  # a value that is not a number
                entry = None
        entries.append(_python(item) if entry is None else entry)
    if not plain:
        return entries, True
    # Numbers only (as_buffer) and the brackets and commas of 4 rows of 4: 16 numbers each.
    if b"".join(shapes).translate(None, _NUMBER_CHARACTERS) != _SKELETON * len(plain):
        return entries, False
    matrices = np.frombuffer(bytearray(b"".join(buffers))).reshape(-1, 4, 4)
    for k, matrix in zip(plain, matrices):
        entries[k]["to_world"] = matrix
    return entries, True
