"""The colour camera stand-in and the colour demo: the synthesised scene in colour (simulate.tint_synthetic),
realtime.SceneCamera on a colour profile (frames = sensor.capture of the CFA mosaic), load_scene(cfa=),
`nrhdr simulate --cfa` naming a colour recipe that runs, `nrhdr demo --cfa` (RGB PNG and three-channel EXR,
grey where the scene is grey, coloured as the scene where it is coloured) and `nrhdr warmup --cfa`."""
from __future__ import annotations

import shlex
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from scipy.ndimage import maximum_filter, minimum_filter

from gst_plugins import cli
from nrhdr_core import cfa as cfas
from nrhdr_core import io, profile, realtime, scene, sensor, simulate

ROOT = Path(__file__).resolve().parents[1]
STILL = simulate.Motion(pan=0.0, tilt=0.0, zoom=1.0, fov=1.0)
LUMA = np.array([0.2126, 0.7152, 0.0722])


def unit(rgb):
    c = np.asarray(rgb, float)
    return c / (LUMA @ c)


# ---- the synthesised scene in colour --------------------------------------------------------------------

def test_tinted_synthetic_scene_keeps_the_luminance_and_colours_its_regions():
    h, w = 240, 320
    lum = scene.synthetic_hdr_scene(h, w)
    rgb = simulate.tint_synthetic(lum)
    assert rgb.shape == (3, h, w) and rgb.dtype == np.float32 and rgb.flags.c_contiguous
    y = np.tensordot(LUMA, rgb.astype(np.float64), axes=1)
    np.testing.assert_allclose(y, lum, rtol=1e-5, atol=1e-7)
    # a wall pixel (right of the window, above the floor) and the zone plate's centre are grey
    for yy, xx in ((int(0.7 * h), int(0.95 * w)), (int(0.35 * h), int(0.22 * w))):
        assert rgb[0, yy, xx] == rgb[1, yy, xx] == rgb[2, yy, xx] == pytest.approx(lum[yy, xx], rel=1e-6)
    # the patch column: each patch's colour scaled to the pixel's luminance
    x = int(0.40 * w)
    for k, (name, colour) in enumerate(simulate.SYNTHETIC_PATCHES):
        yy = int((0.18 + 0.07 * k + 0.03) * h)
        np.testing.assert_allclose(rgb[:, yy, x], unit(colour) * lum[yy, x], rtol=1e-5, err_msg=name)
    # the bright sky is blue, the floor warm
    win = rgb[:, int(0.12 * h):int(0.62 * h), int(0.48 * w):int(0.92 * w)]
    sky = lum[int(0.12 * h):int(0.62 * h), int(0.48 * w):int(0.92 * w)] > 3
    assert sky.mean() > 0.5
    assert (win[2][sky] > win[1][sky]).all() and (win[1][sky] > win[0][sky]).all()
    floor = rgb[:, int(0.95 * h), int(0.9 * w)]
    assert floor[0] > floor[1] > floor[2]
    # deterministic, and the luminance scene is untouched
    np.testing.assert_array_equal(simulate.tint_synthetic(lum), rgb)
    np.testing.assert_array_equal(lum, scene.synthetic_hdr_scene(h, w))


def test_tint_refuses_a_colour_image():
    with pytest.raises(ValueError, match="tint_synthetic"):
        simulate.tint_synthetic(np.ones((3, 8, 8), np.float32))


# ---- realtime.SceneCamera and load_scene -----------------------------------------------------------------

def _rgb_scene(h=40, w=48, seed=3):
    rng = np.random.default_rng(seed)
    return (0.05 + rng.random((3, h, w)) ** 2 * 4).astype(np.float32)


@pytest.mark.parametrize("cfa", cfas.PATTERNS)
def test_scene_camera_colour_frames_are_the_capture_of_the_mosaic(cfa):
    prof = profile.default(24, 32, seed=2, cfa=cfa)
    sc = _rgb_scene()
    sens = (0.7, 1.0, 1.3)
    cam = realtime.SceneCamera(sc, prof, frames=3, motion=STILL, seed=5, sensitivity=sens)
    render = simulate.ClipRenderer(sc, prof, 3, 0.0, STILL, sensitivity=sens)
    masks = cfas.channel_masks(cfa, 24, 32)
    for i in (0, 1, 2, 4):                                  # frame 4 repeats frame 1 (3-frame path)
        rgb = render.flux(i % 3)
        assert rgb.shape == (3, 24, 32)
        mosaic = np.zeros((24, 32), np.float32)
        for c in range(3):
            mosaic[masks[c]] = rgb[c][masks[c]]
        want = sensor.capture(mosaic, prof, np.random.default_rng((5, i % 3)))
        got = cam.frame(i)
        assert got.dtype == np.uint16 and got.shape == (24, 32)
        np.testing.assert_array_equal(got, want)
    # the exposure comes from the scene's luminance, each channel weighed by its sensitivity
    assert cam.k == pytest.approx(simulate.exposure_scale(simulate.luminance(sc), prof, 0.0))


def test_scene_camera_colour_frames_follow_the_channel_means():
    """A constant colour through a colour SceneCamera: the clear photosites of each CFA channel read the
    channel's exposed flux (independent of the renderer: exposure = 0.18 x regular white / luminance)."""
    prof = profile.default(32, 32, seed=1, cfa="rggb")
    colour = np.array([0.3, 0.5, 0.9])
    sc = np.broadcast_to(colour[:, None, None], (3, 32, 32)).astype(np.float32)
    cam = realtime.SceneCamera(sc, prof, frames=1, motion=STILL, seed=1)
    k = 0.18 * prof.regular_white / float(LUMA @ colour)
    f = cam.frame(0).astype(float) - prof.black_level
    masks = cfas.channel_masks("rggb", 32, 32)
    for c in range(3):
        clear = masks[c] & ~prof.mask
        assert f[clear].mean() == pytest.approx(k * colour[c], rel=0.05)


def test_scene_camera_monochrome_frames_unchanged():
    """A monochrome profile: frames are sensor.capture of the flux itself; an RGB scene is seen as its
    luminance."""
    prof = profile.default(24, 32, seed=2)
    sc = _rgb_scene()
    lum = simulate.luminance(sc)
    cam = realtime.SceneCamera(lum, prof, frames=2, motion=STILL, seed=4)
    render = simulate.ClipRenderer(lum, prof, 2, 0.0, STILL)
    for i in range(2):
        np.testing.assert_array_equal(cam.frame(i),
                                      sensor.capture(render.flux(i), prof, np.random.default_rng((4, i))))
    rgb_cam = realtime.SceneCamera(sc, prof, frames=2, motion=STILL, seed=4)
    np.testing.assert_array_equal(rgb_cam.frame(1), cam.frame(1))


def test_scene_camera_refuses_a_scene_of_another_shape():
    prof = profile.default(24, 32, cfa="rggb")
    with pytest.raises(ValueError, match="planar RGB"):
        realtime.SceneCamera(np.ones((4, 20, 20), np.float32), prof)
    with pytest.raises(ValueError, match="sensitivity"):
        realtime.SceneCamera(_rgb_scene(), profile.default(24, 32), sensitivity=(2.0, 1.0, 1.0))


def test_load_scene_reads_rgb_for_a_colour_camera(tmp_path):
    sc = _rgb_scene(20, 24)
    f = tmp_path / "s.exr"
    io.write_image(f, np.moveaxis(sc, 0, 2), np.float32, channel_names=["R", "G", "B"])
    rgb, name = realtime.load_scene(str(f), 20, cfa="bggr")
    assert name == "s.exr"
    np.testing.assert_array_equal(rgb, io.read_rgb(f))
    lum, _ = realtime.load_scene(str(f), 20)
    np.testing.assert_array_equal(lum, io.read_luminance(f))
    syn, name = realtime.load_scene("synthetic", 60, cfa="rggb")
    grey, _ = realtime.load_scene("synthetic", 60)
    assert name == "synthetic" and grey.ndim == 2 and syn.shape == (3,) + grey.shape
    np.testing.assert_array_equal(syn, simulate.tint_synthetic(grey))
    with pytest.raises(ValueError, match="cfa"):
        realtime.load_scene("synthetic", 60, cfa="rgbg")


# ---- nrhdr simulate --cfa: the printed recipes run ---------------------------------------------------

def _printed(text: str):
    recipe = next(ln for ln in text.splitlines() if ln.startswith("run it:"))
    launch = next(ln.strip() for ln in text.splitlines() if ln.strip().startswith("nrhdr launch"))
    return recipe, launch


@pytest.mark.gst
def test_simulate_colour_prints_recipes_that_run(tmp_path, capsys, gst_subprocess_env):
    out = tmp_path / "colour clip"
    assert cli.main(["simulate", "-o", str(out), "--cfa", "grbg", "--frames", "2", "--width", "32",
                     "--height", "24"]) == 0
    recipe, launch = _printed(capsys.readouterr().out)
    assert f"pipelines/colour_to_exr.sh {shlex.quote(str(out))}" in recipe
    # the display line, with a sink that needs no screen
    line = launch.replace("autovideosink", "fakesink")
    script = f'nrhdr() {{ {shlex.quote(sys.executable)} -m gst_plugins.cli "$@"; }}\n{line}'
    p = subprocess.run(["bash", "-c", script], cwd=ROOT, env=gst_subprocess_env, capture_output=True,
                       text=True, timeout=300)
    assert p.returncode == 0, p.stdout[-2000:] + p.stderr[-2000:]
    # the recipes as printed: camera-RGB EXR frames beside the clip; the display script (no display here:
    # it says so and plays into fakesink)
    exr_cmd, rest = recipe.split("run it: ", 1)[1].split(" (", 1)
    display_cmd = rest.split("), ", 1)[1].split(" (", 1)[0]
    assert display_cmd == f"pipelines/raw_to_display.sh {shlex.quote(str(out))}"
    for cmd in (exr_cmd, display_cmd):
        p = subprocess.run(["bash", "-c", cmd], cwd=ROOT, env=gst_subprocess_env, capture_output=True, text=True,
                           timeout=300)
        assert p.returncode == 0, cmd + "\n" + p.stdout[-2000:] + p.stderr[-2000:]
    exrs = sorted(Path(f"{out}_exr").glob("frame_*.exr"))
    assert len(exrs) == 2
    values, state = io.read_exr(exrs[1])
    truth = simulate.read_truth(simulate.load_clip(out), 1)
    assert values.shape == truth.shape == (3, 24, 32) and state.shape == (24, 32)
    assert np.median(np.abs(np.log2(np.maximum(values, 1) / np.maximum(truth, 1)))) < 0.1


def test_simulate_monochrome_recipe_unchanged(tmp_path, capsys):
    out = tmp_path / "mono"
    assert cli.main(["simulate", "-o", str(out), "--frames", "1", "--width", "16", "--height", "12"]) == 0
    recipe, _ = _printed(capsys.readouterr().out)
    assert recipe == f"run it: pipelines/raw_to_display.sh {out}   or"


# ---- nrhdr demo --cfa ----------------------------------------------------------------------------------

W, H = 160, 120


@pytest.fixture(scope="module")
def colour_demo(tmp_path_factory, gst_registry):
    out = tmp_path_factory.mktemp("demo") / "colour"
    import contextlib
    import io as pyio
    buf = pyio.StringIO()
    with contextlib.redirect_stdout(buf):
        rc = cli.main(["demo", "--cfa", "rggb", "-o", str(out), "--frames", "2", "--width", str(W),
                       "--height", str(H), "--method", "preview"])
    return rc, out, buf.getvalue()


def _smooth(a: np.ndarray, size: int = 5) -> np.ndarray:
    """Pixels whose size x size neighbourhood of `a` (H, W) bool is all True."""
    return minimum_filter(a.astype(np.uint8), size=size, mode="nearest").astype(bool)


def _regions(truth: np.ndarray, white: float):
    """(grey, {patch name: pixels}) of a truth frame (3, H, W): pixels whose 5 x 5 neighbourhood is grey
    (resp. the patch's colour), flat (max / min of the luminance under 1.5) and below the sensor's white."""
    y = np.tensordot(LUMA, truth, axes=1)
    flat = _smooth(maximum_filter(y, 5) < 1.5 * minimum_filter(y, 5)) & _smooth(truth.max(0) < 0.5 * white)
    chroma = truth / np.maximum(y, 1e-6)
    grey = flat & _smooth(np.abs(chroma - 1).max(0) < 1e-3)
    patches = {name: flat & _smooth(np.abs(chroma - unit(c)[:, None, None]).max(0) < 1e-3 * unit(c).max())
               for name, c in simulate.SYNTHETIC_PATCHES}
    return grey, patches


@pytest.mark.gst
def test_colour_demo_writes_rgb_png_and_rgb_exr(colour_demo):
    rc, out, text = colour_demo
    assert rc == 0, text
    assert "in colour (Bayer rggb)" in text and "channels R, G, B" in text
    pngs = sorted((out / "png").glob("frame_*.png"))
    exrs = sorted((out / "exr").glob("frame_*.exr"))
    assert len(pngs) == len(exrs) == 2
    img = io.read_image(pngs[0], np.uint8)
    assert img.shape == (H, W, 3)
    assert io.exr_channels(exrs[0]) == 3                     # R, G, B (+ state, below)
    values, state = io.read_exr(exrs[0])
    assert values.shape == (3, H, W) and state.shape == (H, W)
    info = simulate.load_clip(out / "clip")
    assert info["cfa"] == "rggb" and info["nd_layout"] == "balanced"


@pytest.mark.gst
@pytest.mark.parametrize("frame", [0, 1])
def test_colour_demo_is_grey_where_the_scene_is_grey_and_coloured_as_the_scene(colour_demo, frame):
    rc, out, text = colour_demo
    assert rc == 0, text
    prof = profile.load(out / "clip" / "camera.json")
    truth = simulate.read_truth(simulate.load_clip(out / "clip"), frame)
    values, _ = io.read_exr(out / "exr" / f"frame_{frame:05d}.exr")
    png = io.read_image(out / "png" / f"frame_{frame:05d}.png", np.uint8).astype(float)
    grey, patches = _regions(truth, prof.white)
    assert grey.sum() > 200
    # EXR: camera RGB, grey areas grey
    ratio_rg = np.median(values[0][grey] / values[1][grey])
    ratio_bg = np.median(values[2][grey] / values[1][grey])
    assert ratio_rg == pytest.approx(1.0, abs=0.03) and ratio_bg == pytest.approx(1.0, abs=0.03)
    # PNG (white balance 1, 1, 1 from the profile): grey areas within a few codes of grey
    spread = png.max(axis=2) - png.min(axis=2)
    assert np.median(spread[grey]) <= 3
    seen = 0
    for name, colour in simulate.SYNTHETIC_PATCHES:
        px = patches[name]
        if px.sum() < 8:
            continue
        seen += 1
        want = unit(colour) / unit(colour)[1]
        got = np.median(values[:, px] / values[1, px], axis=1)
        np.testing.assert_allclose(got, want, rtol=0.1, err_msg=name)
        # the PNG: a channel clearly stronger in the scene's colour is clearly stronger in the picture
        mean = png[px].mean(axis=0)
        for i in range(3):
            for j in range(3):
                if colour[i] > 1.3 * colour[j]:
                    assert mean[i] > mean[j] + 10, (name, mean)
    assert seen >= 5


@pytest.mark.gst
def test_colour_demo_refuses_a_monochrome_method_and_odd_size(tmp_path, capsys):
    assert cli.main(["demo", "--cfa", "rggb", "-o", str(tmp_path / "a"), "--method", "nearest"]) == 2
    assert "--method nearest" in capsys.readouterr().err
    assert cli.main(["demo", "--cfa", "bggr", "-o", str(tmp_path / "b"), "--width", "33"]) == 2
    assert "--width 33" in capsys.readouterr().err
    assert not (tmp_path / "a").exists() and not (tmp_path / "b").exists()


# ---- nrhdr warmup --cfa ------------------------------------------------------------------------------

def test_warmup_cfa_adds_the_colour_stages(monkeypatch, capfd):
    from gst_plugins import runtime
    from nrhdr_core import chain, hdr_output, tonemap
    calls, rgb = [], []

    def fake_warmup(settings, tone=False, calibrated=True, *, stages=chain.STAGES, transfers=(), elements=False,
                    cfa="none"):
        sets = [settings] if isinstance(settings, chain.ChainSettings) else list(settings)
        calls.append((tuple(stages), cfa, {s.method for s in sets}, elements))

    monkeypatch.setattr(chain, "warmup", fake_warmup)
    monkeypatch.setattr(tonemap, "warmup_rgb", lambda **kw: rgb.append(("tonemap", kw)))
    monkeypatch.setattr(hdr_output, "warmup_rgb", lambda **kw: rgb.append(("hdr", kw)))
    monkeypatch.setattr(runtime, "run_pipeline", lambda *a, **k: pytest.fail("nrhdr warmup ran a pipeline"))
    assert cli.main(["warmup"]) == 0
    mono = list(calls)
    assert all(cfa == "none" for _, cfa, _, _ in mono) and not rgb
    calls.clear()
    assert cli.main(["warmup", "--cfa", "gbrg"]) == 0
    out, _ = capfd.readouterr()
    assert calls[:len(mono)] == mono                        # the monochrome stages first, as they are
    colour = calls[len(mono):]
    assert {s for st, cfa, _, _ in colour for s in st} == {"validity", "crosstalk", "reconstruction"}
    assert all(cfa == "gbrg" and el for _, cfa, _, el in colour)
    assert set().union(*(m for st, _, m, _ in colour if "reconstruction" in st)) == set(chain.COLOUR_METHODS)
    assert sorted(k for k, _ in rgb) == ["hdr", "tonemap"] and all(kw["elements"] for _, kw in rgb)
    assert "Bayer gbrg" in out and "RGB tone map" in out
