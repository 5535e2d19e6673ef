"""Output files written whole or not at all: each writer writes to a temporary name beside
the destination and renames it over the destination when done (a rename within one folder
is atomic on POSIX file systems), so an interrupted render or recovery never leaves a
truncated image, plot or scene behind, and an existing file stays as it was."""

from __future__ import annotations

import contextlib
import os
import uuid
from pathlib import Path
from typing import Iterator


@contextlib.contextmanager
def replaced(path: str | os.PathLike[str]) -> Iterator[str]:
    """A temporary file name beside ``path`` (same folder and suffix, so that writers that
    choose the format by the extension still do), renamed over ``path`` when the block
    ends and deleted if it raises (Ctrl-C included)."""
    path = Path(path)
    partial = path.with_name(f".{path.stem}.{uuid.uuid4().hex[:12]}.partial{path.suffix}")
    try:
        yield os.fspath(partial)
        os.replace(partial, path)
    except BaseException:
        with contextlib.suppress(OSError):
            os.unlink(partial)
        raise


def remove_partials(folder: str | os.PathLike[str]) -> None:
    """Delete the temporary files of :func:`replaced` that a killed process left in
    ``folder`` (a kill gives the writer no chance to delete its own)."""
    for path in Path(folder).glob(".*.partial*"):
        with contextlib.suppress(OSError):
            path.unlink()

