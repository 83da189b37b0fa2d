"""Flat-field analysis without a mask (nrhdr_core/flats.py, `nrhdr calibrate` without --mask).

The flats come from a small generator written here, independent of the project's simulator: a 12-bit sensor
with Poisson shot noise, Gaussian read noise, a conserving 3 x 3 crosstalk kernel, a vignetting gradient,
PRNU, and planted hot / dead / stuck pixels; frames written as 16-bit TIFF (tifffile) or PNG (Pillow) with
`exposures.csv`. Masks: the 2 x 2 checkerboard, the paper's non-regular mask (nrhdr_core/mask.py), a
blue-noise-like mask made here (thresholded high-pass noise), with a seed per test."""
from __future__ import annotations

import csv
import json
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings, strategies as st

from nrhdr_core import calibration, flats, mask as masks, profile

GAIN = 0.5            # DN per electron
FULL_WELL = 9000.0    # electrons: the 12-bit ADC clips (4095) first
BLACK = 64.0
CLIP = 4095


def checkerboard(h, w, seed=0):
    yy, xx = np.mgrid[0:h, 0:w]
    return ((yy + xx + seed) % 2) == 1


def nonregular(h, w, seed=0):
    return masks.nonregular_mask(h, w, seed=seed)


def bluenoise_like(h, w, seed=0):
    """Half the pixels, the largest of white noise minus its 3 x 3 box mean (suppressed low frequencies)."""
    n = np.random.default_rng(seed).random((h, w))
    p = np.pad(n, 1, mode="reflect")
    box = sum(p[1 + dy:1 + dy + h, 1 + dx:1 + dx + w] for dy in (-1, 0, 1) for dx in (-1, 0, 1)) / 9
    hp = n - box
    return hp > np.median(hp)


MASKS = {"checkerboard": checkerboard, "nonregular": nonregular, "bluenoise": bluenoise_like}


def crosstalk_3x3(e, edge, corner):
    """Conserving 3 x 3 crosstalk: every pixel sends `edge` of its electrons to each edge neighbour and
    `corner` to each corner neighbour inside the sensor, and keeps the rest."""
    h, w = e.shape
    out = e.copy()
    for dy in (-1, 0, 1):
        for dx in (-1, 0, 1):
            if dy == dx == 0:
                continue
            k = edge if dy == 0 or dx == 0 else corner
            src = e[max(0, -dy):h - max(0, dy), max(0, -dx):w - max(0, dx)]
            out[max(0, dy):h - max(0, -dy), max(0, dx):w - max(0, -dx)] += k * src
            out[max(0, -dy):h - max(0, dy), max(0, -dx):w - max(0, dx)] -= k * src
    return out


def make_frames(mask, nd, seed, read_noise=3.0, edge=0.01, corner=0.0025, vignetting=0.3, frames=2,
                n_lo=10, n_hi=14, defects=None):
    """[(exposure_s, [uint16 frames])]: dark, n_lo geometric steps up to the regular pixels' saturation,
    n_hi steps up to 2.5 x ND x it. `defects`: {"hot": [(y, x, offset DN)], "dead": [(y, x)],
    "stuck": [(y, x, code)]}."""
    rng = np.random.default_rng(seed)
    h, w = mask.shape
    yy, xx = np.mgrid[0:h, 0:w]
    r2 = ((yy - h / 2) / h) ** 2 + ((xx - w / 2) / w) ** 2
    light = (1 - vignetting * r2 / r2.max()) * (1 + 0.01 * rng.standard_normal((h, w)))   # vignetting, PRNU
    rate = (CLIP - BLACK) / GAIN / 0.01            # electrons/s: a regular pixel saturates at 10 ms
    t = np.concatenate([[0.0], np.geomspace(2e-5, 0.008, n_lo), np.geomspace(0.011, 0.01 * 2.5 * nd, n_hi)])
    d = defects or {}
    out = []
    for ti in t:
        e = crosstalk_3x3(rate * ti * light / np.where(mask, nd, 1.0), edge, corner)
        fr = []
        for _ in range(frames):
            n = np.minimum(rng.poisson(np.maximum(e, 0)).astype(np.float64), FULL_WELL)
            code = (n + read_noise * rng.standard_normal((h, w))) * GAIN + BLACK
            for y, x, off in d.get("hot", ()):
                code[y, x] += off
            for y, x in d.get("dead", ()):
                code[y, x] = BLACK + read_noise * GAIN * rng.standard_normal()
            for y, x, c in d.get("stuck", ()):
                code[y, x] = c
            fr.append(np.clip(np.rint(code), 0, CLIP).astype(np.uint16))
        out.append((float(ti), fr))
    return out


def write_sweep(folder: Path, sweep, fmt="tif") -> Path:
    """The sweep format `nrhdr calibrate` reads: 16-bit frames + exposures.csv (file,exposure_s)."""
    folder.mkdir(parents=True, exist_ok=True)
    rows = []
    for i, (t, frs) in enumerate(sweep):
        for j, fr in enumerate(frs):
            name = f"f{i:02d}_{j}.{fmt}"
            if fmt == "tif":
                import tifffile
                tifffile.imwrite(folder / name, fr)
            else:
                from PIL import Image
                Image.fromarray(fr).save(folder / name)
            rows.append((name, repr(t)))
    with open(folder / "exposures.csv", "w", newline="") as f:
        csv.writer(f).writerows([("file", "exposure_s")] + rows)
    return folder


def in_memory(sweep) -> calibration.FlatSweep:
    """The FlatSweep `calibration.read_flats` would make of these frames."""
    st_ = [np.stack(frs).astype(np.float64) for _, frs in sweep]
    return calibration.FlatSweep(Path("memory"), np.array([t for t, _ in sweep]),
                                 np.stack([s.mean(0) for s in st_]).astype(np.float32),
                                 np.stack([s.max(0) for s in st_]).astype(np.uint16),
                                 np.stack([s.var(0, ddof=1) for s in st_]).astype(np.float32),
                                 np.array([len(frs) for _, frs in sweep]))


def planted(mask, rng, n=3):
    """n hot, n dead, n stuck pixels at distinct random positions away from the border."""
    h, w = mask.shape
    pos = rng.choice((h - 4) * (w - 4), 3 * n, replace=False)
    ys, xs = 2 + pos // (w - 4), 2 + pos % (w - 4)
    p = list(zip(ys.tolist(), xs.tolist()))
    return {"hot": [(y, x, 300.0 + 100 * k) for k, (y, x) in enumerate(p[:n])], "dead": p[n:2 * n],
            "stuck": [(y, x, 900 + 500 * k) for k, (y, x) in enumerate(p[2 * n:])]}


def defect_map(shape, d):
    m = np.zeros(shape, np.uint8)
    for y, x, _ in d["hot"]:
        m[y, x] = flats.DEFECT_HOT
    for y, x in d["dead"]:
        m[y, x] = flats.DEFECT_DEAD
    for y, x, _ in d["stuck"]:
        m[y, x] = flats.DEFECT_STUCK
    return m


# ---- the detector on masks it has not seen ---------------------------------------------------------------

@pytest.mark.parametrize("kind", sorted(MASKS))
@pytest.mark.parametrize("seed", [11, 29])
def test_recovers_mask_nd_and_defects(kind, seed):
    """48 x 64, ND 6, 1 % / 0.25 % crosstalk, 30 % vignetting, read noise 3 e-, 2 frames per exposure: the
    mask exactly (every pixel but the dead and stuck ones, whose kind cannot be measured), every planted
    defect with its kind and no other, the ND within 1 % (6 % on the checkerboard, where every interior
    pixel of a kind has the same neighbours and only the sensor's border separates crosstalk from ND)."""
    rng = np.random.default_rng(seed)
    m = MASKS[kind](48, 64, seed)
    d = planted(m, rng)
    det = flats.detect(in_memory(make_frames(m, 6.0, seed, defects=d)))
    truth = defect_map(m.shape, d)
    measurable = ~np.isin(truth, (flats.DEFECT_DEAD, flats.DEFECT_STUCK))
    assert np.array_equal(det.mask[measurable], m[measurable])
    assert np.array_equal(det.defects, truth)
    assert det.nd == pytest.approx(6.0, rel=0.01 if kind != "checkerboard" else 0.06)
    assert det.confident and det.separation > 20 and det.ambiguous == 0


@settings(max_examples=6, deadline=None)
@given(seed=st.integers(0, 2 ** 31 - 1), nd=st.floats(2.0, 16.0), kind=st.sampled_from(sorted(MASKS)))
def test_any_seed_and_nd(seed, nd, kind):
    """Any mask seed and ND 2..16 (32 x 40, read noise 3 e-, 2 frames, crosstalk 1 % / 0.25 %): the mask
    exactly, ND within 2 % (8 % on the checkerboard, whose crosstalk only the ~140 border pixels separate
    from the ND at this size)."""
    m = MASKS[kind](32, 40, seed % 1000)
    det = flats.detect(in_memory(make_frames(m, nd, seed)))
    assert np.array_equal(det.mask, m)
    assert det.nd == pytest.approx(nd, rel=0.02 if kind != "checkerboard" else 0.08)
    assert not det.defects.any()


def test_without_dark_frame():
    """No dark frame (the sweep starts at the shortest lit exposure, black level 64): the mask, the ND within
    1 %, the defects (hot ones by the intercept of the response fit)."""
    m = nonregular(48, 64, 3)
    d = planted(m, np.random.default_rng(3))
    det = flats.detect(in_memory(make_frames(m, 6.0, 3, defects=d)[1:]))
    truth = defect_map(m.shape, d)
    measurable = ~np.isin(truth, (flats.DEFECT_DEAD, flats.DEFECT_STUCK))
    assert np.array_equal(det.mask[measurable], m[measurable])
    assert np.array_equal(det.defects, truth)
    assert det.nd == pytest.approx(6.0, rel=0.01)


def test_constant_code_at_black_is_dead():
    """One code in every frame: at the black level a dead pixel, above it a stuck one."""
    m = checkerboard(32, 40)
    det = flats.detect(in_memory(make_frames(m, 4.0, 2, defects={"stuck": [(10, 10, BLACK), (20, 20, 2000)]})))
    assert det.defects[10, 10] == flats.DEFECT_DEAD and det.defects[20, 20] == flats.DEFECT_STUCK
    assert np.count_nonzero(det.defects) == 2
    assert det.mask[10, 10] == m[10, 10] and det.mask[20, 20] == m[20, 20]      # opposite of the neighbours


def test_strong_crosstalk_and_noise():
    """Crosstalk 2.5 % per edge and 0.6 % per corner (an attenuated pixel among regular ones reads ~1.8 x its
    own signal at ND 8) and read noise 20 e-: the mask still exactly; the crosstalk share per regular edge
    neighbour is measured (truth 8 x 2.5 % = 20 % of the attenuated response)."""
    m = nonregular(48, 64, 5)
    det = flats.detect(in_memory(make_frames(m, 8.0, 5, read_noise=20.0, edge=0.025, corner=0.006)))
    assert np.array_equal(det.mask, m)
    assert det.nd == pytest.approx(8.0, rel=0.02)
    assert det.crosstalk_share["attenuated_per_regular_edge"] == pytest.approx(0.2, rel=0.15)


@pytest.mark.parametrize("kind", sorted(MASKS))
def test_strong_vignetting(kind):
    """The corners get a fifth of the centre's light (80 % vignetting), ND 4: the mask exactly."""
    m = MASKS[kind](48, 64, 5)
    det = flats.detect(in_memory(make_frames(m, 4.0, 5, vignetting=0.8)))
    assert np.array_equal(det.mask, m)
    assert det.confident


def test_low_separation_is_not_confident():
    """An ND of 1.05 under 30 e- read noise: the populations overlap, the detection says so."""
    m = nonregular(32, 40, 3)
    det = flats.detect(in_memory(make_frames(m, 1.05, 3, read_noise=30.0, edge=0.0, corner=0.0)))
    assert not det.confident
    with pytest.raises(calibration.CalibrationError, match="cannot be told apart.*--mask"):
        flats.check_confidence(det, "flats")
    flats.check_confidence(det, "flats", accept=True)


def test_no_attenuated_pixels_is_not_confident():
    """A sensor without ND pixels: no two populations."""
    m = np.zeros((32, 40), bool)
    det = flats.detect(in_memory(make_frames(m, 1.0, 4, edge=0.0, corner=0.0)))
    assert not det.confident


# ---- the command end to end -------------------------------------------------------------------------------

@pytest.fixture(scope="module")
def written_sweep(tmp_path_factory):
    m = nonregular(48, 64, 7)
    d = planted(m, np.random.default_rng(7), n=2)
    folder = write_sweep(tmp_path_factory.mktemp("flats_nomask"), make_frames(m, 6.0, 7, defects=d), "png")
    return folder, m, d


def _cli(args):
    from gst_plugins import cli
    a = cli.build_parser().parse_args(["calibrate", *map(str, args)])
    return a.func(a)


def test_cli_without_mask(written_sweep, tmp_path, capsys):
    """`nrhdr calibrate FLATS -o camera.json` (no --mask): the profile's mask is the generator's (up to the
    dead pixels' unmeasurable kind), its ND within 2 %, and the JSON reports the detection."""
    folder, m, d = written_sweep
    out = tmp_path / "camera.json"
    assert _cli([folder, "-o", out, "--json", "-q", "--no-plots"]) == 0
    s = json.loads(capsys.readouterr().out)
    det = s["mask_detection"]
    assert det["confident"] and det["separation"] > 20 and det["ambiguous_share"] == 0
    assert det["defects"] == {"hot": 2, "dead": 2, "stuck": 2}
    assert sorted((y, x) for y, x, _ in det["defect_pixels"]) == sorted(
        [(y, x) for y, x, _ in d["hot"]] + list(d["dead"]) + [(y, x) for y, x, _ in d["stuck"]])
    prof = profile.load(out)
    truth = defect_map(m.shape, d)
    measurable = ~np.isin(truth, (flats.DEFECT_DEAD, flats.DEFECT_STUCK))
    assert np.array_equal(prof.mask[measurable], m[measurable])
    assert prof.nd == pytest.approx(6.0, rel=0.02)
    assert prof.crosstalk.info["mask_detection"]["separation"] == det["separation"]
    if "defects" in {f.name for f in __import__("dataclasses").fields(profile.CameraProfile)}:
        assert np.array_equal(prof.defects, truth)


def test_cli_without_mask_prints_confidence(written_sweep, tmp_path, capsys):
    """The text report names the confidence figures and the defects; the plots include the detection's."""
    folder, _, _ = written_sweep
    assert _cli([folder, "-o", tmp_path / "c.json", "-q"]) == 0
    text = capsys.readouterr().out
    assert "mask from the flats" in text and "separation" in text and "ambiguous" in text
    assert "2 hot, 2 dead, 2 stuck" in text
    assert (tmp_path / "c_calib_detection.png").stat().st_size > 1000
    for p in tmp_path.glob("c*"):                         # the detection's plot alone is refused too
        if p.name != "c_calib_detection.png":
            p.unlink()
    assert _cli([folder, "-o", tmp_path / "c.json", "-q"]) == 2
    assert "c_calib_detection.png already exists" in capsys.readouterr().err


def test_cli_refuses_low_separation(tmp_path, capsys):
    """Overlapping populations: exit 2, a message with the figures and the way out, no profile written;
    --accept-low-confidence writes it."""
    m = nonregular(32, 40, 9)
    folder = write_sweep(tmp_path / "f", make_frames(m, 1.05, 9, read_noise=30.0, edge=0.0, corner=0.0))
    out = tmp_path / "c.json"
    assert _cli([folder, "-o", out, "-q", "--no-plots"]) == 2
    err = capsys.readouterr().err
    assert "cannot be told apart" in err and "sigma apart" in err and "--accept-low-confidence" in err
    assert not out.exists()
    assert _cli([folder, "-o", out, "-q", "--no-plots", "--accept-low-confidence"]) == 0
    assert out.exists()
