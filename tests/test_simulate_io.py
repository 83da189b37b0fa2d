"""The simulator (scene to raw video with motion) and the file layer (OpenImageIO, raw video, EXR)."""
import json
import os
import re

import numpy as np
import pytest

from nrhdr_core import io, profile, simulate, validity
from conftest import shared_data


def small_scene(rng):
    yy, xx = np.mgrid[0:120, 0:160].astype(np.float32)
    return (1.0 + 0.5 * np.sin(xx / 7.0) * np.cos(yy / 9.0) + (xx > 100) * 20.0).astype(np.float32)


def test_clip_folder_contents_and_truth(tmp_path, rng):
    p = profile.default(48, 64, seed=2)
    info = simulate.simulate_clip(small_scene(rng), tmp_path / "c", p, frames=4, fps=25, seed=3,
                                  sequence="png", progress=False)
    d = tmp_path / "c"
    assert (d / "clip.raw").stat().st_size == 4 * 48 * 64 * 2
    assert json.loads((d / "clip.json").read_text())["frames"] == 4
    assert profile.load(d / "camera.json").mask.tolist() == p.mask.tolist()
    raw = io.read_raw_video(d / "clip.raw", 64, 48)
    assert raw.shape == (4, 48, 64)
    seq = io.read_image(d / "raw_png" / "frame_00002.png", np.uint16)[:, :, 0]
    assert np.array_equal(seq, raw[2])
    # the truth is the noise-free flux: the ND-scaled capture agrees with it where nothing clips
    truth, _ = io.read_exr(d / "truth" / "frame_00001.exr")
    v, s = validity.classify(np.asarray(raw[1]), p, "all")
    ok = validity.known_mask(s) & (truth > 300)
    rel = (v[ok] - truth[ok]) / truth[ok]
    assert abs(rel.mean()) < 0.01            # unbiased
    assert rel.std() < 0.15                  # within shot noise of ND pixels
    # camera motion: consecutive truths differ
    t0, _ = io.read_exr(d / "truth" / "frame_00000.exr")
    t3, _ = io.read_exr(d / "truth" / "frame_00003.exr")
    assert np.abs(t0 - t3).mean() > 0.01 * t0.mean()
    assert info["exposure_scale"] > 0


def test_truth_is_the_camera_paths_view_without_objects_or_cut(tmp_path):
    """Without moving objects and cut, frame i's truth is the view at t = i / (frames - 1) times the exposure
    factor, and clip.json names neither."""
    yy, xx = np.mgrid[0:60, 0:80].astype(np.float32)
    sc = (1.0 + 0.5 * np.sin(xx / 3.0) + (yy > 30) * 9.0).astype(np.float32)   # 1:1 at fov 0.8: no prefilter
    p = profile.default(48, 64, seed=2)
    m = simulate.Motion(pan=0.2, tilt=-0.1, zoom=1.1, fov=0.8)
    info = simulate.simulate_clip(sc, tmp_path / "c", p, frames=3, motion=m, seed=1, progress=False)
    k = np.float32(simulate.exposure_scale(sc, p, 0.0))
    for i in range(3):
        truth, _ = io.read_exr(tmp_path / "c" / "truth" / f"frame_{i:05d}.exr")
        assert np.array_equal(truth, simulate.view(sc, 48, 64, i / 2, m) * k)
    assert "objects" not in info and "cut" not in info
    assert not {"objects", "cut"} & set(json.loads((tmp_path / "c" / "clip.json").read_text()))


def test_simulation_is_deterministic(tmp_path, rng):
    s = small_scene(rng)
    p = profile.default(24, 32, seed=1)
    simulate.simulate_clip(s, tmp_path / "a", p, frames=2, seed=5, progress=False)
    simulate.simulate_clip(s, tmp_path / "b", p, frames=2, seed=5, progress=False)
    simulate.simulate_clip(s, tmp_path / "c", p, frames=2, seed=6, progress=False)
    a, b, c = ((tmp_path / x / "clip.raw").read_bytes() for x in "abc")
    assert a == b and a != c


def test_exposure_stops_double_the_flux(rng):
    p = profile.default(8, 8)
    s = small_scene(rng)
    assert simulate.exposure_scale(s, p, 1.0) == pytest.approx(2 * simulate.exposure_scale(s, p, 0.0))


def test_simulate_errors(tmp_path):
    with pytest.raises(ValueError, match="frames"):
        simulate.simulate_clip(np.ones((10, 10)), tmp_path, frames=0)
    with pytest.raises(simulate.ClipError, match="clip.json"):
        simulate.load_clip(tmp_path)


def test_exr_roundtrip_with_state(tmp_path, rng):
    v = (rng.random((9, 11)) * 1e5).astype(np.float32)
    s = rng.integers(0, 255, (9, 11)).astype(np.uint8)
    io.write_exr(tmp_path / "f.exr", v, s)
    v2, s2 = io.read_exr(tmp_path / "f.exr")
    assert np.array_equal(v, v2) and np.array_equal(s, s2)
    assert not [f for f in os.listdir(tmp_path) if f.startswith(".")]  # no temp file left


def test_read_luminance_cleans_negative_and_nonfinite(tmp_path):
    px = np.zeros((4, 4, 3), np.float32)
    px[0, 0] = -1.0
    px[1, 1] = np.nan
    px[2, 2] = np.inf
    px[3, 3] = [1.0, 2.0, 3.0]
    io.write_image(tmp_path / "s.exr", px, np.float32)
    lum = io.read_luminance(tmp_path / "s.exr")
    assert np.isfinite(lum).all() and (lum >= 0).all()
    assert lum[3, 3] == pytest.approx(0.2126 + 2 * 0.7152 + 3 * 0.0722, rel=1e-5)
    assert lum[2, 2] == lum.max()


def test_raw_video_truncated_is_an_error(tmp_path):
    with io.RawVideoWriter(tmp_path / "r.raw", 4, 3) as w:
        w.write(np.zeros((3, 4), np.uint16))
    with open(tmp_path / "r.raw", "ab") as f:
        f.write(b"\0" * 5)
    with pytest.raises(io.ImageFileError, match="r.raw.*1 frames \\+ 5 bytes"):
        io.read_raw_video(tmp_path / "r.raw", 4, 3)


def test_raw_writer_aborted_leaves_nothing(tmp_path):
    with pytest.raises(RuntimeError):
        with io.RawVideoWriter(tmp_path / "x.raw", 2, 2) as w:
            w.write(np.zeros((2, 2), np.uint16))
            raise RuntimeError("interrupted")
    assert list(tmp_path.iterdir()) == []


def test_missing_image_names_the_file(tmp_path):
    with pytest.raises(io.ImageFileError, match="nothere.exr"):
        io.read_luminance(tmp_path / "nothere.exr")


@pytest.mark.parametrize("name", ["Desk.exr", "MtTamWest.exr"])
def test_real_hdr_scene_to_raw(tmp_path, name):
    scene = io.read_luminance(shared_data("hdr", name))
    assert np.isfinite(scene).all() and (scene >= 0).all() and scene.max() > 30 * np.median(scene)
    p = profile.default(60, 80, seed=0)
    simulate.simulate_clip(scene, tmp_path / "c", p, frames=2, progress=False)
    raw = io.read_raw_video(tmp_path / "c" / "clip.raw", 80, 60)
    assert raw.shape == (2, 60, 80) and raw.max() <= 4095


def test_rgb_exr_roundtrip_channels_and_state(tmp_path, rng):
    v = (rng.random((3, 9, 11)) * 1e5).astype(np.float32)
    s = rng.integers(0, 255, (9, 11)).astype(np.uint8)
    io.write_exr(tmp_path / "c.exr", v, s)
    io.write_exr(tmp_path / "n.exr", v)
    v2, s2 = io.read_exr(tmp_path / "c.exr")
    v3, s3 = io.read_exr(tmp_path / "n.exr", shape=(9, 11))
    assert v2.shape == (3, 9, 11) and v2.dtype == np.float32
    assert np.array_equal(v2, v) and np.array_equal(s2, s) and np.array_equal(v3, v) and s3 is None
    # the file holds named channels R, G, B (+ state): any EXR reader sees the colour by name
    px = io.read_image(tmp_path / "c.exr")
    assert px.shape == (9, 11, 4)
    assert np.array_equal(px[:, :, 0], v[0]) and np.array_equal(px[:, :, 2], v[2])
    assert np.array_equal(px[:, :, 3], s.astype(np.float32))
    assert io.exr_channels(tmp_path / "c.exr") == 3 and io.exr_channels(tmp_path / "n.exr") == 3


def undated(path) -> bytes:
    """An EXR file's bytes without the DateTime attribute OpenImageIO stamps into every file it writes."""
    return re.sub(rb"\d{4}:\d\d:\d\d \d\d:\d\d:\d\d", b"", path.read_bytes())


def test_monochrome_exr_is_one_y_channel_as_before(tmp_path, rng):
    """A (H, W) frame is the file `write_image` makes of channel Y (+ state): the monochrome files are
    unchanged by the colour layout."""
    v = (rng.random((7, 5)) * 1e3).astype(np.float32)
    s = rng.integers(0, 255, (7, 5)).astype(np.uint8)
    io.write_exr(tmp_path / "a.exr", v)
    io.write_image(tmp_path / "b.exr", v, np.float32, ["Y"])
    io.write_exr(tmp_path / "c.exr", v, s)
    io.write_image(tmp_path / "d.exr", np.stack([v, s.astype(np.float32)], -1), np.float32, ["Y", "state"])
    assert undated(tmp_path / "a.exr") == undated(tmp_path / "b.exr")
    assert undated(tmp_path / "c.exr") == undated(tmp_path / "d.exr")
    assert io.read_exr(tmp_path / "c.exr")[0].shape == (7, 5) and io.exr_channels(tmp_path / "c.exr") == 1


def test_write_exr_refuses_bad_shapes(tmp_path):
    with pytest.raises(ValueError, match=r"x.exr.*\(3, H, W\)"):
        io.write_exr(tmp_path / "x.exr", np.zeros((4, 5, 6), np.float32))
    with pytest.raises(ValueError, match="x.exr.*state"):
        io.write_exr(tmp_path / "x.exr", np.zeros((3, 5, 6), np.float32), np.zeros((5, 5), np.uint8))
    assert not list(tmp_path.iterdir())


def test_read_rgb_planes_luminance_and_cleaning(tmp_path):
    px = np.zeros((4, 5, 4), np.float32)
    px[..., 3] = 0.5                                 # alpha: ignored
    px[0, 0, :3] = [-1.0, 2.0, 3.0]
    px[1, 1, 1] = np.nan
    px[2, 2, 2] = np.inf
    px[3, 3, :3] = [1.0, 2.0, 7.0]
    io.write_image(tmp_path / "s.exr", px, np.float32, ["R", "G", "B", "A"])
    rgb = io.read_rgb(tmp_path / "s.exr")
    assert rgb.shape == (3, 4, 5) and rgb.dtype == np.float32 and rgb.flags.c_contiguous
    assert rgb[:, 3, 3].tolist() == [1.0, 2.0, 7.0]
    assert rgb[:, 0, 0].tolist() == [0.0, 2.0, 3.0]                 # negative clamped
    assert rgb[1, 1, 1] == 0.0 and rgb[2, 2, 2] == 7.0              # NaN -> 0, +Inf -> largest finite value
    with pytest.raises(io.ImageFileError, match=r"s.exr: 2 of 60 values are NaN or infinite"):
        io.read_rgb(tmp_path / "s.exr", nonfinite="error")
    # without non-finite values, its Rec. 709 luminance is read_luminance's
    px[1, 1, 1] = px[2, 2, 2] = 0.25
    px[0, 0, 0] = 0.0
    io.write_image(tmp_path / "t.exr", px, np.float32, ["R", "G", "B", "A"])
    lum = np.tensordot(io.LUMA_709, io.read_rgb(tmp_path / "t.exr").astype(np.float64), 1)
    assert np.allclose(lum, io.read_luminance(tmp_path / "t.exr"), rtol=1e-6)


def test_read_rgb_of_a_gray_file_is_three_equal_planes(tmp_path, rng):
    g = rng.integers(0, 65535, (6, 7)).astype(np.uint16)
    io.write_image(tmp_path / "g.png", g, np.uint16)
    rgb = io.read_rgb(tmp_path / "g.png")
    assert rgb.shape == (3, 6, 7)
    assert np.allclose(rgb[0], g / 65535.0, atol=1e-7)
    assert np.array_equal(rgb[0], rgb[1]) and np.array_equal(rgb[0], rgb[2])
    with pytest.raises(io.ImageFileError, match="nothere.png"):
        io.read_rgb(tmp_path / "nothere.png")
    with pytest.raises(ValueError, match="nonfinite"):
        io.read_rgb(tmp_path / "g.png", nonfinite="ignore")
