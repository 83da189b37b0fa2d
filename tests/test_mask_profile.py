"""ND masks (paper Fig. 1, 2) and the camera profile file format (docs/PROFILE.md)."""
import json
import re

import numpy as np
import pytest

from nrhdr_core import io, mask, profile


def test_nonregular_mask_half_attenuated_and_seeded():
    a = mask.nonregular_mask(48, 64, seed=1)
    b = mask.nonregular_mask(48, 64, seed=1)
    c = mask.nonregular_mask(48, 64, seed=2)
    assert a.dtype == bool and a.sum() == 48 * 64 // 2
    assert np.array_equal(a, b) and not np.array_equal(a, c)


def test_regular_mask_is_2x2_periodic():
    m = mask.regular_mask(6, 8)
    assert m.sum() == 24
    assert np.array_equal(m[:2, :2], m[2:4, 2:4]) and np.array_equal(m[:2, :2], m[4:6, 6:8])


def test_spectra_fig2_regular_two_peaks_nonregular_one():
    reg = mask.mask_spectrum(mask.regular_mask(128, 128))
    non = mask.mask_spectrum(mask.nonregular_mask(128, 128, seed=0))
    def second_peak(s):
        s = s.copy()
        s[64, 64] = 0  # DC after fftshift
        return s.max()
    # regular: a second peak as strong as DC (aliasing ambiguity); non-regular: noise-like floor
    assert second_peak(reg) == pytest.approx(1.0)
    assert second_peak(non) < 0.05


def test_profile_roundtrip(tmp_path):
    p = profile.default(30, 40, seed=9, nd=7.5, l_min=250.0, black_level=16.0, read_noise=3.0)
    path = profile.save(p, tmp_path / "cam.json")
    q = profile.load(path)
    assert np.array_equal(p.mask, q.mask)
    for f in ("nd", "bit_depth", "clip_code", "black_level", "gain", "read_noise", "full_well", "l_min"):
        assert getattr(p, f) == getattr(q, f)
    assert q.white == pytest.approx((4094 - 16) * 7.5)
    # the mask is a viewable 8-bit PNG, 255 = attenuated
    png = io.read_image(tmp_path / "cam_mask.png", np.uint8)
    assert png.dtype == np.uint8 and set(np.unique(png)) <= {0, 255}
    assert np.array_equal(png[:, :, 0] == 255, p.mask)
    doc = json.loads(path.read_text())
    assert doc["format"] == "nrhdr-camera-profile" and doc["version"] == 1 and doc["crosstalk"] is None


@pytest.mark.parametrize("field,value,words", [
    ("nd", 0.5, "nd"), ("clip_code", 5000, "clip_code"), ("l_min", 5000.0, "l_min"),
    ("read_noise", -1.0, "read_noise"), ("bit_depth", 20, "bit_depth"),
])
def test_profile_validation_names_the_field(field, value, words):
    with pytest.raises(profile.ProfileError, match=words):
        profile.default(8, 8, **{field: value})


def test_profile_load_errors(tmp_path):
    p = profile.default(8, 10)
    path = profile.save(p, tmp_path / "cam.json")
    with pytest.raises(profile.ProfileError, match="not found"):
        profile.load(tmp_path / "missing.json")
    bad = tmp_path / "corrupt.json"
    bad.write_text("{ not json")
    with pytest.raises(profile.ProfileError, match="corrupt.json.*not a valid JSON"):
        profile.load(bad)
    doc = json.loads(path.read_text())
    for change, words in [({"version": 99}, "version"), ({"format": "x"}, "format"),
                          ({"width": 12}, "mask.*10x8.*12x8"), ({"nd": "six"}, "nd"),
                          ({"mask": "nope.png"}, "mask.*no such file")]:
        d = dict(doc, **change)
        f = tmp_path / "edited.json"
        f.write_text(json.dumps(d))
        with pytest.raises(profile.ProfileError, match=words):
            profile.load(f)


def test_mask_png_must_be_binary(tmp_path):
    io.write_image(tmp_path / "m.png", np.full((4, 4), 128, np.uint8), np.uint8)
    with pytest.raises(io.ImageFileError, match="only 0.*255"):
        io.read_mask(tmp_path / "m.png")


# ---- reduced-randomness designs ------------------------------------------------------------------

@pytest.mark.parametrize("pattern", ["cell2", "cell2diag", "bluenoise", "voidcluster", "random"])
@pytest.mark.parametrize("shape", [(48, 64), (33, 47)])
def test_new_masks_exactly_half_and_seeded(pattern, shape):
    a = mask.make_mask(pattern, *shape, seed=5)
    b = mask.make_mask(pattern, *shape, seed=5)
    c = mask.make_mask(pattern, *shape, seed=6)
    assert a.dtype == bool and a.shape == shape
    assert int(a.sum()) == round(a.size / 2)
    assert np.array_equal(a, b) and not np.array_equal(a, c)


def test_cell2_two_per_cell_all_arrangements():
    m = mask.cell2_mask(64, 64, seed=1)
    cells = m.reshape(32, 2, 32, 2).transpose(0, 2, 1, 3).reshape(-1, 4)
    assert (cells.sum(1) == 2).all()
    assert len({tuple(c) for c in cells}) == 6            # every one of the C(4,2) arrangements occurs


def test_cell2diag_cells_are_diagonal():
    m = mask.make_mask("cell2diag", 64, 64, seed=1)
    cells = m.reshape(32, 2, 32, 2).transpose(0, 2, 1, 3).reshape(-1, 4)
    assert {tuple(c) for c in cells} == {(True, False, False, True), (False, True, True, False)}


def test_bluenoise_has_little_low_frequency_energy_and_no_peak():
    # blue noise: power concentrated at high frequencies, no spectral peak besides DC (unlike the
    # checkerboard's at (1/2, 1/2)); iid random (white) spreads it evenly
    st_b = mask.spectrum_stats(mask.bluenoise_mask(128, 128, seed=2))
    st_w = mask.spectrum_stats(mask.nonregular_mask(128, 128, seed=2))
    assert st_b["low_freq_power_share"] < 0.2 * st_b["low_freq_area_share"]
    assert st_w["low_freq_power_share"] == pytest.approx(st_w["low_freq_area_share"], rel=0.3)
    assert st_b["peak_ratio"] < 0.1
    assert mask.spectrum_stats(mask.regular_mask(128, 128))["peak_ratio"] == pytest.approx(1.0)


def test_voidcluster_is_blue_noise_without_peak():
    # void-and-cluster (Ulichney 1993): little low-frequency power, no spectral peak besides DC, and the
    # relaxation really acts (far fewer 2 x 2 cells entirely unknown than an iid mask's ~1/16)
    m = mask.voidcluster_mask(128, 128, seed=3)
    st = mask.spectrum_stats(m)
    assert st["low_freq_power_share"] < 0.2 * st["low_freq_area_share"]
    assert st["peak_ratio"] < 0.1
    cells = m.reshape(64, 2, 64, 2).transpose(0, 2, 1, 3).reshape(-1, 4)
    assert np.mean(cells.all(1)) < 0.01 < np.mean(mask.nonregular_mask(128, 128, seed=3)
                                                   .reshape(64, 2, 64, 2).transpose(0, 2, 1, 3)
                                                   .reshape(-1, 4).all(1))


def test_bluenoise_without_jitter_is_the_checkerboard():
    m = mask.bluenoise_mask(32, 32, seed=0, jitter=0.0)
    assert np.array_equal(m, mask.regular_mask(32, 32)) or np.array_equal(m, ~mask.regular_mask(32, 32))


def test_profile_default_takes_new_patterns():
    from nrhdr_core import profile
    p = profile.default(32, 48, seed=3, pattern="cell2")
    assert np.array_equal(p.mask, mask.cell2_mask(32, 48, seed=3))
    with pytest.raises(ValueError, match="pattern"):
        profile.default(8, 8, pattern="hexagonal")


def _defect_map(shape, seed=0):
    rng = np.random.default_rng(seed)
    d = np.zeros(shape, np.uint8)
    idx = rng.choice(d.size, 12, replace=False)
    d.flat[idx[:4]] = profile.DEFECT_HOT
    d.flat[idx[4:8]] = profile.DEFECT_DEAD
    d.flat[idx[8:]] = profile.DEFECT_STUCK
    return d


def test_defect_map_roundtrip_as_png_beside_the_json(tmp_path):
    p = profile.default(12, 16, seed=3)
    d = _defect_map(p.mask.shape)
    q = profile.make(p.mask, defects=d)
    assert q.defects.dtype == np.uint8 and profile.defect_counts(q) == {"hot": 4, "dead": 4, "stuck": 4}
    path = profile.save(q, tmp_path / "cam.json")
    doc = json.loads(path.read_text())
    assert doc["defects"] == "cam_defects.png" and doc["version"] == 2
    png = io.read_image(tmp_path / "cam_defects.png", np.uint8)
    assert png.shape == (12, 16, 1)
    r = profile.load(path)
    assert np.array_equal(r.defects, d) and r.defects.dtype == np.uint8
    # a profile without defects stays a version-1 file without the key
    doc1 = json.loads(profile.save(p, tmp_path / "plain.json").read_text())
    assert doc1["version"] == 1 and "defects" not in doc1 and profile.load(tmp_path / "plain.json").defects is None


def test_defect_map_is_checked(tmp_path):
    p = profile.default(12, 16, seed=3)
    bad = np.zeros((12, 16), np.uint8)
    bad[2, 2] = 7
    with pytest.raises(profile.ProfileError, match="defects.*1 pixels hold others"):
        profile.make(p.mask, defects=bad)
    with pytest.raises(profile.ProfileError, match="defects.*shape"):
        profile.make(p.mask, defects=np.zeros((12, 15), np.uint8))
    path = profile.save(profile.make(p.mask, defects=_defect_map((12, 16))), tmp_path / "cam.json")
    doc = json.loads(path.read_text())
    # wrong size, wrong values, outside the folder, a version-1 file naming one
    io.write_image(tmp_path / "small.png", np.zeros((12, 10), np.uint8), np.uint8)
    io.write_image(tmp_path / "nine.png", np.full((12, 16), 9, np.uint8), np.uint8)
    io.write_image(tmp_path / "wide.png", np.zeros((12, 16), np.uint16), np.uint16)
    (tmp_path / "sub").mkdir()
    (tmp_path / "sub" / "cam_mask.png").write_bytes((tmp_path / "cam_mask.png").read_bytes())
    for change, words in [({"defects": "small.png"}, "defects.*10x12, expected 16x12"),
                          ({"defects": "nine.png"}, "defects.*nine.png: values must be 0"),
                          ({"defects": "wide.png"}, "defects.*8-bit"),
                          ({"defects": "../cam_defects.png"}, "defects.*leaves the folder"),
                          ({"defects": "gone.png"}, "defects.*no such file"),
                          ({"version": 1}, "'defects' need version 2")]:
        f = (tmp_path / "sub" / "edited.json") if "../" in change.get("defects", "") else tmp_path / "edited.json"
        f.write_text(json.dumps(dict(doc, **change)))
        with pytest.raises(profile.ProfileError, match=words):
            profile.load(f)


def test_colour_profile_fields_make_version_3(tmp_path):
    p = profile.default(8, 12, cfa="grbg", white_balance=(2.0, 1.0, 1.5))
    profile.save(p, tmp_path / "c.json")
    doc = json.loads((tmp_path / "c.json").read_text())
    assert doc["version"] == 3 and doc["cfa"] == "grbg" and doc["white_balance"] == [2.0, 1.0, 1.5]
    q = profile.load(tmp_path / "c.json")
    assert q.cfa == "grbg" and q.white_balance == (2.0, 1.0, 1.5) and np.array_equal(q.mask, p.mask)
    # a monochrome profile with unit gains is written as before: no colour field, version 1
    profile.save(profile.default(8, 12), tmp_path / "m.json")
    doc = json.loads((tmp_path / "m.json").read_text())
    assert doc["version"] == 1 and not {"cfa", "white_balance"} & set(doc)


@pytest.mark.parametrize("changes, message", [
    ({"cfa": "rgbg"}, "field 'cfa': must be one of none, rggb, bggr, grbg, gbrg"),
    ({"cfa": 3}, "field 'cfa' must be a string"),
    ({"white_balance": [1, 2]}, "field 'white_balance' must be a list of three numbers"),
    ({"white_balance": [1, 0, 1]}, "field 'white_balance': must be three finite gains"),
    ({"version": 2}, "field 'cfa' needs version 3"),
    ({"width": 11, "height": 8}, None),
])
def test_colour_profile_fields_are_checked(tmp_path, changes, message):
    profile.save(profile.default(8, 12, cfa="rggb"), tmp_path / "c.json")
    doc = json.loads((tmp_path / "c.json").read_text())
    doc.update(changes)
    if "width" in changes:        # an odd width: the mask of that size, and the CFA refuses it
        io.write_mask(tmp_path / "c_mask.png", np.zeros((8, 11), bool))
        message = "field 'cfa': a Bayer sensor has an even width and height"
    (tmp_path / "c.json").write_text(json.dumps(doc))
    with pytest.raises(profile.ProfileError, match=f"c.json.*{re.escape(message)}"):
        profile.load(tmp_path / "c.json")


def test_default_colour_profile_takes_an_nd_layout():
    assert mask.nd_layout_of(profile.default(16, 16, cfa="rggb").mask, "rggb") == "balanced"
    assert mask.nd_layout_of(profile.default(16, 16, cfa="rggb", nd_layout="regular").mask, "rggb") == "regular"
    ind = profile.default(16, 16, cfa="rggb", nd_layout="independent", seed=3)
    assert np.array_equal(ind.mask, mask.make_mask("nonregular", 16, 16, seed=3))
    # monochrome: the pattern as is, whatever nd_layout None / independent
    assert np.array_equal(profile.default(16, 16, seed=3, nd_layout="independent").mask, ind.mask)
    with pytest.raises(ValueError, match="nd_layout: must be one of"):
        profile.default(16, 16, cfa="rggb", nd_layout="cross")
