"""Crosstalk calibration from flat-field sweeps (nrhdr_core/calibration.py, paper 3.2 / 4).

Truth comes from what we put into the simulated sensor (ND, kernel), never from recorded outputs."""
from __future__ import annotations

import argparse
import csv
import json
import shutil

import numpy as np
import pytest

from nrhdr_core import calibration, crosstalk, io, profile, sensor, validity
from conftest import shared_data

H, W = 64, 64
ND = 6.35
EDGE, CORNER = 0.01, 0.0025


def _sweep(tmp_path_factory, name, model_name, frames=6, nd=ND, seed=0):
    out = tmp_path_factory.mktemp(name)
    prof = profile.default(H, W, seed=seed + 1, nd=nd)
    model = crosstalk.sensor_model_preset(model_name, H, W, seed=seed + 2)
    calibration.simulate_flats(out, prof, model, frames_per_exposure=frames, seed=seed, progress=False)
    return out, prof, model


@pytest.fixture(scope="module")
def linear_sweep(tmp_path_factory):
    return _sweep(tmp_path_factory, "flats_linear", "linear")


@pytest.fixture(scope="module")
def linear_cal(linear_sweep, tmp_path_factory):
    flats, prof, model = linear_sweep
    out = tmp_path_factory.mktemp("cal_linear") / "camera.json"
    summary = calibration.run_calibrate(flats, flats / "mask.png", out, nd_nominal=ND, progress=False)
    return summary, profile.load(out), prof, model


def _clean_capture(prof, model, flux, seed=3):
    return sensor.capture(flux, prof.replace(read_noise=0.0), np.random.default_rng(seed),
                          sensor_model=model, shot_noise=False)


def _rel_err(cal, raw, truth, mode, sel=None):
    v, s = validity.classify(raw, cal)
    crosstalk.correct(v, s, cal, mode=mode)
    k = validity.known_mask(s) & (truth >= 20)
    if sel is not None:
        k &= sel
    return float(np.mean(np.abs(v[k] / truth[k] - 1))), int(k.sum())


# ---- recovery of a known crosstalk ----------------------------------------------------------------------

def test_recovers_nd_and_kernel(linear_cal):
    """Known synthetic crosstalk (uniform 1 % edges, 0.25 % corners, ND 6.35): ND within 1 %, kernel
    terms within 0.15 / 0.1 percentage points."""
    s, cal, prof, _ = linear_cal
    assert s["nd"] == pytest.approx(ND, rel=0.01)
    k = np.array(s["kernel_estimate"])                       # in %
    for dy, dx in crosstalk.DIRS:
        truth = (EDGE if (dy == 0 or dx == 0) else CORNER) * 100
        assert k[1 + dy, 1 + dx] == pytest.approx(truth, abs=0.15 if truth > 0.5 else 0.1)
    assert cal.nd == pytest.approx(s["nd"], rel=1e-3)
    assert cal.crosstalk is not None and cal.crosstalk.shape == (H, W)
    # sensor basics from the photon transfer curve
    assert cal.gain == pytest.approx(prof.gain, rel=0.05)
    assert abs(cal.black_level - prof.black_level) < 1.0
    assert prof.clip_code - 6 <= cal.clip_code <= prof.clip_code


def test_correction_removes_crosstalk_on_flats(linear_cal):
    s, cal, prof, model = linear_cal
    for level in (0.5, 3.0):
        flux = np.full((H, W), level * (prof.clip_code - prof.black_level))
        raw = _clean_capture(prof, model, flux)
        before, n = _rel_err(cal, raw, flux, "off", prof.mask)
        after, n2 = _rel_err(cal, raw, flux, "lut", prof.mask)
        assert n > 100 and n2 > 100
        assert before > 0.05                                    # amplified crosstalk (paper 3.1)
        assert after < 0.01                                     # residual < 1 %


def test_kernel_mode_beats_lut_at_edges(linear_cal):
    """The paper's LUT assumes neighbours as bright as the pixel; at a strong edge the kernel mode uses
    the measured neighbours and leaves a smaller error."""
    s, cal, prof, model = linear_cal
    yy, xx = np.mgrid[0:H, 0:W]
    top = prof.clip_code - prof.black_level
    flux = np.where((xx // 4) % 2 == 0, 0.3 * top, 3.0 * top)          # stripes, 10:1 edges
    raw = _clean_capture(prof, model, flux)
    sel = prof.mask
    off, _ = _rel_err(cal, raw, flux, "off", sel)
    lut, _ = _rel_err(cal, raw, flux, "lut", sel)
    ker, _ = _rel_err(cal, raw, flux, "kernel", sel)
    assert lut < off
    assert ker < 0.6 * lut


def test_summary_has_paper_figures(linear_cal):
    s = linear_cal[0]
    for k in ("nd", "nd_eff_median", "dr_gain_stops_40", "dr_gain_stops_20"):
        assert s[k] is not None
    # Eq. 8: crosstalk lowers the effective ND below the ND; the DR gain at 20 % known exceeds the one at
    # 40 % and neither exceeds log2(ND) by more than the sweep resolution
    assert 1 < s["nd_eff_median"] < s["nd"]
    assert 0 < s["dr_gain_stops_40"] < s["dr_gain_stops_20"] < np.log2(s["nd"]) + 0.2
    for p in s["plots"]:
        assert io.read_image(p, np.uint8).shape[2] >= 3


def test_zero_crosstalk_gives_identity(tmp_path_factory):
    flats, prof, model = _sweep(tmp_path_factory, "flats_none", "none", frames=6)
    out = tmp_path_factory.mktemp("cal_none") / "camera.json"
    s = calibration.run_calibrate(flats, flats / "mask.png", out, plots=False, progress=False)
    cal = profile.load(out)
    assert s["nd"] == pytest.approx(ND, rel=0.01)
    assert np.max(np.abs(np.array(s["kernel_estimate"]))) < 0.1     # < 0.1 %
    assert s["nd_eff_median"] == pytest.approx(s["nd"], rel=0.03)   # no crosstalk: ND_eff = ND
    yy, xx = np.mgrid[0:H, 0:W]
    flux = 10 ** (1.5 + 2.3 * xx / W)
    raw = _clean_capture(prof, None, flux)
    v0, s0 = validity.classify(raw, cal)
    for mode in ("lut", "kernel"):
        v, st = v0.copy(), s0.copy()
        crosstalk.correct(v, st, cal, mode=mode)
        k = validity.known_mask(st)
        assert np.array_equal(k, validity.known_mask(s0))
        assert np.median(np.abs(v[k] / v0[k] - 1)) < 0.005
        assert np.percentile(np.abs(v[k] / v0[k] - 1), 99) < 0.03


def test_prototype_preset_like_the_paper(tmp_path_factory):
    """The prototype-like preset: measured ND close to the truth, ND_eff well below ND (paper 4.1)."""
    flats, prof, model = _sweep(tmp_path_factory, "flats_proto", "prototype", frames=4)
    out = tmp_path_factory.mktemp("cal_proto") / "camera.json"
    s = calibration.run_calibrate(flats, flats / "mask.png", out, nd_nominal=ND, plots=False,
                                  progress=False)
    assert s["nd"] == pytest.approx(ND, rel=0.015)
    assert s["nd_eff_median"] < 0.9 * ND
    assert s["dr_gain_stops_40"] < np.log2(ND)


def test_natural_scene_error_reduced(linear_cal):
    s, cal, prof, model = linear_cal
    lum = io.read_luminance(shared_data("hdr", "Desk.exr")).astype(np.float64)
    f = min(lum.shape[0] // H, lum.shape[1] // W)
    lum = lum[:H * f, :W * f].reshape(H, f, W, f).mean(axis=(1, 3))
    flux = lum * (1.2 * ND * 4094 / np.percentile(lum, 99.5))
    raw = _clean_capture(prof, model, flux)
    off, _ = _rel_err(cal, raw, flux, "off", prof.mask)
    lut, _ = _rel_err(cal, raw, flux, "lut", prof.mask)
    ker, _ = _rel_err(cal, raw, flux, "kernel", prof.mask)
    assert lut < 0.7 * off and ker < 0.5 * off


# ---- CLI ---------------------------------------------------------------------------------------------

def _parser():
    ap = argparse.ArgumentParser()
    sub = ap.add_subparsers(dest="cmd")
    calibration.register_cli(sub)
    return ap


def test_cli_calibrate_json(linear_sweep, tmp_path, capsys):
    flats = linear_sweep[0]
    a = _parser().parse_args(["calibrate", str(flats), "--mask", str(flats / "mask.png"), "-o",
                              str(tmp_path / "cam.json"), "--nd-nominal", "6.35", "--json", "-q", "--no-plots"])
    assert a.func(a) == 0
    s = json.loads(capsys.readouterr().out)
    for k in ("nd", "nd_eff_median", "dr_gain_stops_40", "dr_gain_stops_20"):
        assert k in s
    assert profile.load(tmp_path / "cam.json").crosstalk is not None


def test_cli_simulate_flats(tmp_path):
    a = _parser().parse_args(["simulate-flats", str(tmp_path / "f"), "--width", "16", "--height", "12",
                              "--exposures", "8", "--frames", "2", "--format", "png", "-q"])
    assert a.func(a) == 0
    rows = list(csv.DictReader(open(tmp_path / "f" / "exposures.csv")))
    assert len(rows) == 16 and rows[0]["file"].endswith(".png")
    assert io.read_mask(tmp_path / "f" / "mask.png").shape == (12, 16)


# ---- bad input -----------------------------------------------------------------------------------------

@pytest.fixture
def small_flats(tmp_path):
    prof = profile.default(12, 16, seed=2)
    exp = calibration.default_exposures(10, nd=prof.nd)
    calibration.simulate_flats(tmp_path / "f", prof, None, exposures=exp, frames_per_exposure=2, seed=0,
                               progress=False)
    return tmp_path / "f"


def _cli_error(flats, mask, tmp_path, capsys):
    a = _parser().parse_args(["calibrate", str(flats), "--mask", str(mask), "-o", str(tmp_path / "o.json"),
                              "-q", "--no-plots"])
    rc = a.func(a)
    return rc, capsys.readouterr().err


def test_small_flats_calibrate(small_flats, tmp_path, capsys):
    rc, err = _cli_error(small_flats, small_flats / "mask.png", tmp_path, capsys)
    assert rc == 0, err


def test_error_rows_missing_from_csv(small_flats, tmp_path, capsys):
    lines = (small_flats / "exposures.csv").read_text().splitlines()
    (small_flats / "exposures.csv").write_text("\n".join(lines[:-1]) + "\n")
    with pytest.raises(calibration.CalibrationError, match="not listed"):
        calibration.read_index(small_flats)
    rc, err = _cli_error(small_flats, small_flats / "mask.png", tmp_path, capsys)
    assert rc == 2 and "exposures.csv" in err


def test_error_missing_frame_and_bad_csv(small_flats):
    first = sorted(small_flats.glob("flat_*"))[0]
    first.unlink()
    with pytest.raises(calibration.CalibrationError, match=f"{first.name}.*not found"):
        calibration.read_index(small_flats)
    (small_flats / "exposures.csv").write_text("name,time\nx.tif,1\n")
    with pytest.raises(calibration.CalibrationError, match="file.*exposure_s"):
        calibration.read_index(small_flats)
    (small_flats / "exposures.csv").unlink()
    with pytest.raises(calibration.CalibrationError, match="exposures.csv"):
        calibration.read_index(small_flats)


def test_error_frames_of_different_sizes(small_flats):
    victim = sorted(small_flats.glob("flat_*"))[5]
    io.write_image(victim, np.zeros((10, 16), np.uint16), np.uint16)
    with pytest.raises(calibration.CalibrationError, match=f"{victim.name}.*16x10.*one size"):
        calibration.read_flats(small_flats, progress=False)


def test_error_single_frame_per_exposure(small_flats):
    rows = list(csv.DictReader(open(small_flats / "exposures.csv")))
    keep = {}
    for r in rows:
        keep.setdefault(r["exposure_s"], r)
    with open(small_flats / "exposures.csv", "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["file", "exposure_s"])
        for r in keep.values():
            w.writerow([r["file"], r["exposure_s"]])
    for r in rows:
        if keep[r["exposure_s"]] is not r:
            (small_flats / r["file"]).unlink()
    with pytest.raises(calibration.CalibrationError, match="at least two frames"):
        calibration.read_index(small_flats)


def test_error_saturated_everywhere(tmp_path, capsys):
    prof = profile.default(12, 16, seed=2)
    exp = calibration.default_exposures(10, nd=prof.nd)[1:] * 1e4      # every exposure far beyond clipping
    calibration.simulate_flats(tmp_path / "f", prof, None, exposures=exp, frames_per_exposure=2,
                               progress=False)
    rc, err = _cli_error(tmp_path / "f", tmp_path / "f" / "mask.png", tmp_path, capsys)
    assert rc == 2 and "saturated everywhere" in err


def test_error_never_saturates(tmp_path):
    prof = profile.default(12, 16, seed=2)
    exp = calibration.default_exposures(10, nd=prof.nd) / 100
    calibration.simulate_flats(tmp_path / "f", prof, None, exposures=exp, frames_per_exposure=2,
                               progress=False)
    sweep = calibration.read_flats(tmp_path / "f", progress=False)
    with pytest.raises(calibration.CalibrationError, match="does not reach saturation"):
        calibration.calibrate(sweep, prof.mask, progress=False)


def test_error_mask_wrong_size(small_flats, tmp_path, capsys):
    io.write_mask(tmp_path / "m.png", np.zeros((12, 15), bool) | (np.arange(15) % 2 == 0))
    rc, err = _cli_error(small_flats, tmp_path / "m.png", tmp_path, capsys)
    assert rc == 2 and "m.png" in err and "15x12" in err and "16x12" in err


def test_error_mask_missing(small_flats, tmp_path, capsys):
    rc, err = _cli_error(small_flats, tmp_path / "nope.png", tmp_path, capsys)
    assert rc == 2 and "nope.png" in err


def test_defective_pixels_become_uncalibrated(tmp_path):
    """A dead pixel (always 0) and a stuck one (always at the clip code) get no calibration: their codes are
    UNCALIBRATED (missing), never mapped to a made-up flux."""
    prof = profile.default(24, 32, seed=4)
    flats = tmp_path / "f"
    calibration.simulate_flats(flats, prof, None, exposures=calibration.default_exposures(20, nd=prof.nd),
                               frames_per_exposure=2, progress=False)
    dead, stuck = (5, 7), (10, 20)
    for f in flats.glob("flat_*.tif"):
        a = io.read_image(f, np.uint16)[:, :, 0].copy()
        a[dead] = 0
        a[stuck] = 4095
        io.write_image(f, a, np.uint16)
    s = calibration.run_calibrate(flats, flats / "mask.png", tmp_path / "c.json", plots=False, progress=False)
    assert s["defective_pixels"] >= 1 and s["nd"] == pytest.approx(prof.nd, rel=0.02)
    cal = profile.load(tmp_path / "c.json")
    v = np.full((24, 32), 50.0, np.float32) * np.where(prof.mask, prof.nd, 1.0).astype(np.float32)
    st = np.where(prof.mask, validity.ATTENUATED, 0).astype(np.uint8)
    crosstalk.correct(v, st, cal, mode="lut")
    for y, x in (dead, stuck):
        assert st[y, x] & validity.REASON_MASK == validity.UNCALIBRATED
    assert np.mean((st & validity.REASON_MASK) == validity.VALID) > 0.95


def test_linear_sweep_without_dark_frame(tmp_path):
    """A user's sweep may be linearly spaced, start above zero exposure and have a black level: ND and the
    correction still come out right (one usable exposure for the regular pixels is enough)."""
    prof = profile.default(H, W, seed=6, black_level=64.0)
    model = crosstalk.sensor_model_preset("linear", H, W)
    exp = np.linspace(0.001, 0.01 * ND * 1.6, 20)                  # regular pixels saturate at 0.01 s
    calibration.simulate_flats(tmp_path / "f", prof, model, exposures=exp, frames_per_exposure=4,
                               progress=False)
    s = calibration.run_calibrate(tmp_path / "f", tmp_path / "f" / "mask.png", tmp_path / "c.json",
                                  plots=False, progress=False)
    assert s["nd"] == pytest.approx(ND, rel=0.01)
    assert s["black_level"] == pytest.approx(64.0, abs=1.5)
    cal = profile.load(tmp_path / "c.json")
    flux = np.full((H, W), 2.0 * (prof.clip_code - prof.black_level))
    raw = _clean_capture(prof, model, flux)
    before, _ = _rel_err(cal, raw, flux, "off", prof.mask)
    after, n = _rel_err(cal, raw, flux, "lut", prof.mask)
    assert n > 100 and before > 0.05 and after < 0.015


def test_effective_nd_matches_the_known_kernel(linear_cal):
    """Eq. 8 per pixel against the truth of the known linear kernel: an attenuated pixel reads
    F * [(1 - sum K) / ND + sum_d K_d t_d] (t_d = 1 for a regular neighbour, 1/ND for an attenuated one), so
    it clips at ND_eff = 1 / [...] (in units of DN_max)."""
    s, cal, prof, model = linear_cal
    k = model.kernel
    mask = prof.mask
    resp = np.full(mask.shape, (1 - k.sum()) / ND)
    for dy, dx in crosstalk.DIRS:
        nb = crosstalk._shift(mask.astype(float), int(dy), int(dx))          # 1 where the source is attenuated
        resp += k[1 + dy, 1 + dx] * np.where(nb > 0, 1.0 / ND, 1.0)
    inner = np.zeros(mask.shape, bool)
    inner[1:-1, 1:-1] = True
    sel = mask & inner
    top = cal.crosstalk.clip_code - cal.crosstalk.black_level
    est = cal.crosstalk.clip_flux[sel] / top
    truth = 1.0 / resp[sel]
    rel = np.abs(est / truth - 1)
    assert np.median(rel) < 0.01 and np.percentile(rel, 95) < 0.04
    assert s["nd_eff_median"] == pytest.approx(float(np.median(truth)), rel=0.02)
