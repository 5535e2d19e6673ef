"""The scale benchmark (benchmarks/scale.py) at a small size. Its measurements run in worker
processes that reach into the package (the scene parser, the render recordings), and a worker
that fails reports its error in the results instead of raising: here every row and every
recording probe must come back measured."""

from benchmarks import scale


def test_the_scale_benchmark_measures_every_figure_at_a_small_size(capsys):
    result = scale.main(["--counts", "1000", "--repeats", "1", "--size", "32", "--rays", "65536",
                         "--step-max", "1000"])
    capsys.readouterr()
    rows = result["rows"]
    assert [row["instances"] for row in rows] == [1000]
    assert [row for row in rows + result["freeze"] if "error" in row] == []
    row = rows[0]
    assert row["load_s"] > 0 and 0 < row["parse_s"] <= row["load_s"]
    assert row["render_repeat_identical"]
    assert all(probe["identical"] and probe["recordings"] >= 1 for probe in result["freeze"])
