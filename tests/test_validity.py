"""Validity, selection modes and ND scaling (paper section 2.3, Eq. 3), checked pixel by pixel."""
import numpy as np
import pytest

from nrhdr_core import profile, validity as V


def hand_profile():
    m = np.array([[False, True, False], [True, False, True]])
    return profile.make(m, nd=6.0, black_level=10.0, l_min=50.0)


def test_eq3_scaling_states_and_bounds():
    p = hand_profile()
    raw = np.array([[1000, 1000, 4094], [30, 4095, 4094]], np.uint16)
    v, s = V.classify(raw, p, "threshold")
    # regular valid: code - black
    assert v[0, 0] == 990 and s[0, 0] == V.VALID
    # attenuated valid: (code - black) * ND  (Eq. 3)
    assert v[0, 1] == pytest.approx(990 * 6.0) and s[0, 1] == V.VALID | V.ATTENUATED
    # regular clipped: lower bound clip - black
    assert s[0, 2] == V.CLIPPED and v[0, 2] == 4084
    # attenuated below l_min: DARK with upper bound l_min * ND
    assert s[1, 0] == V.DARK | V.ATTENUATED and v[1, 0] == pytest.approx(50 * 6.0)
    # regular clipped at 4095 too
    assert s[1, 1] == V.CLIPPED
    # attenuated clipped: lower bound (clip - black) * ND
    assert s[1, 2] == V.CLIPPED | V.ATTENUATED and v[1, 2] == pytest.approx(4084 * 6.0)
    lo, up = V.bounds(v, s)
    assert np.isnan(lo[0, 0]) and lo[1, 2] == v[1, 2] and up[1, 0] == v[1, 0] and np.isnan(up[1, 2])
    assert V.known_mask(s).tolist() == [[True, True, False], [False, False, False]]


def test_regular_dark_pixels_stay_valid_in_threshold_mode():
    p = hand_profile()
    raw = np.full((2, 3), 12, np.uint16)
    v, s = V.classify(raw, p, "threshold")
    assert (s[~p.mask] == V.VALID).all() and ((s[p.mask] & V.REASON_MASK) == V.DARK).all()


def test_l_min_override():
    p = hand_profile()
    raw = np.full((2, 3), 40, np.uint16)  # signal 30
    _, s1 = V.classify(raw, p, "threshold")
    _, s2 = V.classify(raw, p, "threshold", l_min=20)
    assert ((s1[p.mask] & V.REASON_MASK) == V.DARK).all() and ((s2[p.mask] & V.REASON_MASK) == V.VALID).all()


def test_best_pixel_only_discards_attenuated_next_to_valid_regular():
    m = np.zeros((3, 3), bool)
    m[1, 1] = True
    p = profile.make(m, nd=6.0)
    raw = np.full((3, 3), 4095, np.uint16)
    raw[1, 1] = 3000
    _, s = V.classify(raw, p, "best")          # all regular neighbours clipped: keep the ND pixel
    assert s[1, 1] == V.VALID | V.ATTENUATED
    raw[0, 0] = 2000
    v, s = V.classify(raw, p, "best")          # one valid regular neighbour: discard it
    assert s[1, 1] == V.DISCARDED | V.ATTENUATED and v[1, 1] == pytest.approx(3000 * 6.0)
    assert V.missing_mask(s)[1, 1]


def test_all_mode_discards_below_0db_snr():
    p = hand_profile()
    raw = np.full((2, 3), 10, np.uint16)  # zero signal
    _, s = V.classify(raw, p, "all")
    assert ((s & V.REASON_MASK) == V.DARK).all()


def test_in_place_outputs_and_errors():
    p = hand_profile()
    raw = np.full((2, 3), 500, np.uint16)
    v = np.zeros((2, 3), np.float32)
    s = np.zeros((2, 3), np.uint8)
    V.classify(raw, p, values=v, state=s)
    assert v[0, 0] == 490
    with pytest.raises(ValueError, match="raw frame is 2x3 but the profile.s mask is 3x2"):
        V.classify(np.zeros((3, 2), np.uint16), p)
    with pytest.raises(ValueError, match="uint16"):
        V.classify(np.zeros((2, 3), np.float32), p)
    with pytest.raises(ValueError, match="mode"):
        V.classify(raw, p, "median")


def test_defect_pixels_are_discarded_and_reconstructed():
    from nrhdr_core import reconstruction
    base = profile.default(24, 32, seed=5)
    d = np.zeros(base.mask.shape, np.uint8)
    d[3, 4], d[10, 11], d[20, 30] = profile.DEFECT_HOT, profile.DEFECT_DEAD, profile.DEFECT_STUCK
    p = profile.make(base.mask, defects=d)
    raw = np.where(base.mask, np.round(1500 / base.nd), 1500).astype(np.uint16)   # a flat field
    raw[3, 4], raw[10, 11], raw[20, 30] = 4095, 0, 777      # what such pixels read
    v0, s0 = V.classify(raw, base)
    v, s = V.classify(raw, p)
    bad = d != 0
    # defect pixels: DISCARDED (missing), their ND bit kept; every other pixel exactly as without the map
    assert ((s[bad] & V.REASON_MASK) == V.DISCARDED).all()
    assert np.array_equal(s[bad] & V.ATTENUATED, s0[bad] & V.ATTENUATED)
    assert np.array_equal(s[~bad], s0[~bad]) and np.array_equal(v[~bad], v0[~bad])
    assert not V.known_mask(s)[bad].any() and V.missing_mask(s)[bad].all()
    # the reconstruction fills them from the flat field around them
    out = reconstruction.reconstruct(v, V.known_mask(s))
    assert np.allclose(out[bad], 1500.0, rtol=0.02)


def test_best_mode_does_not_drop_a_pixel_for_a_defective_neighbour():
    m = np.zeros((3, 3), bool)
    m[1, 1] = True                                    # one attenuated pixel, regular pixels around it
    raw = np.full((3, 3), 2000, np.uint16)
    raw[1, 1] = 400
    d = np.zeros((3, 3), np.uint8)
    _, s = V.classify(raw, profile.make(m), "best")
    assert s[1, 1] == V.ATTENUATED | V.DISCARDED      # valid regular neighbours: dropped
    d[~m] = profile.DEFECT_STUCK                      # all its regular neighbours are defective
    _, s = V.classify(raw, profile.make(m, defects=d), "best")
    assert s[1, 1] == V.ATTENUATED | V.VALID and ((s[~m] & V.REASON_MASK) == V.DISCARDED).all()
