"""Mitsuba volume grid files (instancing/io/volume_grid.py): the layout against the format's
definition, and fuzzed files (load or raise an ImageFileError). The lookups on a grid are
checked against Mitsuba's own plugin in tests/test_texture.py."""

from __future__ import annotations

import struct

import numpy as np
from hypothesis import given

import instancing  # noqa: F401  (selects libLLVM before Dr.Jit starts)
from instancing.io.volume_grid import read_volume_grid
import fuzz_inputs as fuzz


def test_values_are_indexed_z_y_x_channel_as_the_format_defines(tmp_path):
    """``data[((z * yres + y) * xres + x) * channels + c]`` is ``values[z, y, x, c]``, and the
    bounding box is read as written."""
    xres, yres, zres, channels = 4, 3, 2, 3
    data = np.arange(xres * yres * zres * channels, dtype="<f4")
    path = tmp_path / "grid.vol"
    path.write_bytes(struct.pack("<3sBiiiii6f", b"VOL", 3, 1, xres, yres, zres, channels,
                                 -1, -2, -3, 4, 5, 6) + data.tobytes())
    grid = read_volume_grid(path)
    assert grid.values.shape == (zres, yres, xres, channels)
    z, y, x, c = 1, 2, 3, 1
    assert grid.values[z, y, x, c] == data[((z * yres + y) * xres + x) * channels + c]
    np.testing.assert_array_equal(grid.bounds[0], [-1, -2, -3])
    np.testing.assert_array_equal(grid.bounds[1], [4, 5, 6])


def test_fuzzed_volume_grids_load_or_raise_documented_errors():
    """A valid grid with bytes replaced, deleted, inserted or cut off: each loads or raises an
    ImageFileError (an InstancingError), without NumPy warnings (tests/fuzz_inputs.py)."""
    @fuzz.ci_settings(100)
    @given(fuzz.mutated_bytes(fuzz.volume_grid_bytes()))
    def check(data):
        fuzz.load_scene_text(data, ".vol")

    check()
