"""benchmarks/public_scenes.py: one file's verdict, rendered as the file asks."""

from __future__ import annotations

import re

from benchmarks.public_scenes import compare, equal_error_time

STAGE = """<shape type="sphere"><bsdf type="diffuse"/></shape>
    <shape type="rectangle"><transform name="to_world"><scale value="4"/><translate z="-1"/></transform>
        <bsdf type="diffuse"/></shape>
    <emitter type="constant"/>
    <sensor type="perspective"><transform name="to_world"><lookat origin="0, -5, 3" target="0, 0, 0"
        up="0, 0, 1"/></transform><film type="hdrfilm"><integer name="width" value="32"/>
        <integer name="height" value="24"/></film></sensor>"""


def _file(tmp_path, integrator: str, body: str = STAGE):
    path = tmp_path / "scene.xml"
    path.write_text(f'<scene version="3.0.0">{integrator}{body}</scene>')
    return path


def _means(detail: str) -> tuple[float, float]:
    ours, reference = re.search(r"means ([0-9.]+) / ([0-9.]+)", detail).groups()
    return float(ours), float(reference)


def test_a_file_is_rendered_with_its_own_integrator_by_both(tmp_path):
    """The file's path (max_depth 3, roulette from the first bounce) by ours and Mitsuba's:
    a match, the means within 1 %; rendered `direct` instead, both means are lower (by 2.8 %)
    by the interreflection between the sphere and the floor that the file asks for."""
    path = _file(tmp_path, '<integrator type="prb"><integer name="max_depth" value="3"/>'
                           '<integer name="rr_depth" value="1"/></integrator>')
    verdict, detail, equal_error = compare(path, (32, 24), 64, 4096, "file", {}, 4)
    ours, reference = _means(detail)
    assert verdict == "match" and abs(ours / reference - 1) < 0.01, detail
    times = re.search(r"render ours ([0-9.]+) s, Mitsuba's ([0-9.]+) s", detail)
    assert times and min(float(t) for t in times.groups()) > 0 and equal_error > 0, detail
    direct = _means(compare(path, (32, 24), 64, 4096, "direct", {}, 4)[1])
    assert max(direct) < 0.98 * min(ours, reference), (detail, direct)


def test_equal_error_time_scales_the_time_ratio_by_the_squared_error_ratio():
    # Half the error at equal spp: a quarter of the samples reach the other's error.
    assert equal_error_time(2.0, 0.5) == 0.5
    assert equal_error_time(1.5, 1.0) == 1.5


def test_files_whose_integrator_ours_do_not_render_or_without_a_sensor_are_reported(tmp_path):
    verdict, detail, equal_error = compare(_file(tmp_path, '<integrator type="ptracer"/>'), (16, 12), 4, 16,
                                           "file", {}, 1)
    assert verdict == "refused" and "its integrator" in detail and "'ptracer'" in detail
    assert equal_error is None
    verdict, _, equal_error = compare(_file(tmp_path, "", '<shape type="sphere"/>'), (16, 12), 4, 16,
                                      "file", {}, 1)
    assert verdict == "no sensor" and equal_error is None
