"""The colour (Bayer) simulator: CFA mosaic, ND layouts over the CFA, camera-RGB truth, clip.json v2 and its
checks, and the `nrhdr simulate` / `nrhdr profile` colour options (docs/SIMULATOR.md, docs/COLOUR.md)."""
import json
import shutil

import numpy as np
import pytest

from nrhdr_core import io, mask, profile, sensor, simulate
from test_simulate_io import undated

# the colour (R = 0, G = 1, B = 2) of each photosite of the top-left 2 x 2 block, written out by hand
PHASES = {"rggb": [[0, 1], [1, 2]], "bggr": [[2, 1], [1, 0]], "grbg": [[1, 0], [2, 1]], "gbrg": [[1, 2], [0, 1]]}
STILL = simulate.Motion(pan=0.0, tilt=0.0, zoom=1.0, fov=1.0)


def constant_scene(rgb, h=24, w=32):
    return np.ones((3, h, w), np.float32) * np.asarray(rgb, np.float32)[:, None, None]


@pytest.mark.parametrize("phase", sorted(PHASES))
def test_mosaic_of_a_constant_colour_scene(phase):
    """Each photosite's flux is its CFA colour x the exposure (scene median luminance at 18 % of the regular
    range) x that channel's sensitivity."""
    colour, sens = (3.0, 1.5, 0.25), (0.5, 1.0, 0.8)
    p = profile.default(16, 20, cfa=phase)
    r = simulate.ClipRenderer(constant_scene(colour), p, 2, motion=STILL, sensitivity=sens)
    lum = 0.2126 * 3.0 + 0.7152 * 1.5 + 0.0722 * 0.25
    k = 0.18 * p.regular_white / lum
    assert r.scale == pytest.approx(k, rel=1e-6)
    flux = r.flux(1)
    assert flux.shape == (3, 16, 20)
    for c in range(3):
        assert np.allclose(flux[c], k * colour[c] * sens[c], rtol=1e-6)
    got = r.photosite_flux(flux)
    for dy in range(2):
        for dx in range(2):
            c = PHASES[phase][dy][dx]
            assert np.allclose(got[dy::2, dx::2], k * colour[c] * sens[c], rtol=1e-6), (phase, dy, dx)


@pytest.mark.parametrize("phase", sorted(PHASES))
def test_raw_mosaic_means_per_colour_and_filter(phase, tmp_path):
    """The captured codes: per CFA position, the regular photosites average the colour's flux, the attenuated
    ones flux / ND (shot noise only)."""
    colour, sens = (2.0, 1.0, 0.5), (0.6, 1.0, 0.8)
    p = profile.default(64, 64, cfa=phase, read_noise=0.0, seed=4)
    info = simulate.simulate_clip(constant_scene(colour, 32, 32), tmp_path / "c", p, frames=1, motion=STILL,
                                  sensitivity=sens, progress=False)
    raw = io.read_raw_video(tmp_path / "c" / "clip.raw", 64, 64)[0].astype(np.float64)
    k = info["exposure_scale"]
    for dy in range(2):
        for dx in range(2):
            c = PHASES[phase][dy][dx]
            f = k * colour[c] * sens[c]
            codes, nd = raw[dy::2, dx::2], p.mask[dy::2, dx::2]
            assert codes[~nd].mean() == pytest.approx(min(f, p.clip_code), rel=0.02)
            assert codes[nd].mean() == pytest.approx(f / p.nd, rel=0.02)


def test_truth_equals_the_camera_rgb_flux_along_the_path(tmp_path, rng):
    """The truth EXR is the view of each channel along the camera path x exposure (from luminance) x the
    channel's sensitivity; the raw is `sensor.capture` of its CFA mosaic with the clip's noise stream."""
    yy, xx = np.mgrid[0:30, 0:40].astype(np.float32)       # 1:1 at fov 0.8: no prefilter
    sc = np.stack([1 + 0.5 * np.sin(xx / 3), 2 + np.cos(yy / 4), 0.5 + (yy > 15) * 9.0]).astype(np.float32)
    p = profile.default(24, 32, cfa="grbg", seed=1)
    m = simulate.Motion(pan=0.2, tilt=-0.1, zoom=1.1, fov=0.8)
    sens = (0.6, 1.0, 0.8)
    info = simulate.simulate_clip(sc, tmp_path / "c", p, frames=3, motion=m, seed=7, sensitivity=sens,
                                  progress=False)
    lum = 0.2126 * sc[0].astype(np.float64) + 0.7152 * sc[1] + 0.0722 * sc[2]
    k = 0.18 * p.regular_white / np.median(lum)
    assert info["exposure_scale"] == pytest.approx(k, rel=1e-6)
    clip = simulate.load_clip(tmp_path / "c")
    prof = profile.load(tmp_path / "c" / "camera.json")
    rng_noise = np.random.default_rng(7)
    raw = io.read_raw_video(tmp_path / "c" / "clip.raw", 32, 24)
    for i in range(3):
        truth = simulate.read_truth(clip, i)
        assert truth.shape == (3, 24, 32) and truth.dtype == np.float32
        for c in range(3):
            expect = simulate.view(sc[c], 24, 32, i / 2, m) * np.float32(info["exposure_scale"] * sens[c])
            assert np.allclose(truth[c], expect, rtol=1e-6)
        mosaic = np.choose(np.tile(np.array(PHASES["grbg"]), (12, 16)), truth)
        assert np.array_equal(raw[i], sensor.capture(mosaic, prof, rng_noise))


def test_grey_scene_colour_clip_is_the_monochrome_clip_per_channel():
    """A luminance scene seen by a colour sensor is grey: with objects and a cut, every channel's flux is the
    monochrome sensor's flux x the channel's sensitivity (powers of two: exact)."""
    yy, xx = np.mgrid[0:60, 0:80].astype(np.float32)
    sc = (1.0 + 0.5 * np.sin(xx / 5.0) * np.cos(yy / 7.0) + (xx > 50) * 6.0).astype(np.float32)
    objs = simulate.random_objects(3, 24, 32, 4, 3.0, 8.0, "mixed", seed=2)
    kw = dict(frames=4, motion=simulate.Motion(), objects=objs, cut_frame=3)
    mono = simulate.ClipRenderer(sc, profile.default(24, 32), **kw)
    col = simulate.ClipRenderer(sc, profile.default(24, 32, cfa="rggb"), sensitivity=(0.5, 1.0, 2.0), **kw)
    for i in range(4):
        f = mono.flux(i)
        for c, s in enumerate((0.5, 1.0, 2.0)):
            assert np.array_equal(col.flux(i)[c], f * np.float32(s)), (i, c)


def test_each_channel_moves_along_the_same_path_with_objects_and_cut():
    """Channel c of an RGB clip is the monochrome clip of scene channel c (up to the exposure factor, which
    the luminance sets): patches carry each channel's texture, the cut shows each channel's second scene."""
    yy, xx = np.mgrid[0:60, 0:80].astype(np.float32)
    sc = np.stack([1 + 0.5 * np.sin(xx / 3), 2 + np.cos(yy / 4), 0.5 + (yy > 30) * 9.0]).astype(np.float32)
    cut = np.ascontiguousarray(sc[:, ::-1])
    objs = (simulate.MovingObject("patch", 10, 8, 2, 1, 9, 1.0, (0.3, 0.6)),)
    kw = dict(frames=4, motion=simulate.Motion(), objects=objs, cut_frame=2)
    col = simulate.ClipRenderer(sc, profile.default(24, 32, cfa="bggr"), cut_scene=cut, **kw)
    for c in range(3):
        mono = simulate.ClipRenderer(sc[c], profile.default(24, 32), cut_scene=cut[c], **kw)
        for i in range(4):
            kc, km = (col.cut_scale, mono.cut_scale) if i >= 2 else (col.scale, mono.scale)
            assert np.allclose(col.flux(i)[c] / kc, mono.flux(i) / km, rtol=1e-5), (c, i)


@pytest.mark.parametrize("pattern", ["nonregular", "bluenoise", "cell2", "regular"])
def test_balanced_layout_halves_every_colour_plane(pattern):
    for seed in (0, 5):
        m = mask.cfa_mask(pattern, 40, 52, "balanced", seed=seed)
        for dy in range(2):
            for dx in range(2):
                assert int(m[dy::2, dx::2].sum()) == 20 * 26 // 2, (pattern, seed, dy, dx)
        assert mask.nd_layout_of(m, "rggb") in ("balanced", "regular")
    # odd sub-lattice sizes (3 x 5 photosites): 7 or 8 attenuated of 15
    m = mask.cfa_mask("nonregular", 6, 10, "balanced", seed=1)
    assert all(int(m[dy::2, dx::2].sum()) in (7, 8) for dy in range(2) for dx in range(2))


def test_balanced_nonregular_is_nonregular_within_each_plane():
    """Each sub-lattice is its own non-regular draw: no two planes alike, none periodic with a short period."""
    m = mask.cfa_mask("nonregular", 64, 64, "balanced", seed=3)
    planes = [m[dy::2, dx::2] for dy in range(2) for dx in range(2)]
    for a in range(4):
        for b in range(a + 1, 4):
            assert not np.array_equal(planes[a], planes[b])
        for py in range(1, 5):
            assert not np.array_equal(planes[a][py:], planes[a][:-py])
            assert not np.array_equal(planes[a][:, py:], planes[a][:, :-py])
    assert mask.nd_layout_of(m, "gbrg") == "balanced"


def test_regular_layout_is_the_assorted_pixels_block_checkerboard():
    m = mask.cfa_mask("nonregular", 16, 24, "regular", seed=9)
    assert np.array_equal(m, mask.cfa_mask("bluenoise", 16, 24, "regular", seed=1))   # no pattern of its own
    assert not m[:2, :2].any() and m[:2, 2:4].all() and m[2:4, :2].all()   # whole 2x2 blocks, top-left clear
    assert np.array_equal(m[4:], m[:-4]) and np.array_equal(m[:, 4:], m[:, :-4])     # period 4 pixels
    for dy in range(2):
        for dx in range(2):
            p = m[dy::2, dx::2]                 # every colour plane a regular checkerboard
            assert np.array_equal(p[1:], ~p[:-1]) and np.array_equal(p[:, 1:], ~p[:, :-1])
    assert m.mean() == 0.5 and mask.nd_layout_of(m, "rggb") == "regular"


def test_independent_layout_is_the_pattern_as_is():
    for pattern in ("nonregular", "regular"):
        assert np.array_equal(mask.cfa_mask(pattern, 12, 16, "independent", seed=4),
                              mask.make_mask(pattern, 12, 16, seed=4))
    # the monochrome checkerboard over a CFA: red and blue never attenuated, the greens always
    m = mask.cfa_mask("regular", 12, 16, "independent")
    assert mask.nd_layout_of(m, "rggb") == "independent" and not m[0::2, 0::2].any() and m[0::2, 1::2].all()


def test_layout_and_profile_errors():
    with pytest.raises(ValueError, match="nd_layout.*must be one of independent, balanced, regular"):
        mask.cfa_mask("nonregular", 8, 8, "diagonal")
    with pytest.raises(ValueError, match="even width and height"):
        mask.cfa_mask("nonregular", 8, 9, "balanced")
    with pytest.raises(ValueError, match="nd_layout.*monochrome"):
        profile.default(8, 8, nd_layout="balanced")
    assert mask.nd_layout_of(np.zeros((4, 4), bool), "rggb") == "none"
    p = profile.default(8, 12, cfa="bggr", nd_layout="regular")
    assert p.cfa == "bggr" and mask.nd_layout_of(p.mask, "bggr") == "regular"
    assert mask.nd_layout_of(profile.default(8, 12, cfa="rggb").mask, "rggb") == mask.DEFAULT_ND_LAYOUT


def test_colour_clip_round_trip(tmp_path):
    sc = constant_scene((1.0, 2.0, 4.0), 30, 40)
    info = simulate.simulate_clip(sc, tmp_path / "c", frames=2, cfa="gbrg", nd_layout="regular",
                                  sensitivity=(0.5, 1.0, 0.8), progress=False)
    doc = json.loads((tmp_path / "c" / "clip.json").read_text())
    assert doc["version"] == 2 and doc["cfa"] == "gbrg" and doc["nd_layout"] == "regular"
    assert doc["sensitivity"] == [0.5, 1.0, 0.8] and info["cfa"] == "gbrg"
    clip = simulate.load_clip(tmp_path / "c")
    assert (clip["cfa"], clip["channels"], clip["sensitivity"]) == ("gbrg", 3, [0.5, 1.0, 0.8])
    prof = profile.load(clip["profile_path"])
    assert prof.cfa == "gbrg" and prof.white_balance == pytest.approx((2.0, 1.0, 1.25))
    assert json.loads((tmp_path / "c" / "camera.json").read_text())["version"] == 3
    assert mask.nd_layout_of(prof.mask, prof.cfa) == "regular"
    assert io.exr_channels(tmp_path / "c" / "truth" / "frame_00001.exr") == 3
    # through the white balance, the truth has the scene's colour again
    t = simulate.read_truth(clip, 0)[:, 5, 5] * np.array(prof.white_balance)
    assert t / t[1] == pytest.approx([0.5, 1.0, 2.0], rel=1e-6)


def test_monochrome_clip_is_unchanged_by_the_colour_arguments(tmp_path):
    sc = (np.arange(24 * 32, dtype=np.float32).reshape(24, 32) % 17 + 1)
    p = profile.default(24, 32, seed=2)
    simulate.simulate_clip(sc, tmp_path / "a", p, frames=2, seed=3, progress=False)
    simulate.simulate_clip(sc, tmp_path / "b", p, frames=2, seed=3, progress=False, cfa="none",
                           nd_layout="independent", sensitivity=(1, 1, 1))
    for f in ("clip.raw", "clip.json", "camera.json", "camera_mask.png"):
        assert (tmp_path / "a" / f).read_bytes() == (tmp_path / "b" / f).read_bytes(), f
    # EXR files carry the time they were written (OpenImageIO's DateTime): the rest is the same
    truth = "truth/frame_00001.exr"
    assert undated(tmp_path / "a" / truth) == undated(tmp_path / "b" / truth)
    doc = json.loads((tmp_path / "a" / "clip.json").read_text())
    assert doc["version"] == 1 and not {"cfa", "nd_layout", "sensitivity"} & set(doc)
    clip = simulate.load_clip(tmp_path / "a")
    assert clip["channels"] == 1 and simulate.read_truth(clip, 1).shape == (24, 32)


def test_simulate_clip_colour_argument_errors(tmp_path):
    sc = constant_scene((1, 1, 1))
    with pytest.raises(ValueError, match="cfa: must be one of"):
        simulate.simulate_clip(sc, tmp_path / "x", frames=1, cfa="rgbg", progress=False)
    with pytest.raises(ValueError, match="sensitivity.*three finite numbers"):
        simulate.simulate_clip(sc, tmp_path / "x", frames=1, cfa="rggb", sensitivity=(1, 0, 1), progress=False)
    with pytest.raises(ValueError, match="sensitivity.*monochrome"):
        simulate.simulate_clip(sc, tmp_path / "x", frames=1, sensitivity=(1, 2, 1), progress=False)
    with pytest.raises(ValueError, match="cfa: the profile's sensor has the CFA 'none'"):
        simulate.simulate_clip(sc, tmp_path / "x", profile.default(24, 32), frames=1, cfa="rggb", progress=False)
    with pytest.raises(ValueError, match="nd_layout: the profile's mask is not in the 'regular' layout"):
        simulate.simulate_clip(sc, tmp_path / "x", profile.default(24, 32, cfa="rggb"), frames=1,
                               nd_layout="regular", progress=False)
    hot = sc.copy()
    hot[2, 3, 3] = 1e33          # a blue value far beyond the luminance the exposure is set from
    with pytest.raises(ValueError, match="hot scene: .*peak flux"):
        simulate.simulate_clip(hot, tmp_path / "x", profile.default(24, 32, cfa="rggb"), frames=1,
                               scene_name="hot scene", progress=False)
    hot[2, 3, 3] = np.nan
    with pytest.raises(ValueError, match="hot scene: 1 scene values are NaN"):
        simulate.simulate_clip(hot, tmp_path / "x", profile.default(24, 32, cfa="rggb"), frames=1,
                               scene_name="hot scene", progress=False)
    assert not (tmp_path / "x").exists()


@pytest.fixture(scope="module")
def colour_clip(tmp_path_factory):
    d = tmp_path_factory.mktemp("colour") / "c"
    simulate.simulate_clip(constant_scene((1.0, 2.0, 0.5), 20, 28), d, profile.default(12, 16, cfa="rggb"),
                           frames=2, progress=False)
    return d


@pytest.mark.parametrize("changes, field", [
    ({"cfa": "rgb"}, "'cfa'"), ({"cfa": 7}, "'cfa'"), ({"cfa": "none"}, "'version'"),
    ({"cfa": "none", "version": 1}, "'nd_layout'"),
    ({"version": 1}, "'version'"), ({"nd_layout": "random"}, "'nd_layout'"), ({"nd_layout": None}, "'nd_layout'"),
    ({"sensitivity": [1, 2]}, "'sensitivity'"), ({"sensitivity": [1, -1, 1]}, "'sensitivity'"),
    ({"sensitivity": "1,1,1"}, "'sensitivity'"), ({"width": 15}, "'width'"), ({"cfa": "bggr"}, "'cfa'"),
    ({"truth": "truth/frame.exr"}, "'truth'"),
])
def test_untrusted_colour_clip_json(colour_clip, tmp_path, changes, field):
    d = tmp_path / "c"
    shutil.copytree(colour_clip, d)
    doc = json.loads((d / "clip.json").read_text())
    doc.update(changes)
    (d / "clip.json").write_text(json.dumps(doc))
    with pytest.raises(simulate.ClipError, match=f"clip.json.*field {field}"):
        simulate.load_clip(d)


def test_truth_channels_contradicting_clip_json(colour_clip, tmp_path):
    d = tmp_path / "c"
    shutil.copytree(colour_clip, d)
    io.write_exr(d / "truth" / "frame_00001.exr", np.ones((12, 16), np.float32))      # a grey frame
    clip = simulate.load_clip(d)
    with pytest.raises(simulate.ClipError, match=r"frame_00001.exr: a truth frame of 1 channel.*clip.json "
                                                 r"field 'cfa' is 'rggb'"):
        simulate.read_truth(clip, 1)
    io.write_exr(d / "truth" / "frame_00000.exr", np.ones((12, 16), np.float32))
    with pytest.raises(simulate.ClipError, match="frame_00000.exr.*field 'cfa'"):
        simulate.load_clip(d)
    # a monochrome clip whose truth is RGB
    mono = tmp_path / "m"
    simulate.simulate_clip(np.ones((20, 28), np.float32), mono, profile.default(12, 16), frames=1, progress=False)
    io.write_exr(mono / "truth" / "frame_00000.exr", np.ones((3, 12, 16), np.float32))
    with pytest.raises(simulate.ClipError, match="frame_00000.exr: a truth frame of 3 channel.*'none'"):
        simulate.load_clip(mono)
    (mono / "truth" / "frame_00000.exr").write_bytes(b"not an exr")
    with pytest.raises(simulate.ClipError, match="frame_00000.exr.*field 'truth'"):
        simulate.load_clip(mono)


def test_truth_of_another_size_is_refused(colour_clip, tmp_path):
    d = tmp_path / "c"
    shutil.copytree(colour_clip, d)
    io.write_exr(d / "truth" / "frame_00001.exr", np.ones((3, 10, 16), np.float32))
    with pytest.raises(simulate.ClipError, match="frame_00001.exr.*16x12"):
        simulate.read_truth(simulate.load_clip(d), 1)


# ---- the command line ------------------------------------------------------------------------------------

def test_cli_simulate_colour_from_an_rgb_scene(tmp_path):
    from gst_plugins import cli
    px = np.zeros((40, 60, 3), np.float32)
    px[...] = [0.5, 0.25, 0.125]
    io.write_image(tmp_path / "s.exr", px, np.float32, ["R", "G", "B"])
    out = tmp_path / "c"
    assert cli.main(["simulate", str(tmp_path / "s.exr"), "-o", str(out), "--frames", "1", "--width", "32",
                     "--height", "24", "--cfa", "bggr", "--nd-layout", "balanced", "--sensitivity",
                     "0.5,1,0.8"]) == 0
    clip = simulate.load_clip(out)
    assert (clip["cfa"], clip["nd_layout"], clip["sensitivity"]) == ("bggr", "balanced", [0.5, 1.0, 0.8])
    t = simulate.read_truth(clip, 0)[:, 10, 10]
    assert t / t[1] == pytest.approx([0.5 * 0.5 / 0.25, 1.0, 0.125 * 0.8 / 0.25], rel=1e-5)
    prof = profile.load(out / "camera.json")
    assert prof.cfa == "bggr" and prof.white_balance == pytest.approx((2.0, 1.0, 1.25))
    assert mask.nd_layout_of(prof.mask, "bggr") == "balanced"


@pytest.mark.parametrize("args, message", [
    (["--cfa", "rggb", "--width", "33"], "--width 33: a Bayer sensor"),
    (["--cfa", "rggb", "--height", "25"], "--height 25: a Bayer sensor"),
    (["--sensitivity", "1,2,1"], "--sensitivity.*give --cfa"),
    (["--nd-layout", "balanced"], "--nd-layout balanced.*give --cfa"),
    (["--cfa", "rggb", "--nd-layout", "regular", "--pattern", "cell2"], "--pattern cell2 contradicts"),
])
def test_cli_simulate_refuses_colour_arguments(tmp_path, capsys, args, message):
    from gst_plugins import cli
    assert cli.main(["simulate", "-o", str(tmp_path / "c"), "--frames", "1", "--width", "32", "--height", "24",
                     *args]) == 2
    import re
    assert re.search(message, capsys.readouterr().err)
    assert not (tmp_path / "c").exists()


@pytest.mark.parametrize("value", ["1,2", "1,x,1", "1,0,1", "1,nan,1"])
def test_cli_rgb_numbers_are_checked(tmp_path, capsys, value):
    from gst_plugins import cli
    assert cli.main(["simulate", "-o", str(tmp_path / "c"), "--cfa", "rggb", "--sensitivity", value]) == 2
    assert "argument --sensitivity" in capsys.readouterr().err
    assert cli.main(["profile", "-o", str(tmp_path / "p.json"), "--cfa", "rggb", "--white-balance", value]) == 2
    assert "argument --white-balance" in capsys.readouterr().err


def test_cli_profile_colour(tmp_path, capsys):
    from gst_plugins import cli
    f = tmp_path / "cam.json"
    assert cli.main(["profile", "-o", str(f), "--width", "32", "--height", "24", "--cfa", "grbg",
                     "--nd-layout", "regular", "--white-balance", "2,1,1.5"]) == 0
    p = profile.load(f)
    assert p.cfa == "grbg" and p.white_balance == (2.0, 1.0, 1.5)
    assert mask.nd_layout_of(p.mask, "grbg") == "regular"
    assert json.loads(f.read_text())["version"] == 3
    assert "CFA grbg, ND layout regular" in capsys.readouterr().out
    assert cli.main(["profile", "-o", str(tmp_path / "m.json"), "--white-balance", "2,1,1.5"]) == 2
    assert "--white-balance" in capsys.readouterr().err
    # --pattern none: the unmodified Bayer camera
    assert cli.main(["profile", "-o", str(tmp_path / "u.json"), "--width", "32", "--height", "24", "--cfa",
                     "rggb", "--pattern", "none"]) == 0
    u = profile.load(tmp_path / "u.json")
    assert u.cfa == "rggb" and not u.mask.any()
