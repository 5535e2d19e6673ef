"""Tests of the EXR reader/writer and the PNG preview writer (instancing/io/image.py).

References: bit patterns of the float32 input (round trips), Mitsuba's own
Bitmap EXR writer and PNG decoder, and the sRGB transfer function in float64.
"""

from __future__ import annotations

import re

import numpy as np
import OpenEXR
import pytest
from hypothesis import given

import instancing  # noqa: F401  (selects the Dr.Jit backend before Mitsuba loads)
import mitsuba as mi
from instancing.core.backend import TensorXf
from instancing.core.errors import InstancingError
from instancing.io.image import (CHANNEL_ORDER_ATTRIBUTE, ImageDataError, ImageFileError,
                                 ImageNotFoundError, read_exr, srgb_encode, write_exr,
                                 write_png)
import fuzz_inputs as fuzz

PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"


@pytest.fixture
def scalar_rgb():
    """Run a test under Mitsuba's scalar_rgb variant, then restore the previous one."""
    previous = mi.variant()
    mi.set_variant("scalar_rgb")
    yield
    if previous is not None:
        mi.set_variant(previous)


def random_bits(rng: np.random.Generator, shape: tuple[int, ...]) -> np.ndarray:
    """Float32 array from random bit patterns (every class: NaN payloads, inf, denormals),
    with the special values planted at the start."""
    bits = rng.integers(0, 2**32, size=shape, dtype=np.uint64).astype(np.uint32)
    specials = np.array([0x7F800000, 0xFF800000, 0x7FC00000, 0xFFC12345, 0x7F800001,
                         0x80000000, 0x00000000, 0x00000001, 0x807FFFFF, 0x3F800000,
                         0xBF800000, 0x7F7FFFFF], dtype=np.uint32)
    flat = bits.reshape(-1)
    flat[:specials.size] = specials
    return bits.view(np.float32)


def same_bits(a: np.ndarray, b: np.ndarray) -> bool:
    """True when two float32 arrays have the same shape and identical bit patterns."""
    a = np.asarray(a, dtype=np.float32)
    b = np.asarray(b, dtype=np.float32)
    return a.shape == b.shape and np.array_equal(a.view(np.uint32), b.view(np.uint32))


def path_pattern(path) -> str:
    """Regex that matches an error message naming ``path``."""
    return re.escape(str(path))


# --- EXR round trips ---------------------------------------------------------------------------

@pytest.mark.parametrize("shape, channels, expected_names", [
    ((5, 7), None, ["Y"]),
    ((5, 7, 1), None, ["Y"]),
    ((6, 4, 3), None, ["R", "G", "B"]),
    ((3, 8, 4), None, ["R", "G", "B", "A"]),
    ((4, 5, 7), ["depth", "nx", "ny", "nz", "instance", "B", "A"],
     ["depth", "nx", "ny", "nz", "instance", "B", "A"]),
    ((4, 5, 3), ["Z", "G", "R"], ["Z", "G", "R"]),
])
def test_exr_round_trip_is_bit_exact(tmp_path, shape, channels, expected_names):
    rng = np.random.default_rng(1234)
    image = random_bits(rng, shape)
    path = tmp_path / "image.exr"
    write_exr(path, image, channels)
    pixels, names = read_exr(path)
    assert names == expected_names
    assert pixels.dtype == np.float32 and pixels.flags["C_CONTIGUOUS"]
    expected = image if image.ndim == 3 else image[:, :, None]
    assert same_bits(pixels, expected)


def test_exr_named_channels_are_stored_sorted_and_order_recorded(tmp_path):
    # EXR sorts channels in the file; the intended order lives in a header attribute.
    names = ["depth", "nx", "ny", "nz", "instance"]
    path = tmp_path / "aov.exr"
    write_exr(str(path), np.zeros((2, 3, 5), np.float32), names)
    exr = OpenEXR.File(str(path), separate_channels=True)
    assert list(exr.channels()) == sorted(names)
    assert exr.header()[CHANNEL_ORDER_ATTRIBUTE] == names
    compression = exr.header()["compression"]
    assert compression in (OpenEXR.ZIP_COMPRESSION, OpenEXR.PIZ_COMPRESSION)
    assert all(c.pixels.dtype == np.float32 for c in exr.channels().values())


def test_exr_special_values_survive(tmp_path):
    values = np.array([[np.inf, -np.inf, np.nan, -0.0, 0.0, 1e-45, -1e-40, 3.4e38, -7.5]],
                      dtype=np.float32)
    path = tmp_path / "special.exr"
    write_exr(path, values)
    pixels, names = read_exr(path)
    assert names == ["Y"]
    assert same_bits(pixels[:, :, 0], values)
    assert np.signbit(pixels[0, 3, 0]) and not np.signbit(pixels[0, 4, 0])


def test_exr_non_contiguous_and_converted_inputs(tmp_path):
    # OpenEXR ignores NumPy strides, so views must be copied before writing.
    rng = np.random.default_rng(7)
    base = rng.standard_normal((8, 10, 6)).astype(np.float32)
    view = base[::2, 1::3, ::2]
    write_exr(tmp_path / "view.exr", view)
    pixels, _ = read_exr(tmp_path / "view.exr")
    assert same_bits(pixels, view)

    # float64, integer and bool data are converted to float32.
    as64 = rng.standard_normal((3, 4, 3))
    write_exr(tmp_path / "f64.exr", as64)
    assert same_bits(read_exr(tmp_path / "f64.exr")[0], as64.astype(np.float32))
    ints = np.arange(12, dtype=np.int32).reshape(3, 4) - 6
    write_exr(tmp_path / "int.exr", ints)
    assert same_bits(read_exr(tmp_path / "int.exr")[0][:, :, 0], ints.astype(np.float32))
    write_exr(tmp_path / "list.exr", [[0.5, 1.5], [2.5, 3.5]])
    assert same_bits(read_exr(tmp_path / "list.exr")[0][:, :, 0], [[0.5, 1.5], [2.5, 3.5]])


def test_exr_from_drjit_tensor(tmp_path):
    rng = np.random.default_rng(3)
    image = rng.standard_normal((6, 5, 3)).astype(np.float32)
    image[0, 0] = [np.inf, -0.0, np.nan]
    tensor = TensorXf(image)
    path = tmp_path / "tensor.exr"
    write_exr(path, tensor)
    pixels, names = read_exr(path)
    assert names == ["R", "G", "B"]
    assert same_bits(pixels, image)


def test_exr_overwrites_existing_file(tmp_path):
    path = tmp_path / "again.exr"
    write_exr(path, np.ones((4, 4, 3), np.float32))
    write_exr(path, np.full((2, 3), 2.0, np.float32), ["depth"])
    pixels, names = read_exr(path)
    assert names == ["depth"] and pixels.shape == (2, 3, 1) and np.all(pixels == 2.0)


def test_read_exr_written_by_mitsuba(tmp_path, scalar_rgb):
    rng = np.random.default_rng(11)
    image = rng.standard_normal((7, 9, 3)).astype(np.float32)
    image[1, 2] = [np.inf, -0.0, -3.0]
    path = tmp_path / "mitsuba.exr"
    mi.Bitmap(image).write(str(path))
    pixels, names = read_exr(path)
    assert names == ["R", "G", "B"]
    assert same_bits(pixels, image)


def test_mitsuba_reads_exr_written_here(tmp_path, scalar_rgb):
    rng = np.random.default_rng(12)
    image = rng.standard_normal((4, 6, 3)).astype(np.float32)
    path = tmp_path / "ours.exr"
    write_exr(path, image)
    assert same_bits(np.array(mi.Bitmap(str(path))), image)


def test_read_foreign_exr_orders_rgba_first_then_sorted(tmp_path):
    # A file without the order attribute, with half and uint channels as other tools write.
    h, w = 3, 4
    rng = np.random.default_rng(5)
    planes = {
        "B": rng.standard_normal((h, w)).astype(np.float32),
        "A": rng.random((h, w)).astype(np.float32),
        "R": rng.standard_normal((h, w)).astype(np.float32),
        "G": rng.standard_normal((h, w)).astype(np.float16),
        "z": rng.standard_normal((h, w)).astype(np.float32),
        "albedo.R": np.full((h, w), 0.25, np.float32),
        "id": np.arange(h * w, dtype=np.uint32).reshape(h, w),
    }
    path = tmp_path / "foreign.exr"
    # (OpenEXR.File replaces the arrays in the dict it is given by Channel objects: pass a copy)
    OpenEXR.File({"compression": OpenEXR.PIZ_COMPRESSION}, dict(planes)).write(str(path))
    pixels, names = read_exr(path)
    assert names == ["R", "G", "B", "A", "albedo.R", "id", "z"]
    assert pixels.dtype == np.float32
    for k, name in enumerate(names):
        assert same_bits(pixels[:, :, k], planes[name].astype(np.float32)), name


def test_read_ignores_stale_channel_order_attribute(tmp_path):
    # An order attribute that does not match the channels (edited by another tool) is ignored.
    planes = {"G": np.zeros((2, 2), np.float32), "R": np.ones((2, 2), np.float32)}
    path = tmp_path / "stale.exr"
    OpenEXR.File({CHANNEL_ORDER_ATTRIBUTE: ["G", "R", "B"]}, planes).write(str(path))
    pixels, names = read_exr(path)
    assert names == ["R", "G"]
    assert np.all(pixels[:, :, 0] == 1) and np.all(pixels[:, :, 1] == 0)


# --- PNG ---------------------------------------------------------------------------------------

def test_srgb_encode_matches_closed_form():
    x = np.array([0.0, 0.0031308, 0.5, 1.0])
    expected = [0.0, 0.0031308 * 12.92, 1.055 * 0.5 ** (1 / 2.4) - 0.055, 1.0]
    np.testing.assert_allclose(srgb_encode(x), expected, rtol=0, atol=1e-15)
    # the two branches meet at the threshold (continuity to ~1e-7 by the standard's rounding)
    assert abs(1.055 * 0.0031308 ** (1 / 2.4) - 0.055 - 12.92 * 0.0031308) < 1e-7


def test_png_known_values(tmp_path):
    values = np.array([[0.0, 1.0, 0.5, 0.0031308, 0.2, -1.0, 4.0, np.inf, -np.inf, np.nan]],
                      dtype=np.float32)
    # 0.5 -> 255 * 0.735357 = 187.52 -> 188; 0.0031308 -> 255 * 0.0404500 = 10.31 -> 10;
    # 0.2 -> 255 * 0.484529 = 123.55 -> 124; out of range and NaN clamp to 0 or 255.
    expected = np.array([[0, 255, 188, 10, 124, 0, 255, 255, 0, 0]], dtype=np.uint8)
    path = tmp_path / "gray.png"
    write_png(path, values)
    assert path.read_bytes()[:8] == PNG_SIGNATURE
    decoded = np.array(mi.Bitmap(str(path)))
    assert decoded.dtype == np.uint8
    np.testing.assert_array_equal(decoded.reshape(expected.shape), expected)


def test_png_rgb_and_rgba(tmp_path):
    rgb = np.array([[[0.0, 0.5, 1.0], [0.0031308, 2.0, -0.5]]], dtype=np.float32)
    write_png(tmp_path / "rgb.png", rgb)
    decoded = np.array(mi.Bitmap(str(tmp_path / "rgb.png")))
    np.testing.assert_array_equal(decoded, [[[0, 188, 255], [10, 255, 0]]])

    # alpha is linear coverage: no sRGB curve and no exposure
    rgba = np.array([[[0.5, 0.5, 0.5, 0.5], [1.0, 0.0, 0.25, 1.5]]], dtype=np.float32)
    write_png(tmp_path / "rgba.png", rgba, exposure=1.0)
    decoded = np.array(mi.Bitmap(str(tmp_path / "rgba.png")))
    assert decoded.shape == (1, 2, 4)
    np.testing.assert_array_equal(decoded, [[[255, 255, 255, 128], [255, 0, 188, 255]]])


def test_png_of_premultiplied_rgba_stores_straight_colour(tmp_path):
    # A render's colour is premultiplied by its alpha: 0.25 at alpha 0.5 is 0.5 straight
    # (188); colour at alpha 0 is 0; an RGB image is unchanged by the flag.
    rgba = np.array([[[0.25, 0.5, 0.0, 0.5], [0.3, 0.3, 0.3, 0.0]]], dtype=np.float32)
    write_png(tmp_path / "rgba.png", rgba, premultiplied=True)
    decoded = np.array(mi.Bitmap(str(tmp_path / "rgba.png")))
    np.testing.assert_array_equal(decoded, [[[188, 255, 0, 128], [0, 0, 0, 0]]])
    rgb = np.array([[[0.0, 0.5, 1.0]]], dtype=np.float32)
    write_png(tmp_path / "rgb.png", rgb, premultiplied=True)
    np.testing.assert_array_equal(np.array(mi.Bitmap(str(tmp_path / "rgb.png"))), [[[0, 188, 255]]])


def test_png_exposure(tmp_path):
    # One stop up turns 0.25 into 0.5 (188); two stops down turns 2.0 into 0.5.
    image = np.array([[0.25, 2.0]], dtype=np.float32)
    write_png(tmp_path / "up.png", image, exposure=1.0)
    write_png(tmp_path / "down.png", image, exposure=-2.0)
    up = np.array(mi.Bitmap(str(tmp_path / "up.png"))).reshape(-1)
    down = np.array(mi.Bitmap(str(tmp_path / "down.png"))).reshape(-1)
    np.testing.assert_array_equal(up, [188, 255])
    np.testing.assert_array_equal(down, [71, 188])  # 0.0625 -> 255 * 0.27730 = 70.71 -> 71


def test_png_agrees_with_mitsuba_conversion(tmp_path, scalar_rgb):
    # Mitsuba's own float -> 8-bit sRGB conversion rounds differently; within one level.
    rng = np.random.default_rng(21)
    image = rng.random((16, 16, 3)).astype(np.float32)
    write_png(tmp_path / "random.png", image)
    ours = np.array(mi.Bitmap(str(tmp_path / "random.png"))).astype(int)
    theirs = np.array(mi.Bitmap(image).convert(mi.Bitmap.PixelFormat.RGB, mi.Struct.Type.UInt8,
                                               True)).astype(int)
    assert np.max(np.abs(ours - theirs)) <= 1


def test_png_from_drjit_tensor(tmp_path):
    image = np.zeros((3, 2, 3), np.float32)
    image[1, 1] = [1.0, 0.5, 0.0]
    write_png(tmp_path / "tensor.png", TensorXf(image))
    decoded = np.array(mi.Bitmap(str(tmp_path / "tensor.png")))
    np.testing.assert_array_equal(decoded[1, 1], [255, 188, 0])
    assert decoded.shape == (3, 2, 3) and decoded.sum() == 255 + 188


# --- errors ------------------------------------------------------------------------------------

def test_read_missing_file(tmp_path):
    path = tmp_path / "nowhere.exr"
    with pytest.raises(ImageNotFoundError, match=path_pattern(path)) as info:
        read_exr(path)
    assert isinstance(info.value, FileNotFoundError)
    assert isinstance(info.value, ImageFileError) and isinstance(info.value, InstancingError)


@pytest.mark.parametrize("content", [b"", b"not an exr file at all" * 10, b"v/1\x01" + b"\0" * 50])
def test_read_corrupt_file(tmp_path, content):
    path = tmp_path / "corrupt.exr"
    path.write_bytes(content)
    with pytest.raises(ImageFileError, match=path_pattern(path)):
        read_exr(path)


def test_read_truncated_file(tmp_path):
    path = tmp_path / "whole.exr"
    write_exr(path, np.random.default_rng(0).standard_normal((64, 64, 3)).astype(np.float32))
    data = path.read_bytes()
    cut = tmp_path / "truncated.exr"
    cut.write_bytes(data[: len(data) * 3 // 4])
    with pytest.raises(ImageFileError, match=path_pattern(cut)):
        read_exr(cut)


def test_read_directory(tmp_path):
    with pytest.raises(ImageFileError, match=path_pattern(tmp_path)):
        read_exr(tmp_path)


def test_read_multipart_file(tmp_path):
    path = tmp_path / "parts.exr"
    parts = [OpenEXR.Part({}, {"Z": np.zeros((2, 2), np.float32)}, name=name)
             for name in ("a", "b")]
    OpenEXR.File(parts).write(str(path))
    with pytest.raises(ImageFileError, match=path_pattern(path)):
        read_exr(path)


@pytest.mark.parametrize("writer", [write_exr, write_png])
@pytest.mark.parametrize("shape", [(5,), (2, 3, 4, 1), ()])
def test_write_wrong_rank(tmp_path, writer, shape):
    path = tmp_path / "rank.out"
    with pytest.raises(ImageDataError, match=path_pattern(path)):
        writer(path, np.zeros(shape, np.float32))
    assert not path.exists()


@pytest.mark.parametrize("writer", [write_exr, write_png])
def test_write_empty_image(tmp_path, writer):
    path = tmp_path / "empty.out"
    with pytest.raises(ImageDataError, match=path_pattern(path)):
        writer(path, np.zeros((0, 4, 3), np.float32))


@pytest.mark.parametrize("writer", [write_exr, write_png])
@pytest.mark.parametrize("image", [
    np.array([["a", "b"], ["c", "d"]]),
    np.array([["1.0", "2.0"], ["3.0", "4.0"]]),
    np.ones((2, 2), np.complex64),
    np.array([[object(), object()]], dtype=object),
    np.zeros((2, 2), dtype="datetime64[s]"),
])
def test_write_non_numeric_data(tmp_path, writer, image):
    path = tmp_path / "data.out"
    with pytest.raises(ImageDataError, match=path_pattern(path)):
        writer(path, image)


def test_write_ragged_nested_list(tmp_path):
    path = tmp_path / "ragged.exr"
    with pytest.raises(ImageDataError, match=path_pattern(path)):
        write_exr(path, [[1.0, 2.0], [3.0]])


@pytest.mark.parametrize("shape, channels", [
    ((2, 2, 3), ["R", "G"]),
    ((2, 2, 3), ["R", "G", "B", "A"]),
    ((2, 2), ["R", "G"]),
    ((2, 2, 5), None),
    ((2, 2, 2), None),
    ((2, 2, 2), ["x", "x"]),
    ((2, 2, 2), ["x", ""]),
    ((2, 2, 2), ["x", "a\0b"]),
    ((2, 2, 2), ["x", 3]),
    ((2, 2, 1), ["n" * 256]),
    ((2, 2, 2), "xy"),
])
def test_write_exr_bad_channels(tmp_path, shape, channels):
    path = tmp_path / "channels.exr"
    with pytest.raises(ImageDataError, match=path_pattern(path)):
        write_exr(path, np.zeros(shape, np.float32), channels)
    assert not path.exists()


def test_write_exr_longest_channel_name(tmp_path):
    name = "n" * 255
    write_exr(tmp_path / "long.exr", np.ones((2, 2), np.float32), [name])
    assert read_exr(tmp_path / "long.exr")[1] == [name]


@pytest.mark.parametrize("channels", [2, 5, 7])
def test_write_png_bad_channel_count(tmp_path, channels):
    path = tmp_path / "count.png"
    with pytest.raises(ImageDataError, match=path_pattern(path)):
        write_png(path, np.zeros((2, 2, channels), np.float32))


@pytest.mark.parametrize("exposure", [float("nan"), float("inf"), "bright", 1e6, -1e6])
def test_write_png_bad_exposure(tmp_path, exposure):
    """(1e6 stops overflowed float64 inside the tone map.)"""
    path = tmp_path / "exposure.png"
    with pytest.raises(ImageDataError, match=path_pattern(path)):
        write_png(path, np.zeros((2, 2), np.float32), exposure=exposure)


@pytest.mark.parametrize("name", ["preview.exr", "preview.jpg", "preview.TIF"])
def test_write_png_refuses_a_name_of_another_format(tmp_path, name):
    """(It wrote PNG bytes under the other format's name.)"""
    with pytest.raises(ImageFileError, match="its name says"):
        write_png(tmp_path / name, np.zeros((2, 2, 3), np.float32))
    assert not (tmp_path / name).exists()


@pytest.mark.parametrize("writer", [write_exr, write_png])
def test_write_unwritable_path(tmp_path, writer):
    missing_dir = tmp_path / "no" / "such" / "dir" / "image.out"
    with pytest.raises(ImageFileError, match=path_pattern(missing_dir)):
        writer(missing_dir, np.zeros((2, 2, 3), np.float32))
    with pytest.raises(ImageFileError, match=path_pattern(tmp_path)):
        writer(tmp_path, np.zeros((2, 2, 3), np.float32))


@fuzz.ci_settings(100)
@given(fuzz.mutated_bytes(fuzz.exr_bytes()))
def test_fuzzed_exr_files_load_or_raise_documented_errors(data):
    """A valid EXR image with bytes replaced, deleted, inserted or cut off reads or raises
    an ImageFileError (an InstancingError) (tests/fuzz_inputs.py)."""
    fuzz.load_scene_text(data, ".exr")


@pytest.mark.parametrize("name", ["preview.png", "photo.JPG", "probe.hdr"])
def test_write_exr_refuses_a_name_of_another_image_format(tmp_path, name):
    """An EXR written under another format's suffix would be unreadable as that format."""
    with pytest.raises(ImageFileError, match=re.escape(name)):
        write_exr(tmp_path / name, np.zeros((2, 2, 3), np.float32))
    assert not (tmp_path / name).exists()
