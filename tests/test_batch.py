"""`nrhdr batch` (nrhdr_core/batch.py, chain.py; docs/BATCH.md), run as a subprocess like a user would, on a
tiny generated clip (64x48): bit-identity with the GStreamer chain (pipelines/raw_to_exr.sh), resume, a
truncated raw file, Ctrl-C."""
from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from conftest import make_test_clip

ROOT = Path(__file__).resolve().parents[1]
PIPELINES = ROOT / "pipelines"


def batch_env():
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join([str(ROOT)] + [p for p in env.get("PYTHONPATH", "").split(os.pathsep)
                                                       if p])
    return env


def nrhdr_batch(*args, env=None, timeout=300):
    p = subprocess.run([sys.executable, "-m", "gst_plugins.cli", "batch", *map(str, args), "--no-progress"],
                       env=env or batch_env(), capture_output=True, text=True, timeout=timeout)
    return p.returncode, p.stdout + p.stderr


def exr_frames(folder):
    return sorted(Path(folder).glob("frame_*.exr"))


def assert_same_exr(a, b):
    """Bit for bit: the pixel data of every channel (Y float32 bits, state), and the channel layout. (The
    files' bytes differ only in OpenEXR's capDate header attribute, a time stamp.)"""
    import OpenImageIO as oiio
    ba, bb = oiio.ImageBuf(str(a)), oiio.ImageBuf(str(b))
    sa, sb = ba.spec(), bb.spec()
    assert (sa.width, sa.height, list(sa.channelnames), str(sa.format)) == \
        (sb.width, sb.height, list(sb.channelnames), str(sb.format)), (a, b)
    pa, pb = np.asarray(ba.get_pixels(oiio.FLOAT)), np.asarray(bb.get_pixels(oiio.FLOAT))
    assert pa.shape == pb.shape
    diff = pa.view(np.uint32) != pb.view(np.uint32)
    assert not diff.any(), f"{a} and {b} differ in {int(diff.sum())} values"


@pytest.fixture(scope="module")
def clip6(tmp_path_factory):
    """64x48 x 6 frames: dark, valid and clipped pixels of both kinds in every frame."""
    return make_test_clip(tmp_path_factory.mktemp("batch") / "clip", frames=6)


@pytest.mark.gst
def test_bit_identical_to_gstreamer_chain_on_two_local_workers(clip6, tmp_path, gst_subprocess_env):
    """nrhdr batch (LocalCluster, 2 worker processes) == pipelines/raw_to_exr.sh with the same settings,
    every frame, every pixel and state byte. Batch runs first: it fills numba's cache in a subprocess, so
    both sides run cached kernels (chain.warmup / batch.warm_cache explain why that matters)."""
    d, prof, raws = clip6
    rc, out = nrhdr_batch(d, "-o", tmp_path / "batch", "--workers", "2", env=gst_subprocess_env)
    assert rc == 0, out
    assert "wrote 6 frames" in out
    env = dict(gst_subprocess_env, METHOD="fse", PRESET="fast")
    p = subprocess.run(["bash", str(PIPELINES / "raw_to_exr.sh"), str(d), str(tmp_path / "gst")], env=env,
                       capture_output=True, text=True, timeout=180)
    assert p.returncode == 0, p.stdout + p.stderr
    a, b = exr_frames(tmp_path / "batch"), exr_frames(tmp_path / "gst")
    assert [f.name for f in a] == [f.name for f in b] == [f"frame_{i:05d}.exr" for i in range(len(raws))]
    for fa, fb in zip(a, b):
        assert_same_exr(fa, fb)
    # and the chain really reconstructed something in every frame (the comparison is not vacuous)
    from nrhdr_core import io, validity
    for f in a:
        _, st = io.read_exr(f)
        assert 0 < ((st & validity.RECONSTRUCTED) != 0).mean() < 1


@pytest.mark.gst
def test_bit_identical_with_other_settings_in_a_plain_loop(clip6, tmp_path, gst_subprocess_env):
    """Other element settings (validity mode 'all', method preview) through the same core function in the
    no-Dask loop (--workers 0) equal the pipeline with MODE=all METHOD=preview; the tone-mapped PNGs
    (--png, --exposure, --operator log) equal pipelines/raw_to_png.sh's pixels. With the local operator the
    first frame's too (the element smooths the operator's statistics over the frames after it)."""
    d, _, raws = clip6
    rc, out = nrhdr_batch(d, "-o", tmp_path / "batch", "--workers", "0", "--mode", "all", "--method",
                          "preview", "--png", "--exposure", "1.5", "--operator", "log", env=gst_subprocess_env)
    assert rc == 0, out
    env = dict(gst_subprocess_env, METHOD="preview", MODE="all")
    p = subprocess.run(["bash", str(PIPELINES / "raw_to_exr.sh"), str(d), str(tmp_path / "gst")], env=env,
                       capture_output=True, text=True, timeout=180)
    assert p.returncode == 0, p.stdout + p.stderr
    a, b = exr_frames(tmp_path / "batch"), exr_frames(tmp_path / "gst")
    assert len(a) == len(b) == len(raws)
    for fa, fb in zip(a, b):
        assert_same_exr(fa, fb)
    env["EXPOSURE"] = "1.5"
    from nrhdr_core import io
    for operator, frames in (("log", len(raws)), ("local", 1)):
        png = tmp_path / f"png_{operator}"
        p = subprocess.run(["bash", str(PIPELINES / "raw_to_png.sh"), str(d), str(png)],
                           env=dict(env, OPERATOR=operator), capture_output=True, text=True, timeout=180)
        assert p.returncode == 0, p.stdout + p.stderr
        pngs = sorted(png.glob("frame_*.png"))
        assert len(pngs) == len(raws)
        if operator == "local":
            rc, out = nrhdr_batch(d, "-o", tmp_path / "batch_local", "--workers", "0", "--mode", "all",
                                  "--method", "preview", "--png", "--exposure", "1.5", "--frames", "1",
                                  env=gst_subprocess_env)
            assert rc == 0, out
        for f in pngs[:frames]:
            ours = io.read_image(tmp_path / ("batch" if operator == "log" else "batch_local") / f.name, np.uint8)
            assert np.array_equal(ours, io.read_image(f, np.uint8)), (operator, f.name)
            assert ours.max() > ours.min()


def test_resume_skips_complete_frames_and_refuses_other_settings(clip6, tmp_path):
    d, _, raws = clip6
    out = tmp_path / "out"
    rc, log = nrhdr_batch(d, "-o", out, "--workers", "0", "--method", "preview", "--png")
    assert rc == 0, log
    n = len(raws)
    ref = tmp_path / "ref"
    ref.mkdir()
    for f in out.glob("frame_*"):
        (ref / f.name).write_bytes(f.read_bytes())
    assert len(list(ref.iterdir())) == 2 * n
    manifest = json.loads((out / "batch.json").read_text())
    assert manifest["settings"]["method"] == "preview" and manifest["png"] is True
    # a killed run: two frames missing (one only its PNG), its stage folder left behind; a user's file that
    # looks like a temp name of an atomic writer is not ours to delete
    (out / "frame_00001.exr").unlink()
    (out / "frame_00004.png").unlink()
    stage = out / ".frames.nrtmp-999999-0123abcd"
    stage.mkdir()
    (stage / "frame_00002.exr").write_bytes(b"partial")
    (out / ".frame_00002.abc123.exr").write_bytes(b"the user's")
    kept = {f.name: f.stat().st_mtime_ns for f in out.glob("frame_*")}
    rc, log = nrhdr_batch(d, "-o", out, "--workers", "0", "--method", "preview", "--png")
    assert rc == 0, log
    assert f"{n - 2} already done, 2 to compute" in log
    for name, mtime in kept.items():   # complete frames are not rewritten
        if not name.startswith(("frame_00001.", "frame_00004.")):
            assert (out / name).stat().st_mtime_ns == mtime, name
    assert not stage.exists() and not list(out.glob(".*nrtmp*"))
    assert (out / ".frame_00002.abc123.exr").read_bytes() == b"the user's"
    (out / ".frame_00002.abc123.exr").unlink()
    from nrhdr_core import io
    for f in ref.iterdir():            # the recomputed frames equal the first run's
        if f.suffix == ".exr":
            assert_same_exr(out / f.name, f)
        else:
            assert np.array_equal(io.read_image(out / f.name, np.uint8), io.read_image(f, np.uint8))
    # other settings: refused (names what differs), exit 2, nothing touched; --force recomputes
    before = {f.name: f.stat().st_mtime_ns for f in out.iterdir()}
    rc, log = nrhdr_batch(d, "-o", out, "--workers", "0", "--method", "nearest", "--png")
    assert rc == 2, log
    assert "--force" in log and "method" in log
    assert {f.name: f.stat().st_mtime_ns for f in out.iterdir()} == before
    rc, log = nrhdr_batch(d, "-o", out, "--workers", "0", "--method", "nearest", "--png", "--force")
    assert rc == 0, log
    assert json.loads((out / "batch.json").read_text())["settings"]["method"] == "nearest"


def test_refuses_a_folder_written_by_something_else(clip6, tmp_path):
    d, _, _ = clip6
    out = tmp_path / "theirs"
    out.mkdir()
    (out / "frame_00000.exr").write_bytes(b"not ours")
    rc, log = nrhdr_batch(d, "-o", out, "--workers", "0", "--method", "preview")
    assert rc == 2, log
    assert "not written by nrhdr batch" in log and "--force" in log
    assert (out / "frame_00000.exr").read_bytes() == b"not ours"


def test_a_second_run_into_the_same_folder_is_refused(clip6, tmp_path):
    """The lock of the output folder (held here as by a running `nrhdr batch` or pipelines/raw_to_exr.sh):
    refused with exit 2 naming the holder; the folder is not touched (the running one's temporary files
    stay). After the holder ends, the run goes ahead."""
    from nrhdr_core import outputs
    d, _, raws = clip6
    out = tmp_path / "out"
    out.mkdir()
    theirs = out / ".frames.nrtmp-1-0123abcd"
    with outputs.lock(out):
        theirs.mkdir()
        rc, log = nrhdr_batch(d, "-o", out, "--workers", "0", "--method", "preview")
        assert rc == 2, log
        assert f"{out.resolve()} is being written by another command (pid {os.getpid()}: " in log, log
        assert theirs.is_dir() and not (out / "batch.json").exists()
    rc, log = nrhdr_batch(d, "-o", out, "--workers", "0", "--method", "preview")
    assert rc == 0, log
    assert len(exr_frames(out)) == len(raws) and not theirs.exists()


def test_bad_numbers_and_another_sensors_calibration_are_refused(clip6, tmp_path):
    from nrhdr_core import profile
    d, prof, _ = clip6
    for opt, val in (("--exposure", "nan"), ("--frames", "0"), ("--workers", "-1"), ("--white", "inf"),
                     ("--threads-per-worker", "1.5")):
        rc, log = nrhdr_batch(d, "-o", tmp_path / "o", opt, val)
        assert rc == 2 and opt in log, (opt, log)
    other = profile.default(prof.height, prof.width, seed=99)      # same size, another mask
    profile.save(other, tmp_path / "other.json")
    rc, log = nrhdr_batch(d, "-o", tmp_path / "o", "--workers", "0", "--crosstalk-profile", tmp_path / "other.json")
    assert rc == 2 and "another sensor" in log and "other.json" in log, log
    assert not (tmp_path / "o").exists()


def test_truncated_raw_file_fails_that_frame_only(clip6, tmp_path):
    """The last frame is short: it is reported by number and file, exit status 1, the other frames are
    written (on 2 Dask worker processes: the error comes back from a worker)."""
    d, prof, raws = clip6
    clip = tmp_path / "clip"
    clip.mkdir()
    for f in d.iterdir():
        if f.is_file():
            (clip / f.name).write_bytes(f.read_bytes())
    size = (clip / "clip.raw").stat().st_size
    os.truncate(clip / "clip.raw", size - 100)
    out = tmp_path / "out"
    rc, log = nrhdr_batch(clip, "-o", out, "--workers", "2", "--method", "preview")
    assert rc == 1, log
    last = len(raws) - 1
    raw_path = str((clip / "clip.raw").resolve())
    assert f"frame {last} of {raw_path}" in log and "truncated" in log, log
    assert [f.name for f in exr_frames(out)] == [f"frame_{i:05d}.exr" for i in range(last)]
    from nrhdr_core import io
    for i in range(last):   # the good frames are the chain's output: Eq. 3 on measured pixels
        v, st = io.read_exr(out / f"frame_{i:05d}.exr")
        known = (st & 0x0F) == 0
        exp = (raws[i].astype(np.float64) - prof.black_level) * np.where(prof.mask, prof.nd, 1.0)
        np.testing.assert_allclose(v[known], exp[known], rtol=1e-6)


def _session_pids(sid):
    p = subprocess.run(["pgrep", "-s", str(sid)], capture_output=True, text=True)
    return [int(x) for x in p.stdout.split()]


def _default_sigint():
    """Popen preexec: Ctrl-C at its default action, as in a user's terminal, even when the tests run with
    SIGINT ignored (started in the background by a non-interactive shell: children inherit SIG_IGN)."""
    import signal as s
    s.signal(s.SIGINT, s.SIG_DFL)
    s.pthread_sigmask(s.SIG_UNBLOCK, [s.SIGINT])


@pytest.mark.skipif(sys.platform != "linux", reason="process-group signals and pgrep -s")
@pytest.mark.parametrize("storm,sig", [(False, signal.SIGINT), (True, signal.SIGINT), (False, signal.SIGTERM)])
def test_ctrl_c_stops_cleanly_and_the_rerun_resumes(tmp_path, storm, sig):
    """SIGINT to the whole process group (a terminal's Ctrl-C), or SIGTERM to the command only (a service
    manager), during a 2-worker run: exit 130 / 143, no process of the run is left, only complete files (no
    temp files, no lock file); the same command then finishes the rest, and every frame equals the chain's
    output. `storm`: SIGINT again and again for 50 ms (Ctrl-C pressed repeatedly): the later ones must not
    break off the clean-up."""
    d, prof, raws = make_test_clip(tmp_path / "clip", width=96, height=72, frames=60)
    out = tmp_path / "out"
    cmd = [sys.executable, "-m", "gst_plugins.cli", "batch", str(d), "-o", str(out), "--workers", "2",
           "--preset", "best", "--no-progress"]
    p = subprocess.Popen(cmd, env=batch_env(), stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                         start_new_session=True, preexec_fn=_default_sigint)
    try:
        t0 = time.monotonic()
        while len(exr_frames(out)) < 3 and p.poll() is None and time.monotonic() - t0 < 240:
            time.sleep(0.05)
        assert p.poll() is None, "the run ended before it could be interrupted"
        t1 = time.monotonic()
        if sig == signal.SIGINT:
            os.killpg(p.pid, signal.SIGINT)
        else:
            p.send_signal(sig)
        while storm and time.monotonic() < t1 + 0.05:
            os.killpg(p.pid, signal.SIGINT)
        log = p.communicate(timeout=60)[0]
    finally:
        if p.poll() is None:
            os.killpg(p.pid, signal.SIGKILL)
    assert p.returncode == 128 + sig, log
    assert "interrupted" in log and "Traceback" not in log, log
    t0 = time.monotonic()
    while _session_pids(p.pid) and time.monotonic() - t0 < 20:   # the resource tracker exits last
        time.sleep(0.2)
    assert _session_pids(p.pid) == []
    done = exr_frames(out)
    assert 3 <= len(done) < len(raws)
    assert not [f for f in out.iterdir() if f.name.startswith(".")]
    assert sorted(f.name for f in tmp_path.iterdir()) == ["clip", "out"]     # no lock file
    from nrhdr_core import io
    for f in done:   # complete files
        v, st = io.read_exr(f)
        assert v.shape == (72, 96) and st is not None
    rc, log = nrhdr_batch(d, "-o", out, "--workers", "0", "--preset", "best")
    assert rc == 0, log
    assert f"{len(done)} already done, {len(raws) - len(done)} to compute" in log
    from nrhdr_core import chain, profile
    prof = profile.load(d / "camera.json")
    for i in (0, len(raws) - 1):   # one frame from before the interruption, one from the rerun
        v, st = chain.process_frame(raws[i], prof, chain.ChainSettings(preset="best"))
        fv, fst = io.read_exr(out / f"frame_{i:05d}.exr")
        assert np.array_equal(fv.view(np.uint32), v.view(np.uint32)) and np.array_equal(fst, st), i


def test_existing_scheduler_with_data_transfer(clip6, tmp_path):
    """--scheduler ADDRESS (a cluster started elsewhere, here by this test) with --transfer data: the
    client sends raw frames and writes the files the worker returns; same frames as the chain in-process."""
    from nrhdr_core import batch, chain, io, profile
    d, _, raws = clip6
    out = tmp_path / "out"
    with batch.local_client(1, 1) as client:
        addr = client.scheduler.address
        rc, log = nrhdr_batch(d, "-o", out, "--scheduler", addr, "--transfer", "data", "--method", "preview",
                              "--png")
    assert rc == 0, log
    assert "oversubscribed" not in log
    prof = profile.load(d / "camera.json")
    s = chain.ChainSettings(method="preview")
    for i, raw in enumerate(raws):
        v, st = chain.process_frame(raw, prof, s)
        fv, fst = io.read_exr(out / f"frame_{i:05d}.exr")
        assert np.array_equal(fv.view(np.uint32), v.view(np.uint32)) and np.array_equal(fst, st), i
        png = io.read_image(out / f"frame_{i:05d}.png", np.uint8)[:, :, 0]
        assert np.array_equal(png, chain.tonemap_frame(v, prof, s)), i
    assert not [f for f in out.iterdir() if f.name.startswith(".")]


@pytest.mark.gst
def test_given_crosstalk_calibration_equals_gstreamer(tmp_path, gst_subprocess_env):
    """A clip of a sensor with crosstalk, calibrated from simulated flats (`nrhdr calibrate`), the
    calibration given separately (--crosstalk-profile = nrcrosstalk profile=): same frames as the
    GStreamer chain, in kernel mode (the default)."""
    from gst_plugins import cli
    from nrhdr_core import calibration, crosstalk, profile, scene, simulate
    prof = profile.default(48, 64, seed=4)
    model = crosstalk.sensor_model_preset("prototype", 48, 64, seed=2)
    simulate.simulate_clip(scene.synthetic_hdr_scene(180, 240, seed=3), tmp_path / "clip", prof, frames=3,
                           seed=5, sensor_model=model, progress=False)
    calibration.simulate_flats(tmp_path / "flats", prof, model, exposures=calibration.default_exposures(16),
                               frames_per_exposure=2, seed=6, progress=False)
    cal = tmp_path / "cal" / "cam.json"
    assert cli.main(["calibrate", str(tmp_path / "flats"), "--mask", str(tmp_path / "flats" / "mask.png"),
                     "-o", str(cal), "--json", "-q", "--no-plots"]) == 0
    clip = tmp_path / "clip"
    rc, log = nrhdr_batch(clip, "-o", tmp_path / "batch", "--workers", "0", "--crosstalk-profile", cal,
                          "--method", "preview", env=gst_subprocess_env)
    assert rc == 0, log
    cmd = [sys.executable, "-m", "gst_plugins.cli", "launch", "-q", "filesrc", f"location={clip / 'clip.raw'}",
           "!", "rawvideoparse", "format=gray16-le", "width=64", "height=48", "framerate=30/1",
           "plane-strides=<128>", "!", "nrvalidity", f"profile={clip / 'camera.json'}", "!", "nrcrosstalk",
           f"profile={cal}", "!", "nrreconstruct", "method=preview", "!", "nrexrsink", "write-state=true",
           f"location={tmp_path / 'gst'}/frame_%05d.exr"]
    p = subprocess.run(cmd, env=gst_subprocess_env, capture_output=True, text=True, timeout=180)
    assert p.returncode == 0, p.stdout + p.stderr
    a, b = exr_frames(tmp_path / "batch"), exr_frames(tmp_path / "gst")
    assert len(a) == len(b) == 3
    from nrhdr_core import chain, io
    raws = np.fromfile(clip / "clip.raw", "<u2").reshape(3, 48, 64)
    uncalibrated = profile.load(clip / "camera.json")
    for i, (fa, fb) in enumerate(zip(a, b)):
        assert_same_exr(fa, fb)
        # the calibration was applied: the chain without it gives other values
        v0, _ = chain.process_frame(raws[i], uncalibrated, chain.ChainSettings(method="preview"))
        assert not np.array_equal(io.read_exr(fa)[0], v0)
    # the accurate LUT setting reaches the chain: batch --crosstalk lut --crosstalk-lut full equals
    # nrcrosstalk mode=lut lut=full, and differs from the compact (default) table's frames
    rc, log = nrhdr_batch(clip, "-o", tmp_path / "batch_full", "--workers", "0", "--crosstalk-profile", cal,
                          "--crosstalk", "lut", "--crosstalk-lut", "full", "--method", "preview",
                          env=gst_subprocess_env)
    assert rc == 0, log
    cmd_full = list(cmd)
    i = cmd_full.index(f"profile={cal}")
    cmd_full[i + 1:i + 1] = ["mode=lut", "lut=full"]
    cmd_full[-1] = f"location={tmp_path / 'gst_full'}/frame_%05d.exr"
    p = subprocess.run(cmd_full, env=gst_subprocess_env, capture_output=True, text=True, timeout=180)
    assert p.returncode == 0, p.stdout + p.stderr
    a, b = exr_frames(tmp_path / "batch_full"), exr_frames(tmp_path / "gst_full")
    assert len(a) == len(b) == 3
    cal_prof = profile.load(cal)
    for i, (fa, fb) in enumerate(zip(a, b)):
        assert_same_exr(fa, fb)
    compact, _ = chain.process_frame(raws[0], uncalibrated, chain.ChainSettings(
        method="preview", crosstalk="lut", crosstalk_lut="compact"), crosstalk_profile=cal_prof)
    assert not np.array_equal(io.read_exr(a[0])[0], compact)


@pytest.mark.parametrize("field", ["raw", "profile"])
def test_clip_naming_a_file_outside_its_folder_is_refused_unless_allowed(tmp_path, field):
    """A clip folder from someone else whose clip.json names '../secret.raw' (or a profile outside) must not
    make batch read that file into its output."""
    from nrhdr_core import batch
    d, prof, raws = make_test_clip(tmp_path / "recv", frames=2)
    name = {"raw": "clip.raw", "profile": "camera.json"}[field]
    (d / name).rename(tmp_path / name)
    if field == "profile":
        (d / "camera_mask.png").rename(tmp_path / "camera_mask.png")
    doc = json.loads((d / "clip.json").read_text())
    doc[field] = f"../{name}"
    (d / "clip.json").write_text(json.dumps(doc))
    with pytest.raises(batch.BatchError, match=rf"'{field}'.*\.\./{name}"):
        batch.open_source(d)
    src = batch.open_source(d, allow_outside=True)
    assert (src.raw if field == "raw" else src.profile) == (tmp_path / name).resolve()
    rc, out = nrhdr_batch(d, "-o", tmp_path / "out", "--workers", "0", "--method", "nearest")
    assert rc == 2 and f"../{name}" in out and not (tmp_path / "out").exists(), out


# ---- raw still sequences ------------------------------------------------------------------------------------

def _stills(folder, raws, pattern="frame_{:05d}.tif"):
    from nrhdr_core import io
    folder.mkdir(parents=True)
    for i, r in enumerate(raws):
        io.write_image(folder / pattern.format(i), r, np.uint16)
    return folder


@pytest.mark.gst
def test_still_sequence_equals_the_stills_pipeline_and_the_raw_clip(clip6, tmp_path, gst_subprocess_env):
    """A folder of 16-bit TIFFs (the clip's frames) with its camera.json: nrhdr batch on a local Dask worker
    == pipelines/stills_to_hdr.sh (nrimagesrc ! chain ! nrexrsink) == nrhdr batch over the raw clip, every
    pixel's float32 bits and state byte; the rerun resumes, a changed file is another input."""
    import shutil
    d, _, raws = clip6
    stills = _stills(tmp_path / "stills", raws)
    for f in ("camera.json", "camera_mask.png"):
        shutil.copy(d / f, stills / f)
    rc, out = nrhdr_batch(stills, "-o", tmp_path / "batch", "--workers", "1", env=gst_subprocess_env)
    assert rc == 0, out
    assert "wrote 6 frames" in out
    p = subprocess.run(["bash", str(PIPELINES / "stills_to_hdr.sh"), str(stills), str(tmp_path / "gst")],
                       env=gst_subprocess_env, capture_output=True, text=True, timeout=180)
    assert p.returncode == 0, p.stdout + p.stderr
    rc, out = nrhdr_batch(d, "-o", tmp_path / "raw", "--workers", "0", env=gst_subprocess_env)
    assert rc == 0, out
    a, b, c = (exr_frames(tmp_path / n) for n in ("batch", "gst", "raw"))
    assert [f.name for f in a] == [f.name for f in b] == [f.name for f in c] == \
        [f"frame_{i:05d}.exr" for i in range(len(raws))]
    for fa, fb, fc in zip(a, b, c):
        assert_same_exr(fa, fb)
        assert_same_exr(fa, fc)
    # resume: nothing to do; a rewritten still is another input
    rc, out = nrhdr_batch(stills, "-o", tmp_path / "batch", "--workers", "0")
    assert rc == 0 and "skipped 6 done" in out, out
    os.utime(stills / "frame_00003.tif", ns=(1, 1))
    rc, out = nrhdr_batch(stills, "-o", tmp_path / "batch", "--workers", "0")
    assert rc == 2 and "other input or settings" in out and "files_sha256" in out, out


def test_still_sequence_pattern_frames_and_refusals(clip6, tmp_path):
    """A pattern with --start-index and --frames; a sequence without a profile, of 8-bit files, or asked
    for more frames than it has is refused (exit 2) naming the folder or file; a still whose pixels cannot
    be decoded fails that frame only, reported with its file (exit 1)."""
    from nrhdr_core import batch, io
    d, prof, raws = clip6
    stills = _stills(tmp_path / "s", raws, "img_{:03d}.png")
    src = batch.open_source(stills / "img_%03d.png", d / "camera.json", start_index=2, frames=3)
    assert (src.frames, src.width, src.height) == (3, 64, 48)
    assert np.array_equal(src.read(0), raws[2]) and src.frame_file(2).endswith("img_004.png")
    rc, out = nrhdr_batch(stills / "img_%03d.png", "--profile", d / "camera.json", "--start-index", "4", "-o",
                          tmp_path / "o1", "--workers", "0", "--method", "nearest")
    assert rc == 0 and "wrote 2 frames" in out, out
    rc, out = nrhdr_batch(stills, "-o", tmp_path / "o2", "--workers", "0")
    assert rc == 2 and "needs its camera profile: --profile" in out, out
    rc, out = nrhdr_batch(stills, "--profile", d / "camera.json", "--frames", "7", "-o", tmp_path / "o3")
    assert rc == 2 and "--frames 7 but the sequence has 6 files" in out, out
    eight = tmp_path / "eight"
    eight.mkdir()
    io.write_image(eight / "a.tif", raws[0] >> 8, np.uint8)
    rc, out = nrhdr_batch(eight, "--profile", d / "camera.json", "-o", tmp_path / "o4")
    assert rc == 2 and "a.tif: an 8-bit image" in out, out
    assert not (tmp_path / "o4").exists()
    (eight / "a.tif").unlink()
    rc, out = nrhdr_batch(eight, "--profile", d / "camera.json", "-o", tmp_path / "o4")
    assert rc == 2 and "not a clip folder (no clip.json) nor a still sequence" in out, out
    data = (stills / "img_001.png").read_bytes()
    (stills / "img_001.png").write_bytes(data[:len(data) // 2])
    rc, out = nrhdr_batch(stills, "--profile", d / "camera.json", "-o", tmp_path / "o5", "--workers", "0",
                          "--method", "nearest")
    assert rc == 1 and "failed: frame 1 of " + str(stills / "img_001.png") in out, out
    assert [f.name for f in exr_frames(tmp_path / "o5")] == [f"frame_{i:05d}.exr" for i in (0, 2, 3, 4, 5)]
