"""Recorded kernel launches (instancing/core/kernel_recording.py): one recording per key,
replayed with new array values, the least recently used dropped, pinned arguments, failed
recordings run plainly, an owner's tables dropped with its revision."""

import gc
import types
import weakref

import pytest

from instancing.core.backend import Float, UInt32, dr
from instancing.core.kernel_recording import (MAX_PENDING, MAX_RECORDINGS, RecordingTable, Recordings,
                                              call_recorded, jit_state, recordings_of)


def _scaled(x, factor):
    return x * factor.value


def _no_state(*args):
    return []


class _Owner:
    """An object with a revision and its recordings, as a scene."""
    revision = 0

    def __init__(self):
        self.recordings = Recordings()


def test_a_key_is_recorded_once_and_replayed_with_the_new_values():
    table = RecordingTable()
    factor = types.SimpleNamespace(value=2.0)
    for start in (1.0, 5.0, -3.0):
        x = Float(start, start + 1.0)
        result = call_recorded(table, "k", _scaled, (x, factor), _no_state)
        assert dr.all(result == Float(2 * start, 2 * start + 2.0))
    frozen, _ = table.entries["k"]
    assert frozen.n_recordings == 1


def test_a_key_recorded_at_its_second_call_is_traced_before():
    table = RecordingTable()
    factor = types.SimpleNamespace(value=2.0)
    results = [call_recorded(table, key, _scaled, (Float(1.0, 2.0), factor), _no_state, record_at=2)
               for key in ("a", "b", "a", "a")]
    assert all(dr.all(r == Float(2.0, 4.0)) for r in results)
    assert list(table.entries) == ["a"] and table.entries["a"][0].n_recordings == 1
    assert table.calls == {"b": 1}
    for key in range(MAX_PENDING + 5):  # keys met once each: their counts stay bounded
        call_recorded(table, key, _scaled, (Float(1.0, 2.0), factor), _no_state, record_at=2)
    assert len(table.calls) == MAX_PENDING and list(table.entries) == ["a"]


def test_the_least_recently_used_recording_goes_beyond_the_limit():
    table = RecordingTable()
    factor = types.SimpleNamespace(value=1.0)
    for key in range(MAX_RECORDINGS):
        call_recorded(table, key, _scaled, (Float(1.0), factor), _no_state)
    call_recorded(table, 0, _scaled, (Float(1.0), factor), _no_state)  # 0 used again
    call_recorded(table, "new", _scaled, (Float(1.0), factor), _no_state)
    assert len(table.entries) == MAX_RECORDINGS
    assert 1 not in table.entries and 0 in table.entries and "new" in table.entries


def test_a_pinned_argument_is_the_recording_calls_own():
    """A frozen function compares non-array arguments by identity; a pinned one (which the
    key determines) is passed from the recording call, so a new but equal object replays."""
    table = RecordingTable()
    first, second = types.SimpleNamespace(value=3.0), types.SimpleNamespace(value=3.0)
    call_recorded(table, "k", _scaled, (Float(1.0, 2.0), first), _no_state, pinned=(1,))
    result = call_recorded(table, "k", _scaled, (Float(2.0, 4.0), second), _no_state, pinned=(1,))
    assert dr.all(result == Float(6.0, 12.0))
    frozen, pinned = table.entries["k"]
    assert frozen.n_recordings == 1 and pinned[1] is first


def test_a_failed_recording_restores_and_runs_plainly_from_then_on():
    # An array made before the recording and gathered from without being an input (no
    # state_fn lists it): Dr.Jit refuses to record the call.
    hidden = Float(1.0, 2.0)
    dr.eval(hidden)

    def reads_hidden(x, factor):
        return x + dr.gather(Float, hidden, UInt32(0, 1))

    table, failures = RecordingTable(), []
    for _ in range(2):
        result = call_recorded(table, "k", reads_hidden, (Float(1.0, 1.0), None), _no_state,
                               on_failure=lambda: failures.append(1))
        assert dr.all(result == Float(2.0, 3.0))
    assert table.entries["k"] == (None, {}) and failures == [1]


def test_an_interrupt_while_recording_is_raised_not_counted_as_a_failure():
    def interrupted(*args):
        raise KeyboardInterrupt

    table = RecordingTable()
    with pytest.raises(KeyboardInterrupt):
        call_recorded(table, "k", _scaled, (Float(1.0), None), interrupted)


def test_an_owners_tables_go_with_its_revision_and_purposes_are_separate():
    owner = _Owner()
    table = recordings_of(owner, "a")
    assert recordings_of(owner, "a") is table and recordings_of(owner, "b") is not table
    owner.revision += 1
    assert recordings_of(owner, "a") is not table


def test_the_recordings_do_not_keep_their_owner_alive():
    """A frozen function keeps the arguments of its calls, the owner among them: held by
    the owner, the recordings form a cycle that the collector frees (a weak dictionary keyed
    by the owner kept every rendered scene alive)."""
    owner = _Owner()
    owner.value = 2.0
    call_recorded(recordings_of(owner, "a"), "k", _scaled, (Float(1.0, 2.0), owner), _no_state)
    alive = weakref.ref(owner)
    del owner
    gc.collect()
    assert alive() is None


def test_the_state_walk_leaves_the_recordings_out():
    """The arrays of a pinned argument stay out of the owner's state (which would change
    with every recording added)."""
    owner = _Owner()
    owner.values = Float(1.0, 2.0)
    pinned = {"offset": Float(3.0, 4.0)}
    call_recorded(recordings_of(owner, "a"), "k", lambda x, extra: x + extra["offset"],
                  (Float(1.0, 2.0), pinned), _no_state, pinned=(1,))
    assert [id(a) for a in jit_state(vars(owner))] == [id(owner.values)]
