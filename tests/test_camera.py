"""GenICam cameras through Aravis (`aravissrc`) into the chain, against the Aravis fake GigE Vision camera
(`arv-fake-gv-camera-0.8`, a real network client on 127.0.0.1), through the recipe pipelines/camera_live.sh
(docs/CAMERAS.md); and the V4L2 side of the recipe as far as a machine without /dev/video* allows.

One fake camera per test, with its own serial, addressed by IP and checked by its DeviceID (two fake cameras can
both bind 127.0.0.1). Without the fake camera binary the tests are skipped, except under CI=true where they fail.
"""
from __future__ import annotations

import itertools
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from nrhdr_core import io, profile
from nrhdr_core.states import ATTENUATED, RECONSTRUCTED, REASON_MASK, VALID

pytestmark = pytest.mark.gst

ROOT = Path(__file__).resolve().parents[1]
RECIPE = ROOT / "pipelines" / "camera_live.sh"
FAKE = "arv-fake-gv-camera-0.8"
IP = "127.0.0.1"
W, H = 64, 48
_serials = itertools.count()


def _need(what: str, ok: bool) -> None:
    if not ok:
        if os.environ.get("CI") == "true":
            pytest.fail(f"{what} is missing (required under CI=true)")
        pytest.skip(f"{what} is missing (Debian: aravis-tools, libaravis-0.8-0, gir1.2-aravis-0.8)")


def camera_features(env, *names: str) -> dict | None:
    """DeviceID and the named features of the camera answering at 127.0.0.1 (None: no answer), read in a
    child process: the GigE Vision control channel is exclusive, this process must not hold it while
    aravissrc opens the camera."""
    code = ("import json, sys, gi; gi.require_version('Aravis', '0.8'); from gi.repository import Aravis\n"
            "try:\n    d = Aravis.Camera.new(sys.argv[1]).get_device()\n"
            "except Exception:\n    sys.exit(0)\n"
            "print(json.dumps({n: d.get_feature(n).get_value_as_string() for n in sys.argv[2:]}))")
    p = subprocess.run([sys.executable, "-c", code, IP, "DeviceID", *names], capture_output=True, text=True,
                       timeout=30, env=env)
    import json
    return json.loads(p.stdout) if p.stdout.strip() else None


def _die_with_parent():
    """preexec_fn: the child gets SIGTERM when the test process dies (Linux PR_SET_PDEATHSIG), so a killed test
    run leaves no fake camera answering on IP to the next run."""
    import ctypes
    try:
        ctypes.CDLL(None, use_errno=True).prctl(1, signal.SIGTERM)       # PR_SET_PDEATHSIG = 1
    except (OSError, AttributeError):
        pass


@pytest.fixture
def fake_camera(gst_subprocess_env):
    """A fresh fake GigE Vision camera on 127.0.0.1 (settings persist in a camera: one per test); yields
    its serial once it answers with that DeviceID."""
    _need(FAKE, shutil.which(FAKE) is not None)
    probe = subprocess.run(["gst-inspect-1.0", "aravissrc"], env=gst_subprocess_env, capture_output=True)
    _need("the GStreamer element aravissrc", probe.returncode == 0)
    serial = f"NRT{os.getpid() % 100000}{next(_serials)}"
    cam = subprocess.Popen([FAKE, "-i", IP, "-s", serial], stdout=subprocess.DEVNULL, stderr=subprocess.PIPE,
                           preexec_fn=_die_with_parent)
    try:
        deadline = time.monotonic() + 20
        found = None
        while time.monotonic() < deadline and cam.poll() is None:
            found = (camera_features(gst_subprocess_env) or {}).get("DeviceID")
            if found == serial:
                break
            time.sleep(0.3)
        if cam.poll() is not None:
            pytest.fail(f"{FAKE} exited: {cam.stderr.read().decode(errors='replace')}")
        assert found == serial, (f"the camera at {IP} answers as {found!r}, not the fake camera {serial} this "
                                 f"test started (another camera on {IP}?)")
        yield serial
    finally:
        cam.send_signal(signal.SIGTERM)
        try:
            cam.wait(10)
        except subprocess.TimeoutExpired:
            cam.kill()
            cam.wait()


def mono16_profile(folder: Path, **fields) -> Path:
    """The fake camera's Mono16: a full 16-bit ramp. Its profile says so: bit depth 16, white level 65535,
    codes beyond the bit depth an error."""
    base = profile.default(H, W, seed=11)
    f = dict(bit_depth=16, white_level=65535, gain=10.0, l_min=400.0, out_of_range="error")
    f.update(fields)
    return profile.save(profile.make(base.mask, **f), folder / "fake16.json")


def recipe(env, *args, **settings):
    e = dict(env, CAMERA=IP, **{k: str(v) for k, v in settings.items()})
    return subprocess.run(["bash", str(RECIPE), *args], env=e, capture_output=True, text=True, timeout=300)


def gdp_frames(gst, path: Path):
    """(pts list, frames as uint16 (H, W)) of a raw.gdp recording, read back with gdpdepay."""
    pipe = gst.parse_launch(f"filesrc location={path} ! gdpdepay ! appsink name=s sync=false")
    sink = pipe.get_by_name("s")
    pipe.set_state(gst.State.PLAYING)
    pts, frames = [], []
    try:
        while True:
            smp = sink.try_pull_sample(10 * gst.SECOND)
            if smp is None:
                break
            buf = smp.get_buffer()
            pts.append(buf.pts)
            frames.append(np.frombuffer(buf.extract_dup(0, buf.get_size()), "<u2").reshape(H, W).copy())
    finally:
        pipe.set_state(gst.State.NULL)
    return pts, frames


def check_exr_matches_raw(p: profile.CameraProfile, exr: Path, raw: np.ndarray) -> None:
    """An EXR frame holds the raw frame's measurements: at every VALID pixel (code - black) x ND on attenuated
    pixels (paper Eq. 3), and the known pixels are not rewritten by the reconstruction."""
    values, state = io.read_exr(exr)
    assert state is not None and values.shape == (H, W) and np.isfinite(values).all()
    ok = ((state & REASON_MASK) == VALID) & ((state & RECONSTRUCTED) == 0)
    assert ok.sum() > W * H // 4
    scale = np.where((state & ATTENUATED) != 0, p.nd, 1.0)
    np.testing.assert_allclose(values[ok], ((raw.astype(np.float64) - p.black_level) * scale)[ok], rtol=1e-5)
    assert np.array_equal((state & ATTENUATED) != 0, p.mask)


def test_record_recipe_writes_exr_frames_raw_frames_with_timestamps_and_a_preview(fake_camera, gst,
                                                                                  gst_subprocess_env, tmp_path):
    prof = mono16_profile(tmp_path)
    out = tmp_path / "rec"
    r = recipe(gst_subprocess_env, "record", out, PROFILE=prof, FRAMES=8, FPS=20, EXPOSURE=5000, GAIN=0,
               PIXEL_FORMAT="Mono16", SINK=f"pngenc ! multifilesink location={tmp_path}/preview_%05d.png")
    assert r.returncode == 0, r.stdout + r.stderr
    exrs = sorted(out.glob("frame_*.exr"))
    assert [e.name for e in exrs] == [f"frame_{i:05d}.exr" for i in range(8)]
    assert list(tmp_path.glob("preview_*.png")), "no preview frame"
    # the camera settings reached the camera (a fake camera keeps them until it is restarted)
    f = camera_features(gst_subprocess_env, "ExposureTimeAbs", "GainRaw", "PixelFormat", "Width", "Height",
                        "AcquisitionFrameRate")
    assert f["DeviceID"] == fake_camera and f["PixelFormat"] == "Mono16" and (f["Width"], f["Height"]) == (
        str(W), str(H))
    assert float(f["ExposureTimeAbs"]) == 5000 and int(f["GainRaw"]) == 0
    assert float(f["AcquisitionFrameRate"]) == 20
    pts, raws = gdp_frames(gst, out / "raw.gdp")
    assert len(pts) == 8 and all(t is not None and t != gst.CLOCK_TIME_NONE for t in pts)
    assert all(b > a for a, b in zip(pts, pts[1:])), pts
    p = profile.load(prof)
    for exr, raw in zip(exrs, raws):
        check_exr_matches_raw(p, exr, raw)
    # the ramp moves: the frames are successive camera frames, not one frame repeated
    assert not np.array_equal(raws[0], raws[-1])


def test_stop_mid_recording_keeps_every_frame(fake_camera, gst, gst_subprocess_env, tmp_path):
    prof = mono16_profile(tmp_path)
    out = tmp_path / "rec"
    env = dict(gst_subprocess_env, CAMERA=IP, PROFILE=str(prof))
    proc = subprocess.Popen(["bash", str(RECIPE), "record", str(out)], env=env, stdout=subprocess.PIPE,
                            stderr=subprocess.STDOUT, text=True, start_new_session=True)
    try:
        deadline = time.monotonic() + 240
        while time.monotonic() < deadline and proc.poll() is None and len(list(out.glob("frame_*.exr"))) < 3:
            time.sleep(0.2)
        assert proc.poll() is None, proc.communicate()[0]
        proc.send_signal(signal.SIGINT)
        log = proc.communicate(timeout=120)[0]
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()
    assert proc.returncode == 130, log
    exrs = sorted(out.glob("frame_*.exr"))
    assert len(exrs) >= 3 and not list(out.glob(".*tmp*")), log
    pts, raws = gdp_frames(gst, out / "raw.gdp")
    assert len(raws) == len(exrs), (len(raws), len(exrs))      # both recordings hold every frame captured
    p = profile.load(prof)
    for exr, raw in zip(exrs, raws):
        check_exr_matches_raw(p, exr, raw)


def test_a_late_preview_never_costs_the_recording_a_frame(fake_camera, gst_subprocess_env, tmp_path):
    """The preview shares the chain: a preview sink that is always late (ts-offset -2 s: every frame 2 s behind)
    sends QoS events up through the tee; the recording still gets every frame (with QoS on in the chain,
    nrvalidity drops most of them)."""
    prof = mono16_profile(tmp_path)
    out = tmp_path / "rec"
    r = recipe(gst_subprocess_env, "record", out, PROFILE=prof, FRAMES=12, PIXEL_FORMAT="Mono16",
               SINK="fakesink sync=true qos=true max-lateness=1000000 ts-offset=-2000000000")
    assert r.returncode == 0, r.stdout + r.stderr
    assert len(list(out.glob("frame_*.exr"))) == 12, r.stdout + r.stderr


def test_timestamps_survive_the_chain(fake_camera, gst, tmp_path):
    prof = mono16_profile(tmp_path)
    pipe = gst.parse_launch(
        f"aravissrc camera-name={IP} num-buffers=6 ! video/x-raw,format=GRAY16_LE,width={W},height={H} "
        f"! identity name=cam ! nrvalidity profile={prof} ! nrcrosstalk mode=lut ! nrreconstruct method=preview "
        f"! appsink name=s sync=false")
    at_camera = []
    pipe.get_by_name("cam").get_static_pad("src").add_probe(
        gst.PadProbeType.BUFFER, lambda pad, info: (at_camera.append(info.get_buffer().pts), gst.PadProbeReturn.OK)[1])
    sink = pipe.get_by_name("s")
    pipe.set_state(gst.State.PLAYING)
    out = []
    try:
        while len(out) < 6:
            smp = sink.try_pull_sample(30 * gst.SECOND)
            assert smp is not None, f"{len(out)} frames arrived"
            assert smp.get_caps().get_structure(0).get_name() == "other/x-nrhdr"
            out.append(smp.get_buffer().pts)
    finally:
        pipe.set_state(gst.State.NULL)
    assert out == at_camera and len(set(out)) == 6


def test_mono16_ramp_with_a_12_bit_profile_is_an_error(fake_camera, gst_subprocess_env, tmp_path):
    base = profile.default(H, W, seed=11)
    prof = profile.save(profile.make(base.mask, out_of_range="error"), tmp_path / "cam12.json")
    r = recipe(gst_subprocess_env, "record", tmp_path / "rec", PROFILE=prof, FRAMES=3, PIXEL_FORMAT="Mono16")
    assert r.returncode != 0
    assert "nrvalidity" in r.stderr + r.stdout and "codes above the 12-bit range of profile cam12.json" in r.stdout + r.stderr


def test_pixel_format_that_does_not_fit_the_caps_is_an_error(fake_camera, gst_subprocess_env, tmp_path):
    # PixelFormat=Mono8 through `features` while the caps say GRAY16_LE: aravissrc sends 1-byte pixels
    prof = mono16_profile(tmp_path)
    r = recipe(gst_subprocess_env, "record", tmp_path / "rec", PROFILE=prof, FRAMES=3, PIXEL_FORMAT="Mono8")
    log = r.stdout + r.stderr
    assert r.returncode != 0
    assert f"buffer of {W * H} bytes does not hold exactly one {W}x{H} GRAY16_LE frame" in log, log


def test_recipe_refuses_missing_profile_and_mode(gst_subprocess_env, tmp_path):
    r = recipe(gst_subprocess_env, "record", tmp_path / "rec")
    assert r.returncode == 2 and "set PROFILE" in r.stderr
    (tmp_path / "bad.json").write_text("{}")
    r = recipe(gst_subprocess_env, "preview", PROFILE=tmp_path / "bad.json")
    assert r.returncode == 2 and "bad.json" in r.stderr and "not an nrhdr camera profile" in r.stderr
    r = recipe(gst_subprocess_env, "show")
    assert r.returncode == 2 and "unknown mode 'show'" in r.stderr


def test_v4l2_recipe_names_the_missing_device(gst_subprocess_env, tmp_path):
    prof = mono16_profile(tmp_path)
    dev = "/dev/video97"
    if os.path.exists(dev):
        pytest.skip(f"{dev} exists here")
    e = dict(gst_subprocess_env, CAMERA=dev, PROFILE=str(prof), FRAMES="2")
    r = subprocess.run(["bash", str(RECIPE), "record", str(tmp_path / "rec")], env=e, capture_output=True,
                       text=True, timeout=120)
    assert r.returncode == 2 and f"V4L2 device {dev} not found" in r.stderr
    assert not list((tmp_path / "rec").glob("frame_*"))
    e.update(CAMERA="/dev/null", EXPOSURE="100")     # a V4L2 device takes no GenICam settings
    r = subprocess.run(["bash", str(RECIPE), "preview"], env=e, capture_output=True, text=True, timeout=120)
    assert r.returncode == 2 and "GenICam settings" in r.stderr and "V4L2_CONTROLS" in r.stderr


def test_v4l2src_offers_gray16_le(gst):
    """The recipe's V4L2 source negotiates GRAY16_LE (V4L2 Y16): v4l2src's template has it; opening a device
    that does not exist fails naming it."""
    f = gst.ElementFactory.find("v4l2src")
    if f is None:
        pytest.skip("v4l2src (gstreamer1.0-plugins-good) is not installed")
    caps = next(t for t in f.get_static_pad_templates() if t.direction == gst.PadDirection.SRC).get_caps()
    assert caps.can_intersect(gst.Caps.from_string(f"video/x-raw,format=GRAY16_LE,width={W},height={H}"))
    pipe = gst.parse_launch(f"v4l2src device=/dev/video97 num-buffers=1 ! video/x-raw,format=GRAY16_LE ! fakesink")
    try:
        assert pipe.set_state(gst.State.PLAYING) == gst.StateChangeReturn.FAILURE
        msg = pipe.get_bus().pop_filtered(gst.MessageType.ERROR)
        assert msg is not None and "/dev/video97" in msg.parse_error()[0].message
    finally:
        pipe.set_state(gst.State.NULL)
