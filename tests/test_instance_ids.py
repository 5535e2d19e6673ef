"""``InstanceIds``: behaves like the list of id strings it stands for (the reference), rejects
every name two entries would share, and stores a batch without a string per instance."""

from __future__ import annotations

import re
import sys

import numpy as np
import pytest

import instancing
from instancing.core.errors import SceneError
from instancing.scene.instance_ids import InstanceIds

ENTRIES = [("solo", None), ("tree", 4), ("a[7]", None), ("a", 3), ("3", None), ("x[1]", 2)]


def _both(entries):
    """The ids and the plain list they stand for; a name None adds ``count`` instances
    without ids (named by their indices)."""
    ids, names = InstanceIds(), []
    for name, count in entries:
        if name is None:
            ids.add_unnamed(count)
            names += [str(k) for k in range(len(names), len(names) + count)]
            continue
        ids.add(name, count)
        names += [name] if count is None else [f"{name}[{k}]" for k in range(count)]
    return ids, names


def test_reads_like_the_list_of_names():
    ids, names = _both(ENTRIES)
    assert len(ids) == len(names) and list(ids) == names and ids == names and names == ids
    assert [ids[i] for i in range(-len(names), len(names))] == names + names
    assert ids[2:9:3] == names[2:9:3]
    for i, name in enumerate(names):
        assert ids.index(name) == i and name in ids
    for absent in ("tree[4]", "tree[01]", "a[3]", "x[1][2]", "solo[0]", "tre", 7):
        assert absent not in ids
        with pytest.raises(ValueError):
            ids.index(absent)
    with pytest.raises(IndexError):
        ids[len(names)]
    assert ids != names[:-1] and ids != ["solo"] * len(names)


@pytest.mark.parametrize("entries, taken", [
    ([("a", None), ("a", None)], "a"),
    ([("a", 3), ("a[2]", None)], "a[2]"),      # a single id inside an earlier batch
    ([("a[2]", None), ("a", 3)], "a[2]"),      # a batch covering an earlier single id
    ([("a", 2), ("a", 5)], "a[0]"),            # two batches with one prefix
])
def test_a_shared_name_is_rejected(entries, taken):
    ids = InstanceIds()
    with pytest.raises(SceneError, match=re.escape(f"{taken!r} is used twice")):
        for name, count in entries:
            ids.add(name, count)


def test_instances_without_ids_read_like_their_indices():
    entries = [(None, 3), ("solo", None), (None, 2), (None, 4), ("20", None), ("b", 2), (None, 1)]
    ids, names = _both(entries)
    assert list(ids) == names and ids == names and len(ids) == len(names)
    assert [ids[i] for i in range(len(names))] == names
    for i, name in enumerate(names):
        assert ids.index(name) == i and name in ids
    for absent in ("3", "016", "+4", "-1", "17", "b"):  # '3' is "solo"; past the end: 17
        assert absent not in ids
    assert ids.batches() == [("b", 11, 2)]
    assert "0..2" in repr(ids)


@pytest.mark.parametrize("entries, taken", [
    ([("1", None), (None, 3)], "1"),            # a run covering an earlier single id
    ([(None, 3), ("2", None)], "2"),            # a single id inside an earlier run
])
def test_an_index_name_is_taken_by_a_run(entries, taken):
    ids = InstanceIds()
    with pytest.raises(SceneError, match=re.escape(f"{taken!r} is used twice")):
        for name, count in entries:
            ids.add_unnamed(count) if name is None else ids.add(name, count)


def test_a_million_instances_without_ids_cost_no_string_each():
    ids = InstanceIds()
    for _ in range(1000):
        ids.add_unnamed(1000)
    held = sum(sys.getsizeof(v) for v in vars(ids).values())
    assert held < 2000
    assert ids[654_321] == "654321" and ids.index("999999") == 999_999


def test_names_a_batch_cannot_make_are_free():
    ids, names = _both([("a", 3), ("a[3]", None), ("a[01]", None), ("a[x]", None), ("a[]", None)])
    assert list(ids) == names


def test_a_million_instance_batch_costs_no_string_per_instance():
    ids = InstanceIds()
    ids.add("forest", 1_000_000)
    held = sum(sys.getsizeof(v) for v in vars(ids).values())
    assert held < 2000
    assert ids[999_999] == "forest[999999]" and ids.index("forest[123456]") == 123456


def test_scene_loaded_from_a_batch_keeps_ids_and_float32_transforms():
    """A built scene's transforms are the float32 roundings of the input; the description
    reads them back (float64 values of the stored float32 matrices)."""
    rng = np.random.default_rng(4)
    batch = np.tile(np.eye(4), (5, 1, 1))
    batch[:, :3, :3] *= rng.uniform(0.5, 2.0, (5, 1, 1))
    batch[:, :3, 3] = rng.uniform(-3, 3, (5, 3))
    scene = instancing.load_scene({"instances": [{"id": "b", "model": "sphere", "to_world": batch}]})
    assert scene.instance_ids == [f"b[{k}]" for k in range(5)]
    np.testing.assert_array_equal(scene.to_world, batch.astype(np.float32))
    np.testing.assert_allclose(scene.from_world, np.linalg.inv(batch), rtol=0, atol=1e-6)
