"""Resource limits (instancing.core.memory): work that cannot fit is refused before anything
large is allocated, with the estimate in the message."""

from __future__ import annotations

import numpy as np
import pytest

import instancing
from instancing.core import memory
from instancing.rendering import film
from instancing.core.errors import ResourceError


def _camera(width: int, height: int) -> dict:
    return {"type": "perspective", "fov": 40, "width": width, "height": height,
            "to_world": [{"look_at": {"origin": [0, -4, 1], "target": [0, 0, 0], "up": [0, 0, 1]}}]}


def _ball_scene(width: int, height: int):
    return instancing.load_scene({
        "materials": {"grey": {"type": "diffuse", "reflectance": 0.5}},
        "instances": [{"model": "sphere", "material": "grey"}],
        "camera": _camera(width, height),
        "lights": [{"type": "point", "position": [0, -3, 3], "intensity": 10.0}]})


#: The memory the tests give the machine: this one's 24 GiB, whatever the host (an
#: accelerator's host has more than some of the estimates refused here).
TEST_MACHINE_BYTES = 24 * 2 ** 30


def test_largest_film_is_refused_with_its_estimate_before_rendering(monkeypatch):
    # 32768 x 32768 (the largest side accepted) needs ~1e9 pixels' worth of passes and film.
    monkeypatch.setattr(memory, "physical_memory", lambda: TEST_MACHINE_BYTES)
    scene = _ball_scene(8, 8)

    def rendered(*args, **kwargs):
        raise AssertionError("the render started")

    monkeypatch.setattr(film, "_image", rendered)
    with pytest.raises(ResourceError) as err:
        instancing.render(scene, "direct", spp=1, width=32768, height=32768)
    text = str(err.value)
    assert "32768x32768" in text and "GiB" in text and "this machine has" in text
    estimate = float(text.split("about ")[1].split(" GiB")[0])
    # Passes of 2^30 lanes and three film copies, 3 channels of 4 bytes: 60 GiB.
    np.testing.assert_allclose(estimate, 4 * 3 * 5 * 2 ** 30 / 2 ** 30, rtol=1e-2)


def test_film_that_overflows_drjit_array_sizes_is_refused():
    scene = _ball_scene(8, 8)
    aovs = ["depth", "position", "normal", "shading_normal", "instance", "albedo", "uv"]
    with pytest.raises(ResourceError, match=r"2\^32"):
        instancing.render(scene, "aov", spp=1, aovs=aovs, width=32768, height=32768)


def test_render_that_fits_is_not_refused():
    image = instancing.render(_ball_scene(16, 12), "direct", spp=2)
    assert image.shape == (12, 16, 3)


def test_npy_of_1e8_matrices_is_refused_from_its_header(tmp_path, monkeypatch):
    """A sparse file whose header says 1e8 matrices (12.8 GB of data never written): refused
    without reading it."""
    monkeypatch.setattr(memory, "physical_memory", lambda: TEST_MACHINE_BYTES)
    path = tmp_path / "huge.npy"
    count = 100_000_000
    with open(path, "wb") as f:
        np.lib.format.write_array_header_1_0(
            f, {"descr": "<f8", "fortran_order": False, "shape": (count, 4, 4)})
        f.truncate(f.tell() + count * 128)
    with pytest.raises(ResourceError) as err:
        instancing.load_scene({"instances": [{"model": "sphere", "to_world": str(path)}]})
    text = str(err.value)
    assert "100000000 instances" in text and str(path) in text and "GiB" in text


def test_instance_count_beyond_memory_is_refused_before_the_build(monkeypatch):
    # The machine's memory shrunk to 50 MB: 100 000 instances (about 100 MB at peak) refused,
    # whether given as one array or as separate entries.
    monkeypatch.setattr(memory, "physical_memory", lambda: 50_000_000)
    matrices = np.tile(np.eye(4), (100_000, 1, 1))
    matrices[:, 0, 3] = np.arange(100_000)
    with pytest.raises(ResourceError, match="100000 instances would need about 95.4 MiB"):
        instancing.load_scene({"instances": [{"model": "sphere", "to_world": matrices}]})
    entries = [{"model": "sphere", "to_world": [{"translate": [float(k), 0, 0]}]}
               for k in range(60_000)]
    with pytest.raises(ResourceError, match="a scene of 60000 instances"):
        instancing.load_scene({"instances": entries})


def test_resource_error_is_an_instancing_error_and_a_memory_error():
    assert issubclass(ResourceError, instancing.InstancingError)
    assert issubclass(ResourceError, MemoryError)
    assert memory.physical_memory() > 2 ** 28
