"""Validity per colour on a Bayer mosaic (docs/COLOUR.md "Validity and crosstalk per colour"): every
neighbour rule of nrhdr_core.validity takes same-colour photosites only; clipping and l_min per photosite."""
import numpy as np
import pytest

from nrhdr_core import profile, validity as V

# rggb: R at (even, even), B at (odd, odd), G elsewhere
R_OFFSETS = {(dy, dx) for dy in (-2, 0, 2) for dx in (-2, 0, 2)} - {(0, 0)}
G_OFFSETS = R_OFFSETS | {(-1, -1), (-1, 1), (1, -1), (1, 1)}


def colour_profile(mask, cfa="rggb", **kw):
    return profile.make(mask, nd=6.0, black_level=0.0, l_min=50.0, cfa=cfa, **kw)


def best_state(mask, raw, cfa="rggb"):
    _, s = V.classify(raw, colour_profile(mask, cfa), "best")
    return s


@pytest.mark.parametrize("y,x,offsets", [(4, 4, R_OFFSETS), (5, 5, R_OFFSETS), (4, 5, G_OFFSETS),
                                         (5, 4, G_OFFSETS)])
def test_best_pixel_uses_exactly_the_same_colour_neighbours(y, x, offsets):
    """An attenuated photosite is discarded exactly when a regular photosite at one of its same-colour
    offsets (R, B: 2 apart; G: diagonal or 2 apart) is valid; a valid regular pixel anywhere else in its 5 x 5
    (other colours, the 8 direct neighbours of R and B) does not count."""
    h = w = 10
    for dy in range(-2, 3):
        for dx in range(-2, 3):
            if (dy, dx) == (0, 0):
                continue
            mask = np.zeros((h, w), bool)
            mask[y, x] = True
            raw = np.full((h, w), 4095, np.uint16)     # every regular pixel clipped ...
            raw[y, x] = 3000
            raw[y + dy, x + dx] = 2000                  # ... but this one
            s = best_state(mask, raw)
            want = V.ATTENUATED | (V.DISCARDED if (dy, dx) in offsets else V.VALID)
            assert s[y, x] == want, (dy, dx)


def test_best_pixel_monochrome_keeps_its_8_neighbours():
    mask = np.zeros((6, 6), bool)
    mask[2, 2] = True
    raw = np.full((6, 6), 4095, np.uint16)
    raw[2, 2] = 3000
    raw[2, 3] = 2000                                    # a direct neighbour (G of an R photosite)
    p = profile.make(mask, nd=6.0, black_level=0.0, l_min=50.0)
    assert V.classify(raw, p, "best")[1][2, 2] == V.ATTENUATED | V.DISCARDED
    assert best_state(mask, raw)[2, 2] == V.ATTENUATED | V.VALID


def _clip_frame():
    """A clipped regular R photosite at (4, 4); its same-colour attenuated photosites clipped (bounds 30000,
    25000); an attenuated G photosite next to it not clipped."""
    h = w = 10
    mask = np.zeros((h, w), bool)
    values = np.full((h, w), 100.0, np.float32)
    state = np.zeros((h, w), np.uint8)
    state[4, 4] = V.CLIPPED
    values[4, 4] = 4000.0
    for (y, x), v in (((4, 6), 30000.0), ((2, 2), 25000.0)):
        mask[y, x] = True
        state[y, x] = V.CLIPPED | V.ATTENUATED
        values[y, x] = v
    state[4, 5] = V.VALID | V.ATTENUATED                # G: another colour
    values[4, 5] = 700.0
    return values, state


def test_clipped_neighbour_bound_from_same_colour_attenuated_pixels():
    values, state = _clip_frame()
    lo, _ = V.bounds(values, state, cfa="rggb")
    assert lo[4, 4] == 25000.0                          # the smaller of the same-colour bounds
    lo_mono, _ = V.bounds(values, state)
    assert lo_mono[4, 4] == 4000.0                      # monochrome: an unclipped ND neighbour: no rule
    state[2, 6] = V.VALID | V.ATTENUATED                # a same-colour ND pixel not clipped: no rule
    lo, _ = V.bounds(values, state, cfa="rggb")
    assert lo[4, 4] == 4000.0


def test_clipped_neighbour_bound_falls_back_to_the_colour_planes_5x5():
    values, state = _clip_frame()
    state[4, 6] = state[2, 2] = V.VALID                 # no same-colour ND pixel within 2 ...
    state[0, 8] = V.CLIPPED | V.ATTENUATED              # ... one 4 away (R)
    values[0, 8] = 20000.0
    state[1, 7] = V.VALID | V.ATTENUATED                # B, unclipped: other colour, ignored
    lo, _ = V.bounds(values, state, cfa="rggb")
    assert lo[4, 4] == 20000.0
    n, known, lo2, up2 = V.prepare(values, state, cfa="rggb")
    assert lo2[4, 4] == 20000.0 and n == int((~known).sum())


@pytest.mark.parametrize("cfa", ["rggb", "bggr", "grbg", "gbrg"])
def test_clipping_and_l_min_per_photosite_in_every_phase(cfa):
    """Each photosite against the clip code and the scalar l_min in its own channel: the threshold mode
    classifies a mosaic exactly as the monochrome sensor does (no neighbour rule there)."""
    rng = np.random.default_rng(3)
    mask = rng.random((12, 16)) < 0.5
    raw = rng.integers(0, 4096, (12, 16)).astype(np.uint16)
    raw[rng.random((12, 16)) < 0.2] = 20               # below l_min
    raw[rng.random((12, 16)) < 0.2] = 4095             # clipped
    mono = profile.make(mask, nd=6.0, black_level=10.0, l_min=50.0)
    col = profile.make(mask, nd=6.0, black_level=10.0, l_min=50.0, cfa=cfa)
    for mode in ("threshold", "all"):
        v1, s1 = V.classify(raw, mono, mode)
        v2, s2 = V.classify(raw, col, mode)
        assert np.array_equal(s1, s2) and np.array_equal(v1, v2)
    _, s = V.classify(raw, col, "threshold")
    assert ((s & V.REASON_MASK) == V.DARK).sum() > 0 and ((s & V.REASON_MASK) == V.CLIPPED).sum() > 0
