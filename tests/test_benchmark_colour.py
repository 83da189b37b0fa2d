"""benchmarks/colour.py: its ND layouts, and a `--quick` run at a tiny size on a shared HDR scene and a Kodak image
(every camera, both scene kinds where the shared data is present, the zone plate, frames/s with the `--ceiling` chains,
the goals table)."""
import json

import numpy as np
import pytest
from conftest import load_benchmark, shared_data


@pytest.fixture(scope="module")
def bench():
    return load_benchmark("colour", "bench_colour")


def test_cameras_layouts_over_the_cfa(bench):
    h, w = 16, 24
    for c in bench.ND_CAMERAS:
        m = bench.nd_mask(c, h, w)
        assert m.shape == (h, w) and m.dtype == bool and abs(m.mean() - 0.5) < 0.1
    bal = bench.nd_mask("nr-balanced", h, w)
    sve = bench.nd_mask("sve", h, w)
    for dy, dx in ((0, 0), (0, 1), (1, 0), (1, 1)):   # each photosite of the 2 x 2 Bayer block
        assert bal[dy::2, dx::2].sum() == h * w // 8   # balanced: half of it attenuated
        plane = sve[dy::2, dx::2]                      # SVE: a checkerboard of exposures
        assert (plane[:, 1:] != plane[:, :-1]).all() and (plane[1:] != plane[:-1]).all()
    assert not bench.nd_mask("bayer", h, w).any()
    assert all(p.cfa == "rggb" for p in bench.cameras(h, w).values())


def test_regular_photosites_share_the_unmodified_cameras_codes(bench):
    profs = bench.cameras(8, 12)
    truth = np.full((3, 8, 12), 1000.0, np.float32)
    raws = bench.capture_all(truth, profs, seed=5)
    for c in bench.ND_CAMERAS:
        m = profs[c].mask
        np.testing.assert_array_equal(raws[c][~m], raws["bayer"][~m])
        assert raws[c][m].mean() < raws["bayer"][m].mean() / 3        # attenuated by ND 6.35


def test_quick_run_at_a_tiny_size(bench, tmp_path, capsys):
    hdr, kodak = shared_data("hdr", "Desk.exr"), shared_data("kodak", "kodim01.png")
    rc = bench.main(["--quick", "--scenes", str(hdr), "--kodak", str(kodak), "--size", "48x32",
                     "--zone-size", "24", "--fps-size", "64x48", "--fps-frames", "1", "--repeat", "1",
                     "--ceiling", "--out", str(tmp_path)])
    assert rc == 0
    info = json.loads((tmp_path / "results.json").read_text())
    q = info["quality"]["preview"]
    assert set(q) == {"hdr", "kodak"}
    for kind in q.values():
        assert list(kind) == list(bench.CAMERAS)
        for r in kind.values():
            assert r["report"]["negative"] == 0 and r["report"]["nonfinite"] == 0
            assert r["report"]["all"]["log2_psnr"] > 10 and 0 <= r["de00"] < 50
    # the ND photosites measure what the unmodified camera clips
    hdr_q = q["hdr"]
    for c in bench.ND_CAMERAS:
        assert hdr_q[c]["report"]["bright"]["log2_psnr"] > hdr_q["bayer"]["report"]["bright"]["log2_psnr"]
    z = info["zone_plate"]["preview"]
    assert all(np.isfinite(z[c]["all"]) for c in bench.CAMERAS)
    assert list(info["fps"]) == ["mono", "colour", *bench.CEILING]
    for k in info["fps"]:
        assert info["fps"][k]["fps"] > 0 and set(info["fps"][k]["ms"]) == set(bench.SPEED_STAGES)
    assert info["fps"]["colour-no-crosstalk-median-bounds"]["ms"]["crosstalk"] == 0      # the stage left out
    goals = [g["goal"] for g in info["goals"]]
    assert any("+12 dB" in g for g in goals) and any("3 dB below SVE" in g for g in goals)
    assert any("70 %" in g for g in goals)
    out = capsys.readouterr().out
    assert "anchor: unmodified Bayer camera" in out and "| goal | measured | met |" in out
