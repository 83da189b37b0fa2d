"""benchmarks/temporal.py: its flicker measure on frames of known error, and a `--quick` run at a tiny size
(every clip kind, every output, the tables)."""
import json
import math

import numpy as np
import pytest
from conftest import load_benchmark


@pytest.fixture(scope="module")
def bench():
    return load_benchmark("temporal", "bench_temporal")


def test_flicker_is_the_rms_change_of_the_log2_error_outside_bright(bench):
    truth = np.full((4, 5), 100.0)
    truth[0] = 5000.0                                  # bright in every frame: not counted
    f = bench.Flicker(white=1e6, bright=4000.0)
    outs = [truth * 2, truth.copy(), truth * 2, truth * 0.5]     # errors +1, 0, +1, -1 stops
    outs[1][0] = 1e5                                   # a change only in the bright row
    f.add_clip([truth] * 4, outs)
    assert f.value() == pytest.approx(math.sqrt((1 + 1 + 4) / 3))
    assert bench.Flicker(1e6, 4000.0).value() is None


def test_quick_run_at_a_tiny_size(bench, tmp_path, capsys):
    rc = bench.main(["--quick", "--scenes", "synthetic", "--size", "48x36", "--frames", "3",
                     "--fps-size", "64x48", "--fps-frames", "2", "--repeat", "1", "--out", str(tmp_path)])
    assert rc == 0
    info = json.loads((tmp_path / "results.json").read_text())
    configs = ["off", "on", "camera"] if bench.TemporalReconstructor is not None else ["off", "camera"]
    assert list(info["quality"]) == list(bench.CLIPS)
    for kind, by in info["quality"].items():
        assert list(by) == configs
        for r in by.values():
            assert r["frames"] == 3 and r["negative"] == 0 and r["nonfinite"] == 0
            assert r["all"]["log2_psnr"] > 10 and 0 < r["flicker"] < 3
        # the ND pixels measure what the unmodified camera clips
        assert by["off"]["bright"]["log2_psnr"] > by["camera"]["bright"]["log2_psnr"]
    for by in info["fps"].values():
        assert set(by) == {"preview", *configs} - {"camera"}
        for v in by.values():
            assert len(v["ms"]) == 2 and min(v["ms"]) > 0
            assert v["mean"] == pytest.approx(sum(v["ms"]) / 2) and v["steady"] == v["ms"][1]
    if "on" in configs:      # per frame and region, on against off, every clip kind
        rows = info["per_frame"]
        assert {r["clip"] for r in rows} == set(bench.CLIPS) and {r["frame"] for r in rows} == {0, 1, 2}
        assert all(r["delta"] == pytest.approx(r["on"] - r["off"]) for r in rows)
        # the first frame of a clip is a frame alone: the same output
        assert all(r["delta"] == 0 for r in rows if r["frame"] == 0)
    out = capsys.readouterr().out
    assert "| static |" in out and "| cut |" in out and "preview (anchor)" in out
    assert (tmp_path / "results.md").read_text().count("| fast motion |") == 2


def test_budget_sweep_at_a_tiny_size(capsys):
    """benchmarks/temporal_budget.py: one row per configuration; under a budget the shot starts from the
    preview, so its first frame scores the preview's log2 PSNR exactly."""
    sweep = load_benchmark("temporal_budget", "bench_temporal_budget")
    rc = sweep.main(["--size", "64x48", "--frames", "4", "--budgets", "1,0", "--repeat", "1", "--scene", "synthetic"])
    assert rc == 0
    rows = {r.split("|")[1].strip(): [c.strip() for c in r.split("|")[2:-1]]
            for r in capsys.readouterr().out.splitlines() if r.startswith("| ") and not r.startswith("| configuration")}
    assert list(rows) == ["preview", "budget 1", "budget 0"]
    first = {k: v[-1].split(" / ")[0] for k, v in rows.items()}
    assert first["budget 1"] == first["preview"]
    assert all(float(v[0]) > 0 and int(v[3]) >= 0 for v in rows.values())
