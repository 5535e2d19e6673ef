"""Checkpoints of a recovery: what :func:`~instancing.ad.recovery.recover` needs to go on with
a descent where it stopped and end exactly where an uninterrupted run ends (same seeds).

A checkpoint holds the iterations done, the optimiser's values and Adam moments, the values
the descent started from (parts an instance keeps are restored from them), the running sums
of the iterate average and the history so far. It is saved as one ``.npz`` file (the
history inside as JSON text), written whole or not at all
(:func:`~instancing.io.output_file.replaced`).
"""

from __future__ import annotations

import json
import os
import zipfile
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from ..core.errors import SceneError
from ..io.output_file import replaced

#: The optimiser entry's arrays a checkpoint keeps: Adam's value, step count and moments.
_MOMENTS = ("t", "m", "v")


@dataclass
class RecoveryCheckpoint:
    """The state of a descent after ``iteration`` iterations (see the module docstring):
    per optimiser key its value and Adam's ``t``, ``m``, ``v``; ``start`` and ``sums`` per
    key where the descent keeps them; ``history`` as :class:`RecoveryHistory`'s fields."""

    iteration: int
    optimiser: dict[str, dict[str, np.ndarray]]
    start: dict[str, np.ndarray]
    sums: dict[str, np.ndarray]
    history: dict[str, Any]

    @classmethod
    def capture(cls, iteration: int, opt: Any, start: dict, sums: dict,
                history: dict[str, Any]) -> "RecoveryCheckpoint":
        """The state of ``opt`` (a ``drjit.opt.Adam``) and of the descent's own arrays."""
        optimiser = {}
        for key, (value, _, _, extra) in opt.state.items():
            if extra[3] is not None:
                raise SceneError("a recovery checkpoint keeps Adam's state without AMSGrad")
            optimiser[key] = {"value": np.array(value),
                              **{name: np.array(array) for name, array in zip(_MOMENTS, extra)}}
        return cls(iteration, optimiser, {k: np.array(v) for k, v in start.items()},
                   {k: np.array(v) for k, v in sums.items()}, history)

    def restore(self, opt: Any, start: dict, sums: dict) -> None:
        """Put the checkpoint's values into ``opt`` (whose keys, learning rates and array
        types are those of the run that saved it), and into ``start`` and ``sums`` (the
        descent's dicts, typed by ``opt``'s values)."""
        if sorted(self.optimiser) != sorted(opt.keys()):
            raise SceneError(f"the checkpoint optimises {sorted(self.optimiser)}, this recovery "
                             f"{sorted(opt.keys())}: resume with the arguments it was saved with")
        for key, saved in self.optimiser.items():
            value, _, _, extra = opt.state[key]
            opt[key] = type(value)(saved["value"])
            value, promoted, rate, _ = opt.state[key]
            moments = tuple(type(array)(saved[name]) for name, array in zip(_MOMENTS, extra))
            opt.state[key] = (value, promoted, rate, moments + (None,))
        for target, saved in ((start, self.start), (sums, self.sums)):
            target.clear()
            target.update({key: type(opt[key])(array) for key, array in saved.items()})

    def save(self, path: str | os.PathLike[str]) -> None:
        """Write the checkpoint to ``path`` (.npz), replacing any earlier one whole."""
        arrays = {"meta": np.array(json.dumps({
            "iteration": self.iteration, "history": self.history,
            "optimiser": {key: sorted(entry) for key, entry in self.optimiser.items()},
            "start": sorted(self.start), "sums": sorted(self.sums)}))}
        for key, entry in self.optimiser.items():
            arrays.update({f"optimiser/{key}/{name}": array for name, array in entry.items()})
        arrays.update({f"start/{key}": array for key, array in self.start.items()})
        arrays.update({f"sums/{key}": array for key, array in self.sums.items()})
        with replaced(path) as partial:
            with open(partial, "wb") as f:
                np.savez(f, **arrays)

    @classmethod
    def load(cls, path: str | os.PathLike[str]) -> "RecoveryCheckpoint":
        """Read a checkpoint written by :meth:`save`."""
        path = Path(path)
        if not path.is_file():
            raise SceneError(f"no recovery checkpoint at {path}")
        try:
            with np.load(path, allow_pickle=False) as data:
                meta = json.loads(str(data["meta"]))
                optimiser = {key: {name: data[f"optimiser/{key}/{name}"] for name in names}
                             for key, names in meta["optimiser"].items()}
                start = {key: data[f"start/{key}"] for key in meta["start"]}
                sums = {key: data[f"sums/{key}"] for key in meta["sums"]}
            return cls(int(meta["iteration"]), optimiser, start, sums, meta["history"])
        except (OSError, ValueError, KeyError, TypeError, zipfile.BadZipFile) as err:
            raise SceneError(f"cannot read the recovery checkpoint {path}: {err}") from None
