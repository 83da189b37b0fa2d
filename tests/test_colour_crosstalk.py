"""Crosstalk per colour neighbourhood and mask detection on a Bayer sensor (docs/COLOUR.md "Validity and
crosstalk per colour"; nrhdr_core/calibration.py `colour_spill`, crosstalk.correct on colour profiles,
flats.detect with a CFA).

The flats come from a small generator written here, independent of the project's simulator: a 12-bit Bayer
sensor (its own CFA layout below) with per-channel sensitivity, coloured light, test_flats' conserving 3 x 3
crosstalk kernel with a coupling that may depend on the source photosite's colour, Poisson shot noise and Gaussian read noise;
frames written as 16-bit TIFF with `exposures.csv`."""
from __future__ import annotations

import csv
import dataclasses
import json
from pathlib import Path

import numpy as np
import pytest
import tifffile

from nrhdr_core import calibration, crosstalk, flats, io, mask as masks, profile, validity
from test_flats import crosstalk_3x3

GAIN = 0.5            # DN per electron
FULL_WELL = 9000.0    # electrons: the 12-bit ADC clips (4095) first
BLACK = 64.0
CLIP = 4095
ND = 6.0
RATE = (CLIP - BLACK) / GAIN / 0.01          # electrons/s of a regular photosite in white light (10 ms to clip)


def channels(cfa, h, w):
    """Channel (0 R, 1 G, 2 B) of each photosite: the pattern names its 2 x 2 block row by row."""
    idx = {"r": 0, "g": 1, "b": 2}
    out = np.empty((h, w), np.intp)
    for k, ch in enumerate(cfa):
        out[k // 2::2, k % 2::2] = idx[ch]
    return out


def coloured_crosstalk(e, chan, edge, corner, coupling):
    """test_flats' conserving 3 x 3 crosstalk with a coupling per source colour: a photosite of colour c
    sends coupling[c] x `edge` (`corner`) of its electrons to each edge (corner) neighbour (linear in the
    sent charge: e + crosstalk_3x3(s) - s with s = coupling x e)."""
    sent = e * np.asarray(coupling, float)[chan]
    return e + crosstalk_3x3(sent, edge, corner) - sent


@dataclasses.dataclass
class Sensor:
    mask: np.ndarray
    cfa: str = "rggb"
    sens: tuple = (1.0, 1.0, 1.0)
    coupling: tuple = (1.0, 1.0, 1.0)
    edge: float = 0.01
    corner: float = 0.0025
    read_noise: float = 3.0

    def electrons(self, flux_e):
        """Mean electrons after the ND filters and the crosstalk for photon flux `flux_e` (H, W) electrons."""
        chan = channels(self.cfa, *self.mask.shape)
        e = flux_e * np.asarray(self.sens, float)[chan] / np.where(self.mask, ND, 1.0)
        return coloured_crosstalk(e, chan, self.edge, self.corner, self.coupling)

    def frame(self, flux_e, rng=None):
        e = self.electrons(flux_e)
        if rng is None:
            code = np.minimum(e, FULL_WELL) * GAIN + BLACK
        else:
            n = np.minimum(rng.poisson(np.maximum(e, 0)).astype(np.float64), FULL_WELL)
            code = (n + self.read_noise * rng.standard_normal(e.shape)) * GAIN + BLACK
        return np.clip(np.rint(code), 0, CLIP).astype(np.uint16)

    def sweep(self, folder: Path, light=(1.0, 1.0, 1.0), seed=0, frames=2, n_lo=10, n_hi=14, over=2.5):
        """Dark, n_lo geometric steps up to the brightest channel's saturation, n_hi up to `over` x ND x
        the dimmest channel's (every photosite clipped at the end)."""
        rng = np.random.default_rng(seed)
        h, w = self.mask.shape
        chan = channels(self.cfa, h, w)
        eff = np.asarray(light, float) * np.asarray(self.sens, float)
        t_sat = 0.01 / eff.max()
        t = np.concatenate([[0.0], np.geomspace(2e-3 * t_sat, 0.8 * t_sat, n_lo),
                            np.geomspace(1.1 * t_sat, 0.01 / eff.min() * over * ND, n_hi)])
        folder.mkdir(parents=True, exist_ok=True)
        rows = []
        for i, ti in enumerate(t):
            for j in range(frames):
                name = f"f{i:03d}_{j}.tif"
                tifffile.imwrite(folder / name, self.frame(RATE * ti * np.asarray(light, float)[chan], rng))
                rows.append((name, repr(float(ti))))
        with open(folder / "exposures.csv", "w", newline="") as f:
            wr = csv.writer(f)
            wr.writerow(["file", "exposure_s"])
            wr.writerows(rows)
        return folder


LIGHTS = {"red": (1.0, 0.2, 0.1), "green": (0.2, 1.0, 0.2), "blue": (0.1, 0.2, 1.0)}


def calibrated(tmp: Path, sensor: Sensor):
    """(white-light profile, per-colour profile) of `sensor` calibrated from the generator's sweeps."""
    sw = calibration.read_flats(sensor.sweep(tmp / "white", seed=1), progress=False)
    res = calibration.calibrate(sw, sensor.mask, progress=False, cfa=sensor.cfa)
    white = res.profile
    sweeps = [calibration.read_flats(sensor.sweep(tmp / k, light=v, seed=2 + i), progress=False)
              for i, (k, v) in enumerate(LIGHTS.items())]
    cs = calibration.colour_spill(white, sweeps)
    col = dataclasses.replace(white, crosstalk=dataclasses.replace(white.crosstalk, colour=cs.colour))
    return white, col, cs, tmp


def flat_error(prof, sensor, light, level, mode, lut="full"):
    """Mean relative error (%) per channel of the attenuated photosites of a noise-free coloured flat
    (`level`: a white regular photosite's code above black) after `crosstalk.correct`, interior only."""
    h, w = sensor.mask.shape
    chan = channels(sensor.cfa, h, w)
    truth = level * np.asarray(light, float)[chan]              # DN a regular photosite reads without crosstalk
    raw = sensor.frame(truth / GAIN)
    v, s = validity.classify(raw, prof, "threshold", l_min=0)
    crosstalk.correct(v, s, prof, mode, lut=lut)
    ok = ((s & validity.REASON_MASK) == validity.VALID) & sensor.mask & (truth >= 20)
    ok[:2] = ok[-2:] = False
    ok[:, :2] = ok[:, -2:] = False
    r = (v - truth) / truth
    return np.array([100 * float(np.mean(r[ok & (chan == c)])) for c in range(3)])


@pytest.fixture(scope="module")
def colour_blind(tmp_path_factory):
    """A sensor whose crosstalk does not depend on colour, calibrated under white and coloured light."""
    sensor = Sensor(masks.nonregular_mask(48, 48, seed=3))
    return (sensor,) + calibrated(tmp_path_factory.mktemp("blind"), sensor)


@pytest.fixture(scope="module")
def colour_coupled(tmp_path_factory):
    """A sensor whose red photosites spill 40 % more and blue ones 25 % less than green ones."""
    sensor = Sensor(masks.nonregular_mask(48, 48, seed=4), coupling=(1.4, 1.0, 0.75))
    return (sensor,) + calibrated(tmp_path_factory.mktemp("coupled"), sensor)


@pytest.mark.parametrize("light", ["red", "blue"])
def test_white_light_lut_is_biased_under_coloured_light_and_the_colour_calibration_removes_it(colour_blind,
                                                                                           light):
    sensor, white, col, _, _ = colour_blind
    L = LIGHTS[light]
    for level in (1200.0, 3000.0, 6000.0):
        e_white = flat_error(white, sensor, L, level, "lut")
        e_col = flat_error(col, sensor, L, level, "lut")
        # the dim channels' attenuated photosites next to bright ones read far too much with the white LUT
        assert np.max(np.abs(e_white)) > 15, e_white
        # the per-colour calibration: a few % at most (the faintest channel, whose signal is mostly the
        # bright neighbours' corner spill), 8x less overall
        assert np.max(np.abs(e_col)) < 6.5, e_col
        assert np.mean(np.abs(e_col)) < np.mean(np.abs(e_white)) / 8, (e_white, e_col)
    # white light: both calibrations agree (within the flats' noise)
    assert np.max(np.abs(flat_error(col, sensor, (1, 1, 1), 1200.0, "lut"))) < 1.0


def test_colour_dependent_coupling_needs_the_colour_calibration_in_kernel_mode(colour_coupled):
    """kernel mode uses the neighbours' values, but with the white calibration's coupling (an average over
    the source colours) it is biased where red neighbours spill more; the per-colour factors fix most of it."""
    sensor, white, col, cs, _ = colour_coupled
    e_white = flat_error(white, sensor, LIGHTS["red"], 1200.0, "kernel")
    e_col = flat_error(col, sensor, LIGHTS["red"], 1200.0, "kernel")
    assert e_white[1] > 5, e_white                      # green photosites next to red ones
    assert abs(e_col[1]) < 0.5 * e_white[1] and np.max(np.abs(e_col)) < 5, (e_white, e_col)
    f = cs.summary()["factor"]
    assert f["G(0,1)<-R"] > f["G(0,1)<-B"] and f["G(1,0)<-R"] > f["G(1,0)<-B"]


def test_colour_calibration_round_trips_and_monochrome_is_unchanged(colour_blind, tmp_path):
    sensor, white, col, _, _ = colour_blind
    path = tmp_path / "cam.json"
    profile.save(col, path)
    back = profile.load(path)
    assert back.cfa == "rggb" and np.allclose(back.crosstalk.colour, col.crosstalk.colour)
    # the same calibration on a monochrome profile ignores the colour amplitudes
    mono = dataclasses.replace(col, cfa="none")
    plain = dataclasses.replace(white, cfa="none")
    raw = sensor.frame(np.full(sensor.mask.shape, 1500.0 / GAIN))
    outs = []
    for p in (mono, plain):
        v, s = validity.classify(raw, p, "threshold")
        crosstalk.correct(v, s, p, "kernel")
        outs.append((v, s))
    assert np.array_equal(outs[0][0], outs[1][0]) and np.array_equal(outs[0][1], outs[1][1])


def test_mask_found_within_colour_planes(tmp_path):
    """Channels of different sensitivity under white light: a regular blue photosite reads about what an
    attenuated green one does, so comparing across colours confuses them; within each CFA class the mask
    is recovered exactly and the ND within 2 %."""
    mask = masks.nonregular_mask(48, 48, seed=7)
    sensor = Sensor(mask, sens=(0.5, 1.0, 0.3), edge=0.005, corner=0.001)
    sw = calibration.read_flats(sensor.sweep(tmp_path / "white", seed=5, frames=4, n_lo=12), progress=False)
    det = flats.detect(sw, cfa="rggb")
    assert np.array_equal(det.mask, mask) and det.confident
    assert abs(det.nd / ND - 1) < 0.02
    mono = flats.detect(sw)
    assert (mono.mask != mask).sum() > 50                # across colours the populations mix


def test_simulated_coloured_flats_follow_the_cfa(tmp_path):
    """simulate_flats(light=...): flux of a photosite = the light's channel of its CFA colour x exposure."""
    prof = profile.default(8, 8, cfa="grbg")
    prof = dataclasses.replace(prof, read_noise=0.0)
    calibration.simulate_flats(tmp_path / "f", prof, None, exposures=[0.0, 0.002, 0.004], frames_per_exposure=2,
                               progress=False, light=(0.5, 1.0, 0.25))
    sw = calibration.read_flats(tmp_path / "f", progress=False)
    chan = channels("grbg", 8, 8)
    sig = (sw.mean[2] - prof.black_level) * np.where(prof.mask, prof.nd, 1.0)
    want = (prof.clip_code - prof.black_level) / 0.01 * 0.004 * np.array([0.5, 1.0, 0.25])[chan]
    assert np.allclose(sig, want, rtol=0.15, atol=prof.nd * 2)
    for bad in ((1, 2), (1, -1, 1), (0, 0, 0)):
        with pytest.raises(ValueError, match="light"):
            calibration.simulate_flats(tmp_path / "g", prof, None, exposures=[0.0, 0.01], light=bad, progress=False)
    with pytest.raises(ValueError, match="colour profile"):
        calibration.simulate_flats(tmp_path / "h", profile.default(8, 8), None, exposures=[0.0, 0.01],
                                   light=(1, 0.5, 0.5), progress=False)


def test_cli_calibrates_per_colour(colour_coupled, tmp_path, capsys):
    """`nrhdr calibrate --cfa rggb --colour-flats ...`: the profile has the CFA and the per-colour amplitudes
    (the factors of `colour_spill`), the summary the factors and the bias on each coloured sweep with either
    calibration; colour flats without --cfa are refused."""
    from gst_plugins import cli
    sensor, _, _, cs, tmp = colour_coupled
    io.write_mask(tmp / "mask.png", sensor.mask)
    args = ["calibrate", str(tmp / "white"), "--mask", str(tmp / "mask.png"), "-o", str(tmp_path / "cam.json"),
            "--json", "-q", "--no-plots", "--colour-flats"] + [str(tmp / k) for k in LIGHTS]
    a = cli.build_parser().parse_args(args + ["--cfa", "rggb"])
    assert a.func(a) == 0
    s = json.loads(capsys.readouterr().out)
    assert s["colour"]["factor"] == cs.summary()["factor"]
    check = s["colour"]["check"]                          # the bias on the coloured flats themselves
    assert set(check) == set(LIGHTS)
    for r in check.values():
        assert max(map(abs, r["white"])) > 10 and max(map(abs, r["colour"])) < 0.5 * max(map(abs, r["white"]))
    p = profile.load(tmp_path / "cam.json")
    assert p.cfa == "rggb" and p.crosstalk.colour.shape == (3,) + sensor.mask.shape
    a = cli.build_parser().parse_args(args[:5] + [str(tmp_path / "c2.json")] + args[6:])
    assert a.func(a) == 2
    assert "--cfa" in capsys.readouterr().err


@pytest.mark.parametrize("light", ["red", "green", "blue"])
def test_colour_compact_removes_most_of_the_white_lut_bias(colour_coupled, light):
    """mode lut, lut compact on a per-colour calibration (the fast setting: one pass, neighbour fluxes from
    the compact LUT): under coloured light it removes most of the white-light LUT's bias, within a few
    points of the full table's two-pass correction."""
    sensor, white, col, _, _ = colour_coupled
    L = LIGHTS[light]
    for level in (1200.0, 3000.0):
        e_white = flat_error(white, sensor, L, level, "lut", "compact")
        e_fast = flat_error(col, sensor, L, level, "lut", "compact")
        e_full = flat_error(col, sensor, L, level, "lut", "full")
        assert np.max(np.abs(e_white)) > 25, e_white
        assert np.max(np.abs(e_fast)) < 11, (e_fast, e_full)
        assert np.mean(np.abs(e_fast)) < np.mean(np.abs(e_white)) / 4, (e_white, e_fast)
        assert np.max(np.abs(e_fast - e_full)) < 8, (e_fast, e_full)


def test_colour_compact_equals_the_full_table_under_grey_light(colour_coupled):
    """Grey light: no other-colour spill difference to remove, so the fast setting is the compact LUT: it
    differs from the full path by what the compact LUT differs from the full table (its resampling error,
    docs/CROSSTALK.md "Compact LUT"), measured here on the calibration without its per-colour amplitudes,
    and from that compact LUT by a fraction of a per cent."""
    sensor, white, col, _, _ = colour_coupled
    h, w = sensor.mask.shape
    for level in (300.0, 1500.0, 3500.0):
        raw = sensor.frame(np.full((h, w), level / GAIN))
        out = {}
        for name, p in (("colour", col), ("white", white)):
            for lut in ("full", "compact"):
                v, s = validity.classify(raw, p, "threshold", l_min=0)
                crosstalk.correct(v, s, p, "lut", lut=lut)
                out[name, lut] = (v, s)
        sf = out["colour", "full"][1]
        assert all(np.array_equal(sf, o[1]) for o in out.values())
        ok = (sf & validity.REASON_MASK) == validity.VALID

        def rel(a, b):
            return np.abs(out[a][0] - out[b][0])[ok] / out[b][0][ok]
        fast, compact = rel(("colour", "compact"), ("colour", "full")), rel(("white", "compact"), ("white", "full"))
        p99 = np.percentile(fast, 99), np.percentile(compact, 99)
        between = rel(("colour", "compact"), ("white", "compact"))
        assert np.median(fast) < np.median(compact) + 5e-4 and p99[0] < p99[1] + 0.01, \
            (level, np.median(fast), np.median(compact), p99)
        assert np.median(between) < 1e-3 and np.percentile(between, 99) < 0.02, \
            (level, np.median(between), np.percentile(between, 99))


def test_colour_compact_handles_states_as_the_full_path(colour_coupled):
    """CLIPPED pixels keep their state with their bound lowered to the calibrated clip flux, DARK bounds
    are mapped through the compact LUT (as the monochrome compact setting maps them), pixels without a
    calibrated range become UNCALIBRATED (value as measured): the same states and clipped values as the
    full path."""
    sensor, _, col, _, _ = colour_coupled
    h, w = sensor.mask.shape
    cal = col.crosstalk
    nk = cal.n_knots.copy()
    nk[10:14, 20:24] = 1                                   # no calibrated range
    prof = dataclasses.replace(col, crosstalk=dataclasses.replace(cal, n_knots=nk))
    plain = dataclasses.replace(col, crosstalk=dataclasses.replace(cal, n_knots=nk, colour=None))
    flux = np.full((h, w), 2000.0)
    flux[:, :12] = 40.0 * ND                             # attenuated photosites below l_min: DARK
    flux[30:, 30:] = 20 * (CLIP - BLACK)                 # every photosite clipped
    raw = sensor.frame(flux / GAIN * np.asarray(LIGHTS["red"], float)[channels(sensor.cfa, h, w)])
    v_in, _ = validity.classify(raw, prof, "threshold", l_min=30)
    out = {}
    for name, p, lut in (("full", prof, "full"), ("fast", prof, "compact"), ("plain", plain, "compact")):
        v, s = validity.classify(raw, p, "threshold", l_min=30)
        crosstalk.correct(v, s, p, "lut", lut=lut)
        out[name] = (v, s)
    (vf, sf), (vc, sc), (vp, sp) = out["full"], out["fast"], out["plain"]
    reason = sf & validity.REASON_MASK
    for st in (validity.CLIPPED, validity.DARK, validity.UNCALIBRATED, validity.VALID):
        assert np.any(reason == st), st
    assert np.array_equal(sf, sc) and np.array_equal(sc, sp)
    clipped = reason == validity.CLIPPED
    assert np.array_equal(vf[clipped], vc[clipped]) and np.all(vc[clipped] <= v_in[clipped])
    unc = reason == validity.UNCALIBRATED
    assert np.array_equal(vc[unc], v_in[unc])
    dark = reason == validity.DARK
    assert np.allclose(vc[dark], vp[dark], rtol=1e-6) and np.allclose(vc[dark], vf[dark], rtol=0.05)


def test_identity_colour_calibration_is_the_identity_in_every_colour_setting():
    """`identity_calibration(colour=True)` (what a colour warm-up needs to reach the colour kernels): no
    crosstalk, so every setting returns the measured values."""
    prof = profile.default(12, 16, cfa="rggb")
    prof = prof.replace(crosstalk=crosstalk.identity_calibration(prof.mask, nd=prof.nd, black_level=prof.black_level,
                                                                 clip_code=prof.clip_code, colour=True))
    raw = np.clip(prof.black_level + np.geomspace(5, 3000, 12 * 16).reshape(12, 16), 0, prof.clip_code).astype(np.uint16)
    for mode, lut in (("lut", "compact"), ("lut", "full"), ("kernel", "full")):
        v, s = validity.classify(raw, prof, "threshold", l_min=0)
        v0 = v.copy()
        crosstalk.correct(v, s, prof, mode, lut=lut)
        ok = (s & validity.REASON_MASK) == validity.VALID
        assert ok.sum() > 100 and np.allclose(v[ok], v0[ok], rtol=1e-3, atol=0.05), (mode, lut)


def test_colour_compact_first_order_step_matches_the_compact_lut_at_the_corrected_code():
    """The fast setting takes the compact LUT at the corrected code m - delta to first order (its flux and
    slope at m, docs/CROSSTALK.md section 4b). On a hand-made calibration with a curved code-to-flux table
    and a linear spill table (sigma_d(e) = k_d e), under coloured light (red photosites 3 x as bright as
    the others), delta is computed here from the definition: the pixel's amplitude for each other-colour
    neighbour times k_d (neighbour signal - signal of a flat neighbour at the pixel's flux), neighbour
    fluxes from the compact LUT; the compact LUT at m - delta (the monochrome compact setting on the codes
    m - delta) is the reference, and the step is within the compact LUT's own error (against the full
    table) there. Every VALID pixel of the 16 x 16 frame, borders included."""
    h, w, nd = 16, 16, 6.0
    prof = profile.default(h, w, cfa="rggb", seed=2).replace(nd=nd)
    att = prof.mask
    s = np.where(att, nd, 1.0)
    kk = 12
    knot_flux = np.linspace(0.0, 4000.0 * nd, kk)
    frac = knot_flux / knot_flux[-1]
    codes = (knot_flux[None, None, :] / s[:, :, None]) * (1.0 - 0.08 * frac[None, None, :] ** 2) + 3.0
    codes[:, :, 0] = 3.0
    q, qs, qo = crosstalk.quantize_codes(codes, int(prof.clip_code) + 1)
    k_d = np.array([0.003, 0.012, 0.003, 0.010, 0.010, 0.003, 0.012, 0.003])    # DIRS order
    rng = np.random.default_rng(5)
    colour = rng.uniform(0.8, 1.3, (3, h, w)).astype(np.float32)
    white = crosstalk.CrosstalkCalibration(
        codes_q=q, qscale=qs, qoffset=qo, n_knots=np.full((h, w), kk, np.int32), knot_flux=knot_flux,
        clip_flux=np.full((h, w), np.nan, np.float32), nd=nd, black_level=float(prof.black_level),
        clip_code=int(prof.clip_code), sig_e=np.array([0.0, 1e5], np.float32),
        sigma=np.ascontiguousarray((k_d[:, None] * np.array([0.0, 1e5])).astype(np.float32)),
        alpha=np.ones((h, w), np.float32))
    mono = prof.replace(crosstalk=white)
    col = prof.replace(crosstalk=dataclasses.replace(white, colour=colour))
    chan = channels("rggb", h, w)
    m = np.where(chan == 0, 1500.0, 500.0) / s * rng.uniform(0.9, 1.1, (h, w))      # codes above black
    state0 = np.where(att, validity.ATTENUATED, validity.VALID).astype(np.uint8)

    def compact(codes_, lut="compact"):
        v, st = (codes_ * s).astype(np.float32), state0.copy()
        crosstalk.correct(v, st, mono, "lut", lut=lut)
        assert np.all((st & validity.REASON_MASK) == validity.VALID)
        return v.astype(np.float64)

    f = compact(m)
    delta = np.zeros((h, w))
    for d, (dy, dx) in enumerate(crosstalk.DIRS):
        for y in range(h):
            for x in range(w):
                yy, xx = y + dy, x + dx
                if 0 <= yy < h and 0 <= xx < w and chan[yy, xx] != chan[y, x]:
                    delta[y, x] += colour[chan[yy, xx], y, x] * k_d[d] * (f[yy, xx] - f[y, x]) / s[yy, xx]
    reference = compact(m - delta)
    v, st = (m * s).astype(np.float32), state0.copy()
    crosstalk.correct(v, st, col, "lut", lut="compact")
    assert np.all((st & validity.REASON_MASK) == validity.VALID)
    step = np.abs(reference - f) / f
    err = np.abs(v - reference) / reference
    assert np.all(reference > 0.2 * f)
    assert np.median(step[chan != 0]) > 0.03, np.median(step)        # the correction is not small here
    own = np.abs(reference - compact(m - delta, "full")) / reference       # the compact LUT's own error
    assert np.max(err) < max(np.max(own), 1e-4), (np.max(err), np.max(own))


def test_compact_for_derives_the_colour_tables_before_the_first_frame(monkeypatch):
    """`compact_for` (what nrcrosstalk calls when it starts) also derives a colour calibration's amplitude
    pairs and spill basis, so the first frame derives neither: afterwards the pairs come without the mosaic
    lookup, and with the SVD disabled the colour compact setting still corrects a frame."""
    from nrhdr_core import cfa as cfas
    prof = profile.default(12, 16, cfa="grbg")
    prof = prof.replace(crosstalk=crosstalk.identity_calibration(prof.mask, nd=prof.nd, black_level=prof.black_level,
                                                                 clip_code=prof.clip_code, colour=True))
    crosstalk.compact_for(prof)

    def derived_again(*a, **k):
        raise AssertionError("derived in the frame")
    with monkeypatch.context() as m:
        m.setattr(cfas, "block", derived_again)
        assert crosstalk.colour_pairs(prof.crosstalk, prof.cfa).shape == (2, 12, 16)
        with pytest.raises(AssertionError, match="derived in the frame"):     # a calibration not seen before
            crosstalk.colour_pairs(dataclasses.replace(prof.crosstalk), prof.cfa)
    monkeypatch.setattr(np.linalg, "svd", derived_again)
    raw = np.clip(prof.black_level + np.geomspace(5, 3000, 12 * 16).reshape(12, 16), 0, prof.clip_code).astype(np.uint16)
    v, s = validity.classify(raw, prof, "threshold", l_min=0)
    crosstalk.correct(v, s, prof, "lut", lut="compact")
    assert np.isfinite(v).all()


def _clipped_reference(values, state, f, basis, inv_de, nd, chan):
    """The colour compact pass's CLIPPED-pixel rule written from its definition (docs/CROSSTALK.md 4b): v =
    the largest value of the pixel and the CLIPPED photosites of its colour in its 5 x 5 window; the mean
    (float32 sum, window rows top to bottom, columns left to right) of the flux f of its colour's VALID
    photosites in its 9 x 9 window brighter than v replaces v when there are any; returns the (2, H, W)
    basis values at v (/ ND if attenuated) as a lerp of the basis grid, None where not CLIPPED."""
    from nrhdr_core.states import ATTENUATED, CLIPPED, REASON_MASK, VALID
    h, w = values.shape
    reason = state & REASON_MASK
    out = {}
    for y in range(h):
        for x in range(w):
            if reason[y, x] != CLIPPED:
                continue
            same = lambda yy, xx: 0 <= yy < h and 0 <= xx < w and chan[yy, xx] == chan[y, x]
            v = max(float(values[yy, xx]) for yy in range(y - 2, y + 3) for xx in range(x - 2, x + 3)
                    if same(yy, xx) and reason[yy, xx] == CLIPPED)
            acc, n = np.float32(0.0), 0
            for yy in range(y - 4, y + 5):
                for xx in range(x - 4, x + 5):
                    if same(yy, xx) and reason[yy, xx] == VALID and f[yy, xx] > v:
                        acc, n = np.float32(acc + f[yy, xx]), n + 1
            if n:
                v = float(acc) / n
            q = v * float(inv_de) * (float(np.float32(1.0) / np.float32(nd)) if state[y, x] & ATTENUATED else 1.0)
            i = min(max(int(q), 0), basis.shape[0] - 2)
            t = q - i
            out[y, x] = [np.float32(float(basis[i, k]) + t * float(basis[i + 1, k] - basis[i, k])) for k in range(2)]
    return out


@pytest.mark.parametrize("cfa", ["rggb", "bggr", "grbg", "gbrg"])
@pytest.mark.parametrize("shape", [(13, 17), (11, 150), (70, 40)])
def test_colour_compact_clipped_estimate_follows_its_definition(cfa, shape):
    """The colour compact pass's flux of CLIPPED pixels (`_colour_compact_clipped`) equals the rule written
    from its definition, bit for bit, on random frames with VALID, CLIPPED and DARK pixels, attenuated or
    not, in every Bayer phase; a wide frame with sparse CLIPPED pixels and rows without any; a tall one
    whose row groups are interleaved over 1, 2, 3 or 5 threads."""
    from nrhdr_core import cfa as cfas
    from nrhdr_core.states import ATTENUATED, CLIPPED, DARK, VALID
    rng = np.random.default_rng(sum(map(ord, cfa)) + shape[1])
    h, w = shape
    p_clip = 0.3 if w < 64 else 0.03
    state = rng.choice(np.array([VALID, CLIPPED, DARK], np.uint8), (h, w), p=[0.6 - p_clip, p_clip, 0.4])
    state[h // 2] = np.where(state[h // 2] == CLIPPED, VALID, state[h // 2])
    state |= rng.choice(np.array([0, ATTENUATED], np.uint8), (h, w))
    values = rng.choice(np.array([2.0, 2.5, 3.0], np.float32), (h, w))
    tgt = rng.uniform(0.0, 4.0, (crosstalk.TGT_PLANES, h, w)).astype(np.float32)
    src = rng.uniform(0.0, 1.0, (crosstalk.SRC_PLANES, h, w)).astype(np.float32)
    basis = rng.uniform(0.0, 1.0, (64, 2)).astype(np.float32)
    inv_de, nd = np.float32(7.3), 6.0
    n_clipped = ((state & 15) == CLIPPED).sum(1).astype(np.int64)
    expect = src.copy()
    ref = _clipped_reference(values, state, tgt[0], basis, inv_de, nd, cfas.channel_index(cfa, h, w))
    for (y, x), b in ref.items():
        expect[:2, y, x] = b
    assert len(ref) > 5
    for nt in (1, 2, 3, 5):                 # the row groups interleaved over nt threads: the same result
        got = src.copy()
        crosstalk._colour_compact_clipped(values, state, got, tgt, basis, inv_de, nd, cfas.block(cfa), n_clipped, nt)
        assert np.array_equal(got, expect), nt
