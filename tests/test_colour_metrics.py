"""metrics: CIELAB, CIEDE2000 against the published test data of Sharma, Wu and Dalal (2005, Table 1), the false
colour measure, per-region log2 PSNR of RGB luminance; scene.colour_zone_plate."""
import numpy as np
import pytest

from nrhdr_core import metrics, scene

# Sharma, Wu and Dalal, Color Res. Appl. 30(1) 2005, Table 1: (L1, a1, b1), (L2, a2, b2), CIEDE2000
SHARMA_PAIRS = [
    ((50.0000, 2.6772, -79.7751), (50.0000, 0.0000, -82.7485), 2.0425),
    ((50.0000, 3.1571, -77.2803), (50.0000, 0.0000, -82.7485), 2.8615),
    ((50.0000, 2.8361, -74.0200), (50.0000, 0.0000, -82.7485), 3.4412),
    ((50.0000, -1.3802, -84.2814), (50.0000, 0.0000, -82.7485), 1.0000),
    ((50.0000, -1.1848, -84.8006), (50.0000, 0.0000, -82.7485), 1.0000),
    ((50.0000, -0.9009, -85.5211), (50.0000, 0.0000, -82.7485), 1.0000),
    ((50.0000, 0.0000, 0.0000), (50.0000, -1.0000, 2.0000), 2.3669),
    ((50.0000, -1.0000, 2.0000), (50.0000, 0.0000, 0.0000), 2.3669),
    ((50.0000, 2.4900, -0.0010), (50.0000, -2.4900, 0.0009), 7.1792),
    ((50.0000, 2.4900, -0.0010), (50.0000, -2.4900, 0.0010), 7.1792),
    ((50.0000, 2.4900, -0.0010), (50.0000, -2.4900, 0.0011), 7.2195),
    ((50.0000, 2.4900, -0.0010), (50.0000, -2.4900, 0.0012), 7.2195),
    ((50.0000, -0.0010, 2.4900), (50.0000, 0.0009, -2.4900), 4.8045),
    ((50.0000, -0.0010, 2.4900), (50.0000, 0.0010, -2.4900), 4.8045),
    ((50.0000, -0.0010, 2.4900), (50.0000, 0.0011, -2.4900), 4.7461),
    ((50.0000, 2.5000, 0.0000), (50.0000, 0.0000, -2.5000), 4.3065),
    ((50.0000, 2.5000, 0.0000), (73.0000, 25.0000, -18.0000), 27.1492),
    ((50.0000, 2.5000, 0.0000), (61.0000, -5.0000, 29.0000), 22.8977),
    ((50.0000, 2.5000, 0.0000), (56.0000, -27.0000, -3.0000), 31.9030),
    ((50.0000, 2.5000, 0.0000), (58.0000, 24.0000, 15.0000), 19.4535),
    ((50.0000, 2.5000, 0.0000), (50.0000, 3.1736, 0.5854), 1.0000),
    ((50.0000, 2.5000, 0.0000), (50.0000, 3.2972, 0.0000), 1.0000),
    ((50.0000, 2.5000, 0.0000), (50.0000, 1.8634, 0.5757), 1.0000),
    ((50.0000, 2.5000, 0.0000), (50.0000, 3.2592, 0.3350), 1.0000),
    ((60.2574, -34.0099, 36.2677), (60.4626, -34.1751, 39.4387), 1.2644),
    ((63.0109, -31.0961, -5.8663), (62.8187, -29.7946, -4.0864), 1.2630),
    ((61.2901, 3.7196, -5.3901), (61.4292, 2.2480, -4.9620), 1.8731),
    ((35.0831, -44.1164, 3.7933), (35.0232, -40.0716, 1.5901), 1.8645),
    ((22.7233, 20.0904, -46.6940), (23.0331, 14.9730, -42.5619), 2.0373),
    ((36.4612, 47.8580, 18.3852), (36.2715, 50.5065, 21.2231), 1.4146),
    ((90.8027, -2.0831, 1.4410), (91.1528, -1.6435, 0.0447), 1.4441),
    ((90.9257, -0.5406, -0.9208), (88.6381, -0.8985, -0.7239), 1.5381),
    ((6.7747, -0.2908, -2.4247), (5.8714, -0.0985, -2.2286), 0.6377),
    ((2.0776, 0.0795, -1.1350), (0.9033, -0.0636, -0.5514), 0.9082),
]


def test_ciede2000_matches_the_published_test_data_to_4_decimals():
    lab1 = np.array([p[0] for p in SHARMA_PAIRS]).T          # channels first, one column per pair
    lab2 = np.array([p[1] for p in SHARMA_PAIRS]).T
    want = np.array([p[2] for p in SHARMA_PAIRS])
    got = metrics.ciede2000(lab1, lab2)
    assert len(want) == 34
    np.testing.assert_array_equal(np.round(got, 4), want)
    np.testing.assert_allclose(metrics.ciede2000(lab2, lab1), got, rtol=0, atol=1e-12)   # symmetric
    assert metrics.ciede2000(np.array([50.0, 10, -20]), np.array([50.0, 10, -20])) == 0.0


def test_lab_of_known_colours():
    # D65 white (R = G = B = the diffuse white) is L* = 100, a* = b* = 0, at any white level
    for white in (1.0, 4094.0):
        lab = metrics.linear_rgb_to_lab(np.full((3, 2, 2), white), white=white)
        np.testing.assert_allclose(lab[0], 100.0, atol=1e-9)
        np.testing.assert_allclose(lab[1:], 0.0, atol=1e-9)
    # black is L* = 0; 18 % grey is L* = 49.5 (116 * 0.18^(1/3) - 16)
    assert metrics.linear_rgb_to_lab(np.zeros(3))[0] == pytest.approx(0.0, abs=1e-12)
    assert metrics.linear_rgb_to_lab(np.full(3, 0.18))[0] == pytest.approx(116 * 0.18 ** (1 / 3) - 16)
    # sRGB primaries and white, 8-bit (the usual published values of IEC 61966-2-1 colours)
    codes = np.array([[[255, 255, 255], [255, 0, 0], [0, 255, 0], [0, 0, 255]]], np.uint8)   # (1, 4, 3)
    lab = metrics.srgb_to_lab(codes)[:, 0].T
    np.testing.assert_allclose(lab, [[100.0, 0.0, 0.0], [53.24, 80.09, 67.20], [87.73, -86.18, 83.18],
                                     [32.30, 79.19, -107.86]], atol=0.05)
    # interleaved and planar give the same values; uint8 codes and floats 0..1 too
    np.testing.assert_array_equal(metrics.srgb_to_lab(np.moveaxis(codes, 2, 0), axis=0), metrics.srgb_to_lab(codes))
    np.testing.assert_allclose(metrics.srgb_to_lab(codes / 255.0), metrics.srgb_to_lab(codes), atol=1e-12)
    assert metrics.luminance(np.array([1.0, 1.0, 1.0])) == pytest.approx(1.0)
    # mean CIEDE2000 of display images: white against black is 100 (L* 100 vs 0, S_L = 1 at mean L* 50)
    white, black = np.full((2, 3, 3), 255, np.uint8), np.zeros((2, 3, 3), np.uint8)
    assert metrics.mean_ciede2000_srgb(white, black) == pytest.approx(100.0)
    assert metrics.mean_ciede2000_srgb(white, white) == 0.0
    half = white.copy()
    half[0] = 0
    assert metrics.mean_ciede2000_srgb(white, half, mask=np.array([False, True])) == 0.0
    with pytest.raises(ValueError, match="3 channels"):
        metrics.linear_rgb_to_lab(np.zeros((4, 2, 2)))
    with pytest.raises(ValueError, match="white"):
        metrics.linear_rgb_to_lab(np.zeros((3, 2, 2)), white=0.0)


def test_false_colour_is_zero_on_a_perfect_result_and_positive_on_a_colour_aliased_one():
    rgb, panels = scene.colour_zone_plate(64)
    truth = rgb * 4094.0
    assert metrics.false_colour(truth, truth) == 0.0
    assert metrics.false_colour_db(truth, truth) == float("-inf")
    # an achromatic result at the wrong level has no false colour either (chroma only)
    assert metrics.false_colour(truth, 1.7 * truth, panels["mid"]) == pytest.approx(0.0, abs=1e-18)
    # colour aliasing: the R and B planes sampled at every other row and column of a Bayer CFA, held
    # (nearest neighbour), against the full-rate green
    aliased = truth.copy()
    aliased[0] = np.repeat(np.repeat(truth[0, ::2, ::2], 2, 0), 2, 1)
    aliased[2] = np.repeat(np.repeat(truth[2, 1::2, 1::2], 2, 0), 2, 1)
    fc = metrics.false_colour(truth, aliased, panels["mid"])
    assert fc > 1.0
    assert metrics.false_colour_db(truth, aliased, panels["mid"]) == pytest.approx(10 * np.log10(fc))
    # the rings' outer half (above the R/B sampling's Nyquist limit) alias far more than the inner half
    yy, xx = np.mgrid[0:64, 0:192]
    r = np.hypot(yy - 31.5, xx - 31.5)
    inner = panels["mid"] & (r < 12)
    outer = panels["mid"] & (r > 20)
    assert metrics.false_colour(truth, aliased, outer) > 4 * metrics.false_colour(truth, aliased, inner)
    # a hand check of one pixel: a test with R doubled at the truth's grey
    t = np.full((3, 1, 1), 2.0)
    x = t.copy()
    x[0] *= 2.0
    k = 1.0 / metrics.luminance(t)
    lab = metrics.linear_rgb_to_lab(x * k)
    assert metrics.false_colour(t, x) == pytest.approx(float(lab[1, 0, 0] ** 2 + lab[2, 0, 0] ** 2))


def test_colour_zone_plate_panels():
    rgb, panels = scene.colour_zone_plate(32, mid=0.25, bright=3.0, stops=1.0)
    assert rgb.shape == (3, 32, 96) and rgb.dtype == np.float32
    mid, bright, colour = (panels[n] for n in scene.ZONE_PLATE_PANELS)
    assert not (mid & bright).any() and not (bright & colour).any()
    # achromatic panels, HDR levels: the bright rings lie above the regular clip (1) and below the ND's 6.35
    for m in (mid, bright):
        np.testing.assert_array_equal(rgb[0][m], rgb[1][m])
        np.testing.assert_array_equal(rgb[2][m], rgb[1][m])
    assert rgb[1][bright].min() >= 1.5 - 1e-5 and rgb[1][bright].max() <= 6.0 + 1e-5
    assert rgb[1][mid].min() >= 0.125 - 1e-6 and rgb[1][mid].max() <= 0.5 + 1e-6
    # the colour panel is chromatic, R and B in antiphase around G
    assert np.abs(rgb[0][colour] - rgb[1][colour]).max() > 0.05
    np.testing.assert_allclose(rgb[0][colour] + rgb[2][colour], 2 * rgb[1][colour], rtol=1e-5)
    with pytest.raises(ValueError, match="size"):
        scene.colour_zone_plate(4)


def test_rgb_clip_report_scores_luminance_per_region():
    rng = np.random.default_rng(0)
    truth = rng.uniform(100, 20000, (3, 16, 16))
    perfect = metrics.rgb_clip_report([(truth, truth)], 635.0, 4094.0, 26000.0)
    assert perfect["all"]["log2_psnr"] == float("inf")
    # a chroma-only error leaves the luminance, hence the report, unchanged
    test = truth.copy()
    d = rng.uniform(-50, 50, (16, 16))
    test[0] += d / metrics.LUMA_709[0]
    test[2] -= d / metrics.LUMA_709[2]
    assert metrics.rgb_clip_report([(truth, test)], 635.0, 4094.0, 26000.0)["all"]["log2_psnr"] > 250
    half = metrics.rgb_clip_report([(truth, truth / 2)], 635.0, 4094.0, 26000.0)
    lum = metrics.luminance(truth)
    assert half == metrics.clip_report([(lum, lum / 2)], 635.0, 4094.0, 26000.0)
