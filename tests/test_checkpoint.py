"""Recovery checkpoints (instancing.ad.checkpoint): a descent resumed from a checkpoint ends
exactly where the uninterrupted descent ends; checkpoints survive a save and load; resuming
with other arguments or from a missing or broken file is refused."""

from __future__ import annotations

import numpy as np
import pytest

import instancing
from instancing.ad.checkpoint import RecoveryCheckpoint
from instancing.ad.recovery import recover
from instancing.core.errors import SceneError

from test_recovery import INIT, TARGET, _coloured

KEYS = ["box.translation", "box.rotation", "box.scale", "blue.reflectance"]
#: 24 iterations whose last half is averaged: the checkpoint at 16 holds running sums.
RUN = dict(iterations=24, spp=4, lr=0.02, average_fraction=0.5, seed=5)


def _problem():
    target_scene = instancing.load_scene(_coloured(TARGET, [0.8, 0.3, 0.2]))
    target = instancing.render(target_scene, "direct", spp=32, seed=9)
    return target, target_scene.to_world


def _final(params) -> dict:
    return {key: np.array(params[key]) for key in KEYS}


def test_resumed_recovery_ends_where_the_uninterrupted_one_ends(tmp_path, one_thread):
    """Resumed from a checkpoint before and inside the averaged iterations (saved and loaded),
    on one Dr.Jit thread (bit-reproducible runs): exactly the uninterrupted run's losses,
    errors, restarts and final values."""
    target, truth = _problem()
    params = instancing.traverse(instancing.load_scene(_coloured(INIT, [0.5, 0.5, 0.5])))
    saved = []
    history = recover(params, target, KEYS, target_to_world=truth, checkpoint=saved.append,
                      checkpoint_every=8, restarts=1, restart_iterations=4, **RUN)
    expected = _final(params)
    assert [c.iteration for c in saved] == [8, 16]
    assert saved[1].sums and not saved[0].sums
    for state in saved:
        state.save(tmp_path / "checkpoint.npz")
        loaded = RecoveryCheckpoint.load(tmp_path / "checkpoint.npz")
        fresh = instancing.traverse(instancing.load_scene(_coloured(INIT, [0.5, 0.5, 0.5])))
        resumed = recover(fresh, target, KEYS, target_to_world=truth, resume=loaded,
                          restarts=1, restart_iterations=4, **RUN)
        for key, value in _final(fresh).items():
            np.testing.assert_array_equal(value, expected[key], err_msg=f"{key} from {state.iteration}")
        assert resumed.loss == history.loss and resumed.errors == history.errors
        assert resumed.restarts == history.restarts and resumed.chosen == history.chosen


def test_resuming_with_other_keys_or_past_the_end_is_refused(tmp_path):
    target, truth = _problem()
    params = instancing.traverse(instancing.load_scene(_coloured(INIT, [0.5, 0.5, 0.5])))
    saved = []
    recover(params, target, KEYS, checkpoint=saved.append, checkpoint_every=8, **RUN)
    fresh = instancing.traverse(instancing.load_scene(_coloured(INIT, [0.5, 0.5, 0.5])))
    with pytest.raises(SceneError, match="the checkpoint optimises"):
        recover(fresh, target, KEYS[:2], resume=saved[0], **RUN)
    with pytest.raises(SceneError, match="checkpoint is at iteration 16"):
        recover(fresh, target, KEYS, resume=saved[1], **dict(RUN, iterations=16))
    with pytest.raises(SceneError, match="checkpoint_every must"):
        recover(fresh, target, KEYS, checkpoint=saved.append, checkpoint_every=0, **RUN)


def test_missing_or_broken_checkpoint_files_are_named(tmp_path):
    with pytest.raises(SceneError, match="no recovery checkpoint at .*nowhere.npz"):
        RecoveryCheckpoint.load(tmp_path / "nowhere.npz")
    broken = tmp_path / "broken.npz"
    broken.write_bytes(b"PK\x03\x04 truncated")
    with pytest.raises(SceneError, match="cannot read the recovery checkpoint .*broken.npz"):
        RecoveryCheckpoint.load(broken)
