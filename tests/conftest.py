"""Shared fixtures. Data from ../shared/data is optional for users: tests that need it skip with a
reason when it is missing, except under CI (CI=true), where missing data is a failure."""
from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest

# matplotlib's wheel bundles its own FreeType; loaded after GStreamer has loaded the system one (through
# its plugins), importing matplotlib.ft2font aborts the process ("Fatal Python error: Aborted" in
# matplotlib._mathtext_data). Tests mix both in one process, so load matplotlib's first.
import matplotlib  # noqa: E402
matplotlib.use("Agg")
import matplotlib.ft2font  # noqa: E402,F401

ROOT = Path(__file__).resolve().parents[1]
SHARED_DATA = Path(os.environ.get("NRHDR_SHARED_DATA", ROOT.parent / "shared" / "data"))


def load_benchmark(name: str, module_name: str | None = None):
    """The script benchmarks/<name>.py as a module (benchmarks/ is not a package)."""
    import importlib.util
    spec = importlib.util.spec_from_file_location(module_name or f"bench_{name}", ROOT / "benchmarks" / f"{name}.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def shared_data(*parts) -> Path:
    """Path under ../shared/data; skip (or fail under CI=true) when it is missing."""
    p = SHARED_DATA.joinpath(*parts)
    if not p.exists():
        msg = f"shared test data missing: {p}"
        if os.environ.get("CI", "").lower() == "true":
            pytest.fail(msg + " (CI=true: shared data is required)")
        pytest.skip(msg)
    return p


@pytest.fixture
def rng():
    return np.random.default_rng(12345)


@pytest.fixture
def small_profile():
    from nrhdr_core import profile
    return profile.default(64, 80, seed=3)


# ---- GStreamer (tests/test_elements.py, test_pipelines.py, test_gst_errors.py) -----------------------

@pytest.fixture(scope="session")
def gst_registry(tmp_path_factory):
    """A private GStreamer registry file for this test session (in-process and subprocesses): a cached
    failed plugin import in the user's registry can never leak into the tests."""
    reg = tmp_path_factory.mktemp("gst-registry") / "registry.bin"
    os.environ["GST_REGISTRY"] = str(reg)
    return reg


@pytest.fixture(scope="session")
def gst(gst_registry):
    """GStreamer initialised in-process with the nrhdr elements registered (gst_plugins.register_all)."""
    gi = pytest.importorskip("gi")
    try:
        gi.require_version("Gst", "1.0")
        gi.require_version("GstApp", "1.0")
    except ValueError as e:
        pytest.skip(f"GStreamer GObject introspection missing: {e}")
    import gst_plugins
    gst_plugins.register_all()
    from gi.repository import Gst, GstApp  # noqa: F401  (GstApp: appsrc/appsink methods)
    return Gst


@pytest.fixture(scope="session")
def gst_subprocess_env(gst_registry):
    """Environment for gst-launch-1.0 / pipelines/*.sh subprocesses: gst_plugins.runtime.gst_env() with the
    session's private registry and this interpreter's nrhdr command first on PATH."""
    import shutil
    import sys
    if shutil.which("gst-launch-1.0") is None:
        pytest.skip("gst-launch-1.0 not installed")
    from gst_plugins import runtime
    env = runtime.gst_env()
    env["GST_REGISTRY"] = str(gst_registry)
    bindir = os.path.dirname(sys.executable)
    env["PATH"] = bindir + os.pathsep + env.get("PATH", "")
    nrhdr = os.path.join(bindir, "nrhdr")
    if os.path.exists(nrhdr):
        env["NRHDR"] = nrhdr
    env.pop("DISPLAY", None)
    env.pop("WAYLAND_DISPLAY", None)
    return env


def make_test_clip(out_dir, width=64, height=48, frames=5, fps=5, seed=7, black_level=0.0):
    """A tiny clip folder like `nrhdr simulate` writes (clip.raw GRAY16_LE, clip.json, camera.json +
    camera_mask.png): a horizontal log ramp over ~4.5 decades that moves one pixel per frame, so every clip
    has dark, valid and clipped pixels of both kinds. Returns (dir, profile, raw frames (N, H, W) uint16)."""
    import json
    from nrhdr_core import io, profile, sensor
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    prof = profile.default(height, width, seed=seed, black_level=black_level)
    profile.save(prof, out / "camera.json")
    prof = profile.load(out / "camera.json")
    rng = np.random.default_rng(seed)
    _, xx = np.mgrid[0:height, 0:width]
    raws = []
    with io.RawVideoWriter(out / "clip.raw", width, height) as w:
        for i in range(frames):
            flux = 10.0 ** (0.5 + 4.7 * ((xx + i) % width) / width)
            raw = sensor.capture(flux, prof, rng)
            w.write(raw)
            raws.append(raw)
    (out / "clip.json").write_text(json.dumps(
        {"format": "nrhdr-clip", "version": 1, "width": width, "height": height, "fps": fps,
         "frames": frames, "raw": "clip.raw", "pixel_format": "GRAY16_LE", "profile": "camera.json"},
        indent=2) + "\n")
    return out, prof, np.stack(raws)


@pytest.fixture(scope="session")
def tiny_clip(tmp_path_factory):
    """(clip dir, profile, raw frames): 64x48, 5 frames at 5 fps."""
    return make_test_clip(tmp_path_factory.mktemp("clip") / "clip")


class GstRun:
    """Result of run_appsrc: samples [(caps str, pts, duration, payload)], bus messages, first error."""

    def __init__(self):
        self.samples, self.messages, self.error, self.eos = [], [], None, False

    @property
    def error_text(self) -> str:
        return "" if self.error is None else f"{self.error[0]}: {self.error[1]}"

    def element_messages(self, name):
        return [m.get_structure() for m in self.messages
                if m.type == m.type.ELEMENT and m.get_structure() is not None
                and m.get_structure().get_name() == name]


def hdr_bytes(values, state) -> bytes:
    """The f32-u8-planar frame layout (docs/ARCHITECTURE.md), written out here so tests check the contract:
    float32 values (row-major, native little-endian) then uint8 state, nothing else."""
    v = np.ascontiguousarray(values, "<f4")
    s = np.ascontiguousarray(state, np.uint8)
    assert v.shape == s.shape
    return v.tobytes() + s.tobytes()


def hdr_buffer(values, state, pts=None, duration=None, two_blocks=False):
    """An HDR frame buffer (one memory block, f32-u8-planar) holding copies of `values` and `state`;
    `two_blocks`: the older layout of two memory blocks (values, state)."""
    from gi.repository import Gst
    if two_blocks:
        buf = Gst.Buffer.new()
        buf.append_memory(Gst.Buffer.new_wrapped(np.ascontiguousarray(values, "<f4").tobytes()).get_memory(0))
        buf.append_memory(Gst.Buffer.new_wrapped(np.ascontiguousarray(state, np.uint8).tobytes()).get_memory(0))
    else:
        buf = Gst.Buffer.new_wrapped(hdr_bytes(values, state))
    if pts is not None:
        buf.pts = pts
    if duration is not None:
        buf.duration = duration
    return buf


def raw_buffer(raw, pts=None, duration=None):
    from gi.repository import Gst
    buf = Gst.Buffer.new_wrapped(np.ascontiguousarray(raw, "<u2").tobytes())
    if pts is not None:
        buf.pts = pts
    if duration is not None:
        buf.duration = duration
    return buf


def sample_payload(sample):
    """numpy copies of a sample: (values, state) for other/x-nrhdr, an (H, W) array for gray video."""
    from gi.repository import Gst, GstVideo
    caps = sample.get_caps()
    buf = sample.get_buffer()
    s = caps.get_structure(0)
    if s.get_name() == "other/x-nrhdr":
        w, h = s.get_int("width")[1], s.get_int("height")[1]
        assert buf.get_size() == 5 * w * h, f"HDR frame of {buf.get_size()} bytes, {w}x{h} needs {5 * w * h}"
        ok, mi = buf.map(Gst.MapFlags.READ)
        assert ok
        raw = bytes(mi.data)
        buf.unmap(mi)
        values = np.frombuffer(raw, "<f4", count=w * h).reshape(h, w).copy()
        state = np.frombuffer(raw, np.uint8, offset=4 * w * h).reshape(h, w).copy()
        return values, state
    vi = GstVideo.VideoInfo.new_from_caps(caps)
    dt = np.uint8 if vi.finfo.name == "GRAY8" else np.dtype("<u2")
    ok, mi = buf.map(Gst.MapFlags.READ)
    assert ok
    a = np.ndarray((vi.height, vi.width), dt, buffer=mi.data, offset=vi.offset[0],
                   strides=(vi.stride[0], np.dtype(dt).itemsize)).copy()
    buf.unmap(mi)
    return a


def run_appsrc(desc, caps, buffers, before_push=None, lockstep=False, timeout=90.0):
    """appsrc (caps) ! <desc> ! appsink; push `buffers`, then EOS; collect every sample and bus message.
    `before_push(i, pipeline)` runs before buffer i is pushed; with lockstep the sample of buffer i is
    pulled before buffer i+1 is pushed (deterministic property changes while PLAYING)."""
    import time
    from gi.repository import Gst, GstApp  # noqa: F401
    res = GstRun()
    pipeline = Gst.parse_launch(f"appsrc name=src format=time ! {desc} ! appsink name=sink sync=false")
    src, sink = pipeline.get_by_name("src"), pipeline.get_by_name("sink")
    src.set_property("caps", Gst.Caps.from_string(caps) if isinstance(caps, str) else caps)
    bus = pipeline.get_bus()

    def drain_bus():
        while True:
            m = bus.pop()
            if m is None:
                return
            res.messages.append(m)
            if m.type == Gst.MessageType.ERROR and res.error is None:
                err, _dbg = m.parse_error()
                res.error = (m.src.get_name(), err.message)

    def pull(deadline, until_eos):
        while time.monotonic() < deadline:
            drain_bus()
            if res.error is not None:
                return False
            smp = sink.try_pull_sample(50 * Gst.MSECOND)
            if smp is not None:
                b = smp.get_buffer()
                res.samples.append((smp.get_caps().to_string(), b.pts, b.duration, sample_payload(smp)))
                if not until_eos:
                    return True
            elif sink.is_eos():
                return True
        return False

    try:
        if pipeline.set_state(Gst.State.PLAYING) == Gst.StateChangeReturn.FAILURE:
            drain_bus()
            return res
        deadline = time.monotonic() + timeout
        for i, b in enumerate(buffers):
            if before_push is not None:
                before_push(i, pipeline)
            if src.push_buffer(b) != Gst.FlowReturn.OK:
                break
            if lockstep and not pull(deadline, until_eos=False):
                break
        src.end_of_stream()
        pull(deadline, until_eos=True)
        res.eos = bool(sink.is_eos())
        drain_bus()
    finally:
        pipeline.set_state(Gst.State.NULL)
        drain_bus()
    return res


# ---- NRHDR_JIT_REPORT=1: which tests compiled numba kernels in this process -------------------------------
# After `nrhdr warmup` a test that compiles a chain kernel points at a signature the warm-up misses (or at a
# kernel only tests, calibration or the simulator use); the summary lists them, most seconds first.

if os.environ.get("NRHDR_JIT_REPORT"):
    _JIT_TESTS = []

    @pytest.hookimpl(hookwrapper=True)
    def pytest_runtest_protocol(item, nextitem):
        from nrhdr_core.realtime import JitWatch
        snap = JitWatch.snapshot()
        yield
        n, sec, names = JitWatch.since(snap)
        if n:
            _JIT_TESTS.append((sec, n, item.nodeid, names))

    def pytest_terminal_summary(terminalreporter):
        tr = terminalreporter
        tr.section(f"numba compilations in {len(_JIT_TESTS)} tests (NRHDR_JIT_REPORT)")
        for sec, n, nodeid, names in sorted(_JIT_TESTS, reverse=True):
            tr.write_line(f"{sec:7.1f} s {n:4d} {nodeid}: {', '.join(names)}")
