"""`nrhdr compare` and `metrics.clip_report` (the chain's EXR frames against the simulator's
truth, per region, beside an unmodified camera): figures against errors built by hand, and clear errors."""
import json

import numpy as np
import pytest

from gst_plugins import cli
from nrhdr_core import io, metrics, profile


def _truth(h=24, w=32):
    """Three bands: dark (below l_min x ND = 635), mid, bright (at or above the regular clip 4094)."""
    t = np.empty((h, w), np.float32)
    t[:, : w // 3] = 100.0
    t[:, w // 3: 2 * w // 3] = 2000.0
    t[:, 2 * w // 3:] = 10000.0
    return t


def test_clip_report_one_stop_off_in_the_dark():
    prof = profile.default(24, 32)
    t = _truth()
    o = t.copy()
    o[:, :10] *= 2.0                       # every dark pixel exactly one stop high
    o[:, 10:] *= np.float32(1.01)          # the rest slightly off
    r = metrics.clip_report([(t, o), (t, o)], prof.l_min * prof.nd, prof.regular_white, prof.white)
    peak = np.log2(prof.white)
    assert r["frames"] == 2 and r["negative"] == 0 and r["nonfinite"] == 0
    assert r["dark"]["pixels"] == 2 * 24 * 10
    assert r["dark"]["log2_psnr"] == pytest.approx(20 * np.log10(peak / 1.0), abs=1e-9)
    assert r["mid"]["log2_psnr"] == pytest.approx(20 * np.log10(peak / np.log2(1.01)), abs=1e-3)
    assert r["dark"]["off_1stop"] == 0 and r["all"]["off_3stops"] == 0   # exactly 1 stop is not "more than"
    # PU21 from its own encoding: the dark region's error is that of the encoded values
    assert r["dark"]["pu21_psnr"] == pytest.approx(metrics.pu21_psnr(t[:, :10], o[:, :10], white=prof.white))


def test_clip_report_counts_negative_and_nonfinite_before_the_cap():
    prof = profile.default(24, 32)
    t = _truth()
    o = t.copy()
    o[0, 0] = -5.0
    o[1, 1] = np.nan
    o[2, 2] = np.inf
    r = metrics.clip_report([(t, o)], prof.l_min * prof.nd, prof.regular_white, prof.white)
    assert (r["negative"], r["nonfinite"]) == (1, 2)


def _folder(d, frames):
    d.mkdir()
    for i, f in enumerate(frames):
        io.write_exr(d / f"frame_{i:05d}.exr", f)
    return d


def test_compare_command_matches_the_report(tmp_path, capsys):
    prof = profile.default(24, 32)
    profile.save(prof, tmp_path / "camera.json")
    t = [_truth(), _truth() * np.float32(0.5)]
    nd = [x * np.float32(1.1) for x in t]
    cam = [np.minimum(x, np.float32(4094.0)) for x in t]      # an unmodified camera clips at the regular white
    _folder(tmp_path / "truth", t)
    _folder(tmp_path / "nd", nd)
    _folder(tmp_path / "cam", cam)
    rc = cli.main(["compare", str(tmp_path / "nd"), str(tmp_path / "cam"), "--truth", str(tmp_path / "truth"),
                   "--profile", str(tmp_path / "camera.json"), "--json"])
    assert rc == 0
    got = json.loads(capsys.readouterr().out)["results"]
    lv = (prof.l_min * prof.nd, prof.regular_white, prof.white)
    for name, frames in (("nd", nd), ("cam", cam)):
        want = metrics.clip_report(list(zip(t, frames)), *lv)
        g = got[str(tmp_path / name)]
        assert {k: g[k] for k in ("frames", "negative", "nonfinite")} == {k: want[k] for k in ("frames", "negative", "nonfinite")}
        for k in metrics.REGIONS:
            assert g[k] == pytest.approx(want[k])
    # the camera loses the bright band (clipped), the ND camera does not
    assert got[str(tmp_path / "cam")]["bright"]["log2_psnr"] < got[str(tmp_path / "nd")]["bright"]["log2_psnr"] - 10
    # the table form runs too
    assert cli.main(["compare", str(tmp_path / "nd"), "--truth", str(tmp_path / "truth"),
                     "--profile", str(tmp_path / "camera.json")]) == 0
    assert "| 2 | 0 / 0 |" in capsys.readouterr().out


def test_compare_names_a_missing_truth_frame(tmp_path, capsys):
    prof = profile.default(24, 32)
    profile.save(prof, tmp_path / "camera.json")
    _folder(tmp_path / "truth", [_truth()])
    _folder(tmp_path / "out", [_truth(), _truth()])
    rc = cli.main(["compare", str(tmp_path / "out"), "--truth", str(tmp_path / "truth"),
                   "--profile", str(tmp_path / "camera.json")])
    err = capsys.readouterr().err
    assert rc == 2 and "frame_00001.exr" in err and "no truth frame" in err
    rc = cli.main(["compare", str(tmp_path / "nowhere"), "--truth", str(tmp_path / "truth"),
                   "--profile", str(tmp_path / "camera.json")])
    assert rc == 2 and "not a folder" in capsys.readouterr().err


def test_simulate_pattern_none_is_an_unmodified_camera(tmp_path):
    assert cli.main(["profile", "-o", str(tmp_path / "cam.json"), "--pattern", "none", "--width", "16",
                     "--height", "8"]) == 0
    p = profile.load(tmp_path / "cam.json")
    assert p.mask.shape == (8, 16) and not p.mask.any() and p.nd == pytest.approx(6.35)
