"""The long fuzzing run: many more examples of the readers' fuzz properties than CI runs.

    python -m benchmarks.fuzz [--examples 2000] [--seed 0] [--targets dict,xml,obj,...]

For each target (scene dicts, JSON scene files, Mitsuba XML, OBJ, ASCII and binary PLY, serialized meshes,
EXR images) it runs the property of ``tests/fuzz_inputs.py`` on ``--examples`` inputs drawn
with ``--seed``: every input loads or raises one of the package's documented exceptions,
without NumPy warnings, within the per-example deadline. Printed per target: the examples
run, the time, and the first falsifying input with its error, if any.
"""

from __future__ import annotations

import argparse
import sys
import time
import traceback
from pathlib import Path

from hypothesis import HealthCheck, given, seed, settings

sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "tests"))
import fuzz_inputs as fuzz  # noqa: E402

TARGETS = {
    "dict": (fuzz.mutated_scenes, fuzz.load_scene_dict),
    "json": (fuzz.mutated_json, lambda text: fuzz.load_scene_text(text, ".json")),
    "xml": (fuzz.mutated_xml, lambda text: fuzz.load_scene_text(text, ".xml")),
    "obj": (lambda: fuzz.mutated_bytes(fuzz.VALID_OBJ), lambda data: fuzz.load_scene_text(data, ".obj")),
    "ply-ascii": (lambda: fuzz.mutated_bytes(fuzz.ply_bytes(False)),
                  lambda data: fuzz.load_scene_text(data, ".ply")),
    "ply-binary": (lambda: fuzz.mutated_bytes(fuzz.ply_bytes(True)),
                   lambda data: fuzz.load_scene_text(data, ".ply")),
    "serialized": (lambda: fuzz.mutated_bytes(fuzz.serialized_bytes()),
                   lambda data: fuzz.load_scene_text(data, ".serialized")),
    "exr": (lambda: fuzz.mutated_bytes(fuzz.exr_bytes()), lambda data: fuzz.load_scene_text(data, ".exr")),
}


def run(name: str, examples: int, random_seed: int) -> tuple[int, float, str]:
    """(examples run, seconds, the failure or '') of one target."""
    strategy, check = TARGETS[name]
    count = 0

    @seed(random_seed)
    @settings(max_examples=examples, deadline=fuzz.DEADLINE_MS, database=None,
              suppress_health_check=list(HealthCheck))
    @given(strategy())
    def property_(value):
        nonlocal count
        count += 1
        check(value)

    start = time.perf_counter()
    try:
        property_()
        failure = ""
    except Exception as err:  # the falsifying example and its error, reported
        failure = "".join(traceback.format_exception_only(type(err), err)).strip()
    return count, time.perf_counter() - start, failure


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--examples", type=int, default=2000)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--targets", default=",".join(TARGETS))
    args = parser.parse_args(argv)
    failed = False
    for name in args.targets.split(","):
        count, seconds, failure = run(name, args.examples, args.seed)
        print(f"{name:<11} {count:>6} examples run in {seconds:6.1f} s: "
              f"{'FAILED ' + failure if failure else 'every input loaded or was refused'}", flush=True)
        failed |= bool(failure)
    sys.exit(1 if failed else 0)


if __name__ == "__main__":
    main()
