"""Recording routes stopped mid-recording (docs/RELIABILITY.md "Stop, crash and disk full"): the kept raw
frames equal the simulator's frames byte for byte (frame i of the recording = frame i of the clip), after
SIGINT (a terminal's Ctrl-C to the process group), SIGTERM (to the script only) and SIGKILL (then
`nrhdr recover` / the next run); and the launch wrapper's messages: no repeated error lines, a live display
that drops most frames says so, a foreign `python3` first on PATH does not break the pipelines."""
from __future__ import annotations

import json
import os
import re
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from conftest import make_test_clip

pytestmark = pytest.mark.gst

ROOT = Path(__file__).resolve().parents[1]
PIPELINES = ROOT / "pipelines"


@pytest.fixture(scope="module")
def clip(tmp_path_factory):
    """64x48, 7 frames (a prime: a looping recording's frame i is clip frame i % 7)."""
    return make_test_clip(tmp_path_factory.mktemp("stops") / "clip", frames=7, fps=20)


def _default_sigint():
    signal.signal(signal.SIGINT, signal.SIG_DFL)
    signal.pthread_sigmask(signal.SIG_UNBLOCK, [signal.SIGINT])


def _start(cmd, env):
    return subprocess.Popen([str(c) for c in cmd], env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                            text=True, start_new_session=True, preexec_fn=_default_sigint)


def _wait_size(path, nbytes, p, timeout=240):
    t0 = time.monotonic()
    while not (path.exists() and path.stat().st_size >= nbytes):
        assert p.poll() is None, p.communicate()[0]
        assert time.monotonic() - t0 < timeout, "the recording did not start"
        time.sleep(0.05)


def _stop(p, sig, group):
    try:
        if group:
            os.killpg(p.pid, sig)
        else:
            p.send_signal(sig)
        return p.communicate(timeout=60)[0]
    finally:
        if p.poll() is None:
            os.killpg(p.pid, signal.SIGKILL)
            p.wait()


def assert_frames_of_clip(raw_file, raws):
    """Every frame of `raw_file` is the clip's frame i % N, and the file holds whole frames only."""
    n, h, w = raws.shape
    data = Path(raw_file).read_bytes()
    assert len(data) % (2 * h * w) == 0, f"{raw_file}: {len(data)} bytes is not whole frames"
    got = np.frombuffer(data, "<u2").reshape(-1, h, w)
    for i, f in enumerate(got):
        assert np.array_equal(f, raws[i % n]), f"frame {i} differs from clip frame {i % n}"
    return len(got)


@pytest.mark.parametrize("sig,group", [(signal.SIGINT, True), (signal.SIGTERM, False)])
def test_live_recording_stopped_keeps_every_whole_frame(gst_subprocess_env, clip, tmp_path, sig, group):
    d, prof, raws = clip
    out = tmp_path / "rec"
    env = dict(gst_subprocess_env, FRAMES="100000", LOOP="true")
    p = _start(["bash", PIPELINES / "live_record_and_preview.sh", d, out], env)
    _wait_size(out / ".clip.raw.part", 10 * raws[0].nbytes, p)
    log = _stop(p, sig, group)
    assert p.returncode == 128 + sig, log
    n = assert_frames_of_clip(out / "clip.raw", raws)
    assert n >= 10, log
    c = json.loads((out / "clip.json").read_text())
    assert c["frames"] == n and c["profile"] == "camera.json" and "truth" not in c
    assert sorted(x.name for x in out.iterdir()) == ["camera.json", "camera_mask.png", "clip.json", "clip.raw"]
    assert sorted(x.name for x in tmp_path.iterdir()) == ["rec"]          # no lock file left
    assert f"recorded {n} whole frames" in log


def test_live_recording_killed_is_recovered(gst_subprocess_env, clip, tmp_path):
    """SIGKILL to every process of the recording (a crash): the .part file stays; `nrhdr recover`
    cuts it to whole frames and writes clip.json; the next
    run of the script does the same itself before it refuses to overwrite."""
    d, prof, raws = clip
    out = tmp_path / "rec"
    env = dict(gst_subprocess_env, FRAMES="100000", LOOP="true")
    p = _start(["bash", PIPELINES / "live_record_and_preview.sh", d, out], env)
    _wait_size(out / ".clip.raw.part", 8 * raws[0].nbytes, p)
    _stop(p, signal.SIGKILL, True)
    part = out / ".clip.raw.part"
    # power loss in the middle of a frame: 333 bytes more, or (when the kill cut a frame near its end) as many
    # as keep the last frame partial, so that no frame of garbage is completed
    r = part.stat().st_size % raws[0].nbytes
    with open(part, "ab") as f:
        f.write(b"\x07" * (333 if r + 333 < raws[0].nbytes else raws[0].nbytes - r - 1))
    cut = part.stat().st_size % raws[0].nbytes
    rc = subprocess.run([sys.executable, "-m", "gst_plugins.cli", "recover", out], env=gst_subprocess_env,
                        capture_output=True, text=True)
    assert rc.returncode == 0, rc.stderr
    assert f"{cut} bytes of a partial last frame cut off" in rc.stdout, rc.stdout
    n = assert_frames_of_clip(out / "clip.raw", raws)
    assert n >= 8 and json.loads((out / "clip.json").read_text())["frames"] == n
    # killed again; this time the next run of the script finishes it
    (out / "clip.raw").rename(part)
    (out / ".clip.json.part").write_text(json.dumps({"source_clip_json": str(d / "clip.json"),
                                                     "profile": str(d / "camera.json")}))
    r = subprocess.run(["bash", PIPELINES / "live_record_and_preview.sh", d, out], env=env, capture_output=True,
                       text=True, timeout=120)
    assert r.returncode == 2 and "clip.raw exists" in r.stderr, r.stderr
    assert f"recorded {n} whole frames" in r.stdout
    assert assert_frames_of_clip(out / "clip.raw", raws) == n


@pytest.mark.parametrize("sig,group", [(signal.SIGINT, True), (signal.SIGTERM, False)])
def test_nrhdr_launch_filesink_stopped_keeps_whole_frames(gst_subprocess_env, clip, tmp_path, sig, group):
    d, prof, raws = clip
    rec = tmp_path / "x.raw"
    p = _start([gst_subprocess_env["NRHDR"], "launch", "nrcamsrc", f"location={d}", "num-buffers=100000",
                "loop=true", "!", "filesink", f"location={rec}"], gst_subprocess_env)
    _wait_size(rec, 6 * raws[0].nbytes, p)
    log = _stop(p, sig, group)
    assert p.returncode == 128 + sig, log
    assert assert_frames_of_clip(rec, raws) >= 6


def test_hdr10_and_recording_refuse_to_overwrite(gst_subprocess_env, clip, tmp_path):
    d, prof, raws = clip
    (tmp_path / "v.mkv").write_bytes(b"mine")
    (tmp_path / "r.nrhdr").write_bytes(b"mine")
    for script, out in (("raw_to_hdr10.sh", tmp_path / "v"), ("raw_to_hdr_recording.sh", tmp_path / "r.nrhdr")):
        r = subprocess.run(["bash", PIPELINES / script, d, out], env=dict(gst_subprocess_env, FORMAT="mkv"),
                           capture_output=True, text=True, timeout=120)
        if "no 10-bit encoder" in r.stderr:
            continue
        assert r.returncode == 2 and "OVERWRITE=true" in r.stderr, (script, r.stderr)
    assert (tmp_path / "v.mkv").read_bytes() == b"mine" and (tmp_path / "r.nrhdr").read_bytes() == b"mine"


def test_a_pipeline_refuses_a_folder_another_command_writes(gst_subprocess_env, clip, tmp_path):
    from nrhdr_core import outputs
    d, prof, raws = clip
    out = tmp_path / "exr"
    with outputs.lock(out):           # e.g. `nrhdr batch -o exr` running
        r = subprocess.run(["bash", PIPELINES / "raw_to_exr.sh", d, out], env=gst_subprocess_env,
                           capture_output=True, text=True, timeout=120)
    assert r.returncode == 2 and f"{out} is being written by another command (pid {os.getpid()}" in r.stderr
    assert not out.exists()


@pytest.fixture(scope="module")
def long_clip(tmp_path_factory):
    """64x48, 1500 frames: long enough to stop a file-to-file pipeline mid-way."""
    return make_test_clip(tmp_path_factory.mktemp("long") / "clip", frames=1500, fps=30)


def first_frames(clip_dir, n, out):
    """A clip folder `out` holding the first `n` frames of `clip_dir` (its raw bytes and camera profile):
    the reference a stopped run's kept frames are compared with, without reconstructing the whole clip."""
    import shutil
    out.mkdir()
    c = json.loads((clip_dir / "clip.json").read_text())
    fb = 2 * c["width"] * c["height"]
    with open(clip_dir / c["raw"], "rb") as f:
        (out / c["raw"]).write_bytes(f.read(n * fb))
    for name in ("camera.json", "camera_mask.png"):
        shutil.copy(clip_dir / name, out / name)
    (out / "clip.json").write_text(json.dumps(dict(c, frames=n)))
    return out


@pytest.mark.parametrize("sig,group", [(signal.SIGINT, True), (signal.SIGTERM, False)])
def test_raw_to_exr_stopped_keeps_complete_frames(gst_subprocess_env, long_clip, tmp_path, sig, group):
    """nrexrsink through pipelines/raw_to_exr.sh stopped mid-way: frames 0..k-1 are there, each equal bit
    for bit (values and state) to the same frame of a complete run; no temporary or lock file."""
    from nrhdr_core import io
    d, prof, raws = long_clip
    env = dict(gst_subprocess_env, METHOD="linear")
    out = tmp_path / "exr"
    p = _start(["bash", PIPELINES / "raw_to_exr.sh", d, out], env)
    t0 = time.monotonic()
    while len(list(out.glob("frame_*.exr"))) < 20 if out.is_dir() else True:
        assert p.poll() is None and time.monotonic() - t0 < 240, "the run ended before the stop"
        time.sleep(0.05)
    log = _stop(p, sig, group)
    assert p.returncode == 128 + sig, log
    kept = sorted(out.iterdir())
    assert [f.name for f in kept] == [f"frame_{i:05d}.exr" for i in range(len(kept))]
    assert 20 <= len(kept) < len(raws) and sorted(x.name for x in tmp_path.iterdir()) == ["exr"]
    full = tmp_path / "full"
    r = subprocess.run(["bash", PIPELINES / "raw_to_exr.sh", first_frames(d, len(kept), tmp_path / "head"), full],
                       env=env, capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, r.stdout + r.stderr
    for f in kept:
        (va, sa), (vb, sb) = io.read_exr(f), io.read_exr(full / f.name)
        assert np.array_equal(va.view(np.uint32), vb.view(np.uint32)) and np.array_equal(sa, sb), f.name


def test_raw_to_hdr_recording_stopped_keeps_whole_frames(gst_subprocess_env, long_clip, tmp_path):
    """The reconstructed recording stopped mid-way: whole frames, equal to a complete run of the same command
    over the clip's first frames."""
    d, prof, raws = long_clip
    fb = 5 * prof.width * prof.height
    rec = tmp_path / "stopped.nrhdr"
    p = _start(["bash", PIPELINES / "raw_to_hdr_recording.sh", d, rec],
               dict(gst_subprocess_env, METHOD="linear"))
    _wait_size(Path(str(rec) + ".part"), 20 * fb, p)
    log = _stop(p, signal.SIGTERM, False)
    if p.returncode == 0:
        pytest.skip("the run ended before the stop arrived")
    assert p.returncode == 143, log
    data = rec.read_bytes()
    assert len(data) % fb == 0 and 20 * fb <= len(data) < len(raws) * fb
    assert (tmp_path / "stopped.nrhdr.caps").exists() and not Path(str(rec) + ".part").exists()
    full = tmp_path / "full.nrhdr"
    r = subprocess.run(["bash", PIPELINES / "raw_to_hdr_recording.sh",
                        first_frames(d, len(data) // fb, tmp_path / "head"), full],
                       env=dict(gst_subprocess_env, METHOD="linear"), capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stdout + r.stderr
    assert data == full.read_bytes()


# ---- the launch wrapper's messages ---------------------------------------------------------------------

def test_an_error_is_printed_once(gst_subprocess_env, clip):
    """A pipeline that fails in its first buffer: the element's error once, gst-launch's "doesn't want to
    preroll" once, and not the upstream "Internal data stream error" that is only its consequence."""
    d, prof, raws = clip
    r = subprocess.run([gst_subprocess_env["NRHDR"], "launch", "filesrc", f"location={d / 'clip.raw'}", "!",
                        "other/x-nrhdr,layout=f32-u8-planar,width=64,height=48,framerate=5/1,white=100.0", "!",
                        "nrtonemap", "!", "fakesink"], env=gst_subprocess_env, capture_output=True, text=True,
                       timeout=120)
    assert r.returncode != 0
    err = r.stderr
    assert err.count("ERROR: from element") == 1, err
    assert err.count("ERROR: pipeline doesn't want to preroll.") == 1, err
    assert "Internal data stream error" not in err and "Use filesrc blocksize=15360" in err, err


def test_stderr_filter_keeps_a_first_data_stream_error():
    from gst_plugins.runtime import StderrFilter
    f = StderrFilter()
    lines = ["ERROR: from element /GstPipeline:pipeline0/GstFileSrc:filesrc0: Internal data stream error.\n",
             "Additional debug info:\n", "gstbasesrc.c(3132): gst_base_src_loop ():\n",
             "streaming stopped, reason not-negotiated (-4)\n", "ERROR: pipeline doesn't want to preroll.\n",
             "ERROR: pipeline doesn't want to preroll.\n"]
    assert [x for x in map(f.feed, lines) if x is not None] == lines[:5]


def test_a_live_display_that_drops_most_frames_says_so(gst_subprocess_env, clip):
    d, prof, raws = clip
    r = subprocess.run([gst_subprocess_env["NRHDR"], "launch", "nrcamsrc", f"location={d}", "num-buffers=40",
                        "!", "queue", "leaky=downstream", "max-size-buffers=2", "!", "identity",
                        "sleep-time=150000", "!", "nrvalidity", f"profile={d / 'camera.json'}", "!", "nrtonemap",
                        "!", "fakesink", "sync=true", "qos=true", "max-lateness=20000000"],
                       env=dict(gst_subprocess_env, NRHDR_REPORT_DROPS="1"), capture_output=True, text=True,
                       timeout=180)
    assert r.returncode == 0, r.stderr
    assert "nrhdr: the live display showed only" in r.stderr and "nrvalidity0 " in r.stderr, r.stderr
    assert "Got message #" not in r.stdout          # the -m nrhdr added is not shown


def test_live_recipes_use_the_crosstalk_lut():
    for name in ("live_record_and_preview.sh", "raw_to_display.sh", "raw_to_display_headless.sh"):
        text = (PIPELINES / name).read_text()
        assert 'CROSSTALK:-lut' in text, name
    assert "NRHDR_REPORT_DROPS=1" in (PIPELINES / "live_record_and_preview.sh").read_text()


def _fake_python_prefix(tmp_path):
    """A `python3` first on PATH in a prefix with its own Python 3.x library, like pyenv or conda: CPython
    embedded in GStreamer's plugin loader would take that prefix as its home. The executable itself fails."""
    import sysconfig
    ver = f"{sys.version_info[0]}.{sys.version_info[1]}"
    pre = tmp_path / "fakepy"
    (pre / "bin").mkdir(parents=True)
    lib = pre / "lib" / f"python{ver}"
    lib.mkdir(parents=True)
    (lib / "os.py").write_text(Path(sysconfig.get_paths()["stdlib"], "os.py").read_text())
    exe = pre / "bin" / "python3"
    exe.write_text("#!/bin/sh\necho 'this python3 is not for nrhdr' >&2\nexit 1\n")
    exe.chmod(0o755)
    return pre / "bin"


def test_a_foreign_python3_first_on_path_does_not_break_the_pipelines(gst_subprocess_env, clip, tmp_path):
    from gst_plugins import runtime
    d, prof, raws = clip
    if runtime.embedded_python() is None:
        pytest.skip("GStreamer's Python plugin loader not found")
    fake = _fake_python_prefix(tmp_path)
    env = dict(gst_subprocess_env, PATH=f"{fake}{os.pathsep}{gst_subprocess_env['PATH']}",
               GST_REGISTRY=str(tmp_path / "registry.bin"))      # a fresh plugin scan with that PATH
    env.pop("PYTHONHOME", None)
    r = subprocess.run(["bash", PIPELINES / "raw_to_png.sh", d, tmp_path / "png"], env=env, capture_output=True,
                       text=True, timeout=300)
    assert r.returncode == 0, r.stdout + r.stderr
    assert len(list((tmp_path / "png").glob("frame_*.png"))) == len(raws)
    e = subprocess.run([env["NRHDR"], "env"], env=env, capture_output=True, text=True, timeout=60)
    assert e.returncode == 0 and "export GST_PLUGIN_PATH=" in e.stdout
    assert f"{fake / 'python3'} comes first on PATH" in e.stderr and "PYTHONHOME=" in e.stderr, e.stderr


def test_raw_to_hdr10_stopped_closes_a_playable_video(gst_subprocess_env, long_clip, tmp_path):
    """The 10-bit video stopped mid-way: EOS closes the Matroska file, which is renamed to OUT.mkv and
    decodes to the frames encoded so far."""
    import shutil
    if shutil.which("gst-inspect-1.0") is None or subprocess.run(
            ["gst-inspect-1.0", "--exists", "vp9enc"]).returncode and subprocess.run(
            ["gst-inspect-1.0", "--exists", "x265enc"]).returncode:
        pytest.skip("no 10-bit encoder")
    d, prof, raws = long_clip
    out = tmp_path / "v"
    p = _start(["bash", PIPELINES / "raw_to_hdr10.sh", d, out], dict(gst_subprocess_env, METHOD="linear",
                                                                     FORMAT="mkv"))
    _wait_size(Path(f"{out}.mkv.part"), 20000, p)
    log = _stop(p, signal.SIGINT, True)
    assert p.returncode == 130, log
    assert sorted(x.name for x in tmp_path.iterdir()) == ["v.mkv"]
    r = subprocess.run(["gst-launch-1.0", "-v", "filesrc", f"location={out}.mkv", "!", "matroskademux", "!",
                        "decodebin", "!", "fakesink", "silent=false"], capture_output=True, text=True,
                       timeout=300, env=gst_subprocess_env)
    assert r.returncode == 0, r.stderr
    decoded = len(re.findall(r"last-message = chain .*\(fakesink0:sink\)", r.stdout))
    assert 0 < decoded < len(raws), r.stdout[-2000:]
