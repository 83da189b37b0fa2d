"""Every `nrhdr` command on a colour clip or colour profile (docs/COLOUR.md "Commands on colour clips"): it
works, or it refuses before any work with an error naming the option or file. Commands already covered
elsewhere: simulate and profile (tests/test_colour_simulate.py), demo and warmup (tests/test_colour_demo.py),
hdr10 (tests/test_colour_output.py, tests/test_cli_colour_report.py), calibrate and simulate-flats with --cfa
(tests/test_colour_crosstalk.py)."""
from __future__ import annotations

import json

import numpy as np
import pytest

from gst_plugins.cli import main
from nrhdr_core import batch, chain, io, simulate
from nrhdr_core import profile as profiles

H, W, N = 16, 24, 2


@pytest.fixture(scope="module")
def colour_clip(tmp_path_factory):
    """A simulated rggb clip folder (clip.json with the cfa, camera.json, RGB truth)."""
    d = tmp_path_factory.mktemp("colour") / "clip"
    prof = profiles.default(H, W, seed=1, cfa="rggb")
    simulate.simulate_clip(simulate.synthetic_rgb_scene(), d, prof, frames=N, progress=False)
    return d


@pytest.fixture(scope="module")
def mono_twin(colour_clip, tmp_path_factory):
    """A monochrome profile of the colour clip's sensor (the same mask and size): only the cfa differs."""
    col = profiles.load(colour_clip / "camera.json")
    p = tmp_path_factory.mktemp("mono") / "mono.json"
    profiles.save(profiles.make(col.mask, nd=col.nd, l_min=col.l_min), p)
    assert profiles.load(p).cfa == "none"
    return p


def refused(capsys, argv, *words) -> str:
    """main(argv) exits 2 with every one of `words` in its error."""
    assert main([str(x) for x in argv]) == 2
    err = capsys.readouterr().err
    for w in words:
        assert w in err, err
    return err


# ---- batch ---------------------------------------------------------------------------------------------------
def test_batch_writes_the_colour_chain_rgb_frames(colour_clip, tmp_path):
    """nrhdr batch on a colour clip: R, G, B + state EXR frames, each chain.process_frame's colour frame."""
    out = tmp_path / "exr"
    assert main(["batch", str(colour_clip), "-o", str(out), "--workers", "0", "--method", "preview",
                 "--no-progress"]) == 0
    src = batch.open_source(colour_clip)
    prof = profiles.load(colour_clip / "camera.json")
    for i in range(N):
        v, st = io.read_exr(out / f"frame_{i:05d}.exr")
        want, want_st = chain.process_frame(batch.read_frame(src.raw, W, H, i), prof,
                                            chain.ChainSettings(method="preview"))
        assert v.shape == (3, H, W)
        np.testing.assert_array_equal(v, want)
        np.testing.assert_array_equal(st, want_st)


@pytest.mark.parametrize("args, words", [
    (["--png"], ["--png writes GRAY8", "cfa rggb"]),
    (["--temporal", "on"], ["temporal 'on'", "cfa rggb"]),
    (["--method", "linear"], ["method 'linear'", "cfa rggb"]),
])
def test_batch_refuses_what_the_colour_chain_does_not_do(colour_clip, tmp_path, capsys, args, words):
    out = tmp_path / "exr"
    refused(capsys, ["batch", colour_clip, "-o", out, "--workers", "0", "--no-progress", *args], *words)
    assert not list(out.glob("frame_*")) if out.exists() else True


def test_batch_refuses_a_profile_or_calibration_of_another_cfa(colour_clip, mono_twin, tmp_path, capsys):
    """A monochrome --profile for a clip whose clip.json records a Bayer mosaic, and a monochrome
    --crosstalk-profile of the same sensor for a colour stream: refused, naming both."""
    out = tmp_path / "exr"
    refused(capsys, ["batch", colour_clip, "-o", out, "--profile", mono_twin, "--workers", "0", "--no-progress"],
            f"--profile {mono_twin}", "cfa 'none'", "clip.json records a Bayer rggb sensor")
    refused(capsys, ["batch", colour_clip, "-o", out, "--crosstalk-profile", mono_twin, "--workers", "0",
                     "--no-progress"], f"--crosstalk-profile {mono_twin}", "cfa 'rggb'")
    assert not list(out.glob("frame_*")) if out.exists() else True


def test_batch_refuses_a_monochrome_profile_for_colour_stills(colour_clip, mono_twin, tmp_path, capsys):
    """A still sequence whose folder's camera.json is a colour profile, given a monochrome --profile: refused
    naming both (a folder and a file pattern); with its own profile it is reconstructed in colour."""
    stills = tmp_path / "stills"
    stills.mkdir()
    src = batch.open_source(colour_clip)
    for i in range(N):
        io.write_image(stills / f"frame_{i:05d}.png", batch.read_frame(src.raw, W, H, i), np.uint16)
    profiles.save(profiles.load(colour_clip / "camera.json"), stills / "camera.json")
    out = tmp_path / "exr"
    for loc in (stills, stills / "frame_%05d.png"):
        refused(capsys, ["batch", loc, "-o", out, "--profile", mono_twin, "--workers", "0", "--no-progress"],
                f"--profile {mono_twin}", f"{stills / 'camera.json'} records a Bayer rggb sensor")
    assert not out.exists() or not list(out.glob("frame_*"))
    assert main(["batch", str(stills), "-o", str(out), "--workers", "0", "--method", "preview", "--no-progress"]) == 0
    assert io.read_exr(out / "frame_00000.exr")[0].shape == (3, H, W)


# ---- hdr10 ---------------------------------------------------------------------------------------------------
def test_hdr10_refuses_a_monochrome_method_or_profile_for_a_colour_clip(colour_clip, mono_twin, tmp_path, capsys):
    out = tmp_path / "v.mp4"
    refused(capsys, ["hdr10", colour_clip, out, "--method", "nearest", "--no-progress"], "method 'nearest'",
            "cfa rggb")
    refused(capsys, ["hdr10", colour_clip, out, "--profile", mono_twin, "--no-progress"],
            "clip.json records a Bayer rggb sensor")
    assert not list(tmp_path.iterdir())


# ---- compare -------------------------------------------------------------------------------------------------
def test_compare_scores_colour_frames_on_their_luminance(colour_clip, tmp_path, capsys):
    """EXR frames equal to the RGB truth: no pixel off; G four times too bright: every pixel whose luminance
    is not capped at the white is off by more than a stop (G weighs 0.7152: 4 G gives >= 3.1 x L); the JSON
    says the values scored are the luminance."""
    truth_dir = colour_clip / "truth"
    same, greener = tmp_path / "same", tmp_path / "greener"
    for d in (same, greener):
        d.mkdir()
    white = profiles.load(colour_clip / "camera.json").white
    lum = []
    for f in sorted(truth_dir.glob("frame_*.exr")):
        t, _ = io.read_exr(f)
        io.write_exr(same / f.name, t)
        g = t.copy()
        g[1] *= 4
        io.write_exr(greener / f.name, g)
        lum.append(0.2126 * t[0] + 0.7152 * t[1] + 0.0722 * t[2])
    lum = np.stack(lum)
    assert main(["compare", str(same), str(greener), "--truth", str(truth_dir), "--profile",
                 str(colour_clip / "camera.json"), "--json"]) == 0
    rep = json.loads(capsys.readouterr().out)
    assert rep["values"] == "luminance"
    r_same, r_green = rep["results"][str(same)], rep["results"][str(greener)]
    assert r_same["frames"] == N and r_same["all"]["off_1stop"] == 0
    # luminance >= 1 (the floor) and 3.1 x it below the white: off by log2(3.1) > 1 stop
    assert r_green["all"]["off_1stop"] >= int(((lum >= 1) & (lum * 3.2 < white)).sum())
    assert r_green["all"]["log2_psnr"] < r_same["all"]["log2_psnr"]


def test_compare_refuses_frames_of_the_other_kind(colour_clip, mono_twin, tmp_path, capsys):
    """A monochrome profile for RGB truth, and grey result frames for RGB truth: refused naming the file."""
    truth_dir = colour_clip / "truth"
    grey = tmp_path / "grey"
    grey.mkdir()
    t, _ = io.read_exr(truth_dir / "frame_00000.exr")
    io.write_exr(grey / "frame_00000.exr", t[1])
    refused(capsys, ["compare", grey, "--truth", truth_dir, "--profile", mono_twin],
            str(truth_dir / "frame_00000.exr"), "colour (R, G, B) truth frame", "monochrome")
    refused(capsys, ["compare", grey, "--truth", truth_dir, "--profile", colour_clip / "camera.json"],
            str(grey / "frame_00000.exr"), "a grey (Y) frame", "colour (R, G, B)")


# ---- calibrate, simulate-flats -------------------------------------------------------------------------------
def test_calibrate_refuses_a_sweep_of_another_cfa(tmp_path, capsys):
    """A sweep whose truth.json (nrhdr simulate-flats) records a Bayer sensor, calibrated without --cfa, or a
    monochrome sweep given as --colour-flats: refused before any frame is read, naming the folder."""
    colour, mono = tmp_path / "colour", tmp_path / "mono"
    for d, t in ((colour, {"cfa": "rggb"}), (mono, {"nd": 6.35})):
        d.mkdir()
        (d / "truth.json").write_text(json.dumps(t))
    out = tmp_path / "cam.json"
    refused(capsys, ["calibrate", colour, "-o", out, "-q"], f"FLATS {colour}", "Bayer rggb sensor",
            "give --cfa rggb")
    refused(capsys, ["calibrate", colour, "--cfa", "rggb", "--colour-flats", mono, "-o", out, "-q"],
            f"--colour-flats {mono}", "a monochrome sensor", "give --cfa none")
    assert not out.exists()


def test_simulate_flats_colour_sweep(colour_clip, tmp_path, capsys):
    """simulate-flats --cfa --light writes a sweep whose truth.json and printed calibrate command carry the cfa;
    with a colour --profile the cfa comes from it, another --cfa is refused."""
    out = tmp_path / "fl"
    assert main(["simulate-flats", str(out), "--cfa", "grbg", "--light", "1,0.5,0.25", "--width", "8", "--height",
                 "8", "--exposures", "6", "--frames", "2", "-q"]) == 0
    truth = json.loads((out / "truth.json").read_text())
    assert truth["cfa"] == "grbg" and truth["light"] == [1.0, 0.5, 0.25]
    assert "--cfa grbg" in capsys.readouterr().out
    prof = colour_clip / "camera.json"
    assert main(["simulate-flats", str(tmp_path / "p"), "--profile", str(prof), "--exposures", "6", "--frames", "2",
                 "-q"]) == 0
    assert json.loads((tmp_path / "p" / "truth.json").read_text())["cfa"] == "rggb"
    refused(capsys, ["simulate-flats", tmp_path / "q", "--profile", prof, "--cfa", "bggr", "-q"], "--cfa bggr",
            "'rggb'")
    assert not (tmp_path / "q").exists()


def test_simulate_flats_refuses_coloured_light_for_a_monochrome_sensor(tmp_path, capsys):
    refused(capsys, ["simulate-flats", tmp_path / "fl", "--light", "1,0.2,0.1", "--width", 8, "--height", 8, "-q"],
            "coloured light", "cfa is 'none'")
    assert not (tmp_path / "fl").exists()


# ---- recover -------------------------------------------------------------------------------------------------
def test_recover_keeps_a_colour_recording_colour(colour_clip, tmp_path):
    """A killed recording of a colour clip becomes a colour clip folder: camera.json and clip.json keep the
    cfa, and batch reads it with the colour profile."""
    out = tmp_path / "rec"
    out.mkdir()
    raw = (colour_clip / "clip.raw").read_bytes()
    (out / ".clip.raw.part").write_bytes(raw + b"\x07" * 100)
    (out / ".clip.json.part").write_text(json.dumps({"source_clip_json": str(colour_clip / "clip.json"),
                                                     "profile": str(colour_clip / "camera.json")}))
    assert main(["recover", str(out)]) == 0
    assert (out / "clip.raw").read_bytes() == raw
    assert json.loads((out / "clip.json").read_text())["cfa"] == "rggb"
    assert profiles.load(out / "camera.json").cfa == "rggb"
    assert batch.open_source(out).frames == N
