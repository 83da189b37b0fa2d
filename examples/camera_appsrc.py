#!/usr/bin/env python3
"""A camera SDK feeding nrhdr through appsrc (live), with settings changed from the app while playing.

A stand-in "SDK" (StubCameraSDK) delivers raw GRAY16_LE frames of a non-regular ND sensor from its own
capture thread, like a vendor SDK's frame callback. The app pushes them into a live appsrc (is-live=true,
format=time) with timestamps taken from the pipeline clock at capture (running time = clock time - base
time), and while playing changes nrreconstruct's method and nrtonemap's exposure:

    appsrc is-live=true format=time ! queue ! nrvalidity ! nrcrosstalk
        ! nrreconstruct method=preview ! nrtonemap ! video/x-raw,format=GRAY8 ! appsink (or autovideosink)

Usage:
    .venv/bin/python examples/camera_appsrc.py [--frames 60] [--fps 15] [--width 160] [--height 120]
        [--display]

Prints one line per setting change and a summary (frames captured / displayed, timestamps increasing,
the method each frame was reconstructed with); exit status 0 when every captured frame came out in order.
The queue here keeps every frame (the example checks frames in = frames out); a live app that prefers
dropping to lagging uses `queue leaky=downstream max-size-buffers=2` instead.
"""
from __future__ import annotations

import argparse
import os
import sys
import tempfile
import threading
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))    # run from a checkout
os.environ.setdefault("GST_REGISTRY_FORK", "no")

import gi  # noqa: E402

gi.require_version("Gst", "1.0")
gi.require_version("GstApp", "1.0")
from gi.repository import Gst, GstApp  # noqa: E402,F401

import numpy as np  # noqa: E402

import gst_plugins  # noqa: E402


class StubCameraSDK:
    """Stands in for a vendor camera SDK: `start(on_frame)` runs a capture thread that calls
    `on_frame(raw, sequence)` with uint16 (H, W) raw frames at `fps` (a bright ramp panning across a
    non-regular ND sensor, nrhdr_core.sensor noise model); `stop()` ends it."""

    def __init__(self, profile, fps: float, seed: int = 0):
        self.profile, self.fps = profile, fps
        self._rng = np.random.default_rng(seed)
        self._stop = threading.Event()
        self._thread = None

    def _frame(self, i: int) -> np.ndarray:
        from nrhdr_core import sensor
        h, w = self.profile.height, self.profile.width
        _, xx = np.mgrid[0:h, 0:w]
        flux = 10.0 ** (0.5 + 4.7 * ((xx + 2 * i) % w) / w)      # ~4.5 decades, moving 2 px per frame
        return sensor.capture(flux, self.profile, self._rng)

    def start(self, on_frame) -> None:
        def run():
            period, t_next, i = 1.0 / self.fps, time.monotonic(), 0
            while not self._stop.is_set():
                on_frame(self._frame(i), i)
                i += 1
                t_next += period
                self._stop.wait(max(0.0, t_next - time.monotonic()))

        self._thread = threading.Thread(target=run, name="camera-sdk", daemon=True)
        self._thread.start()

    def stop(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join()


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--frames", type=int, default=60)
    ap.add_argument("--fps", type=int, default=15)
    ap.add_argument("--width", type=int, default=160)
    ap.add_argument("--height", type=int, default=120)
    ap.add_argument("--display", action="store_true", help="show the video (autovideosink)")
    a = ap.parse_args(argv)

    from nrhdr_core import profile
    gst_plugins.register_all()
    tmp = tempfile.TemporaryDirectory(prefix="camera_appsrc-")
    prof_path = profile.save(profile.default(a.height, a.width, seed=1), Path(tmp.name) / "camera.json")
    prof = profile.load(prof_path)

    sink = ("videoconvert ! autovideosink" if a.display else "appsink name=out sync=false max-buffers=0")
    pipeline = Gst.parse_launch(
        f"appsrc name=cam is-live=true format=time "
        f"caps=video/x-raw,format=GRAY16_LE,width={a.width},height={a.height},framerate={a.fps}/1 "
        f"! queue ! nrvalidity profile=\"{prof_path}\" ! nrcrosstalk "
        f"! nrreconstruct name=rec method=preview post-stats=true ! nrtonemap name=tm ! video/x-raw,format=GRAY8 ! {sink}")
    cam, rec, tm = (pipeline.get_by_name(n) for n in ("cam", "rec", "tm"))
    out = pipeline.get_by_name("out")
    frame_ns = Gst.SECOND // a.fps

    captured = []

    def on_frame(raw: np.ndarray, seq: int) -> None:
        """The SDK's callback (its capture thread): stamp with the pipeline clock and push."""
        clock = pipeline.get_clock()
        if clock is None:
            return                                   # not PLAYING yet
        buf = Gst.Buffer.new_wrapped(raw.astype("<u2", copy=False).tobytes())
        buf.pts = clock.get_time() - pipeline.get_base_time()      # running time at capture
        buf.duration = frame_ns
        buf.offset = seq
        captured.append(buf.pts)
        cam.emit("push-buffer", buf)

    sdk = StubCameraSDK(prof, a.fps)
    if pipeline.set_state(Gst.State.PLAYING) == Gst.StateChangeReturn.FAILURE:
        print("camera_appsrc: the pipeline could not start", file=sys.stderr)
        return 1
    pipeline.get_state(5 * Gst.SECOND)
    sdk.start(on_frame)

    bus = pipeline.get_bus()
    methods, pts_out, means, rc = [], [], [], 0
    changed = {"method": False, "exposure": False}
    deadline = time.monotonic() + 60 + 3 * a.frames / a.fps
    while time.monotonic() < deadline:
        n = len(captured)
        # settings from the application while PLAYING (read once per frame by the elements)
        if n >= a.frames // 3 and not changed["method"]:
            rec.set_property("method", "nearest")
            changed["method"] = True
            print(f"camera_appsrc: frame ~{n}: nrreconstruct method -> nearest")
        if n >= 2 * a.frames // 3 and not changed["exposure"]:
            tm.set_property("exposure", 2.0)
            changed["exposure"] = True
            print(f"camera_appsrc: frame ~{n}: nrtonemap exposure -> +2 stops")
        if n >= a.frames and sdk._thread is not None and not sdk._stop.is_set():
            sdk.stop()
            cam.emit("end-of-stream")
        if out is not None:
            smp = out.try_pull_sample(10 * Gst.MSECOND)
            if smp is not None:
                b = smp.get_buffer()
                pts_out.append(b.pts)
                ok, mi = b.map(Gst.MapFlags.READ)
                means.append(float(np.frombuffer(mi.data, np.uint8).mean()))
                b.unmap(mi)
        msg = bus.timed_pop_filtered(0 if out is not None else 10 * Gst.MSECOND,
                                     Gst.MessageType.ERROR | Gst.MessageType.EOS | Gst.MessageType.ELEMENT)
        if msg is None:
            continue
        if msg.type == Gst.MessageType.ERROR:
            err, dbg = msg.parse_error()
            print(f"camera_appsrc: ERROR from {msg.src.get_name()}: {err.message}", file=sys.stderr)
            rc = 1
            break
        if msg.type == Gst.MessageType.EOS:
            break
        s = msg.get_structure()
        if s is not None and s.get_name() == "nrhdr-frame-stats":
            methods.append(s.get_value("method"))
    else:
        print("camera_appsrc: timed out", file=sys.stderr)
        rc = 1
    sdk.stop()
    if out is not None:                                # samples still queued after EOS
        while (smp := out.try_pull_sample(0)) is not None:
            pts_out.append(smp.get_buffer().pts)
    pipeline.set_state(Gst.State.NULL)
    tmp.cleanup()

    increasing = all(b > a_ for a_, b in zip(pts_out, pts_out[1:]))
    switch = methods.index("nearest") if "nearest" in methods else None
    print(f"camera_appsrc: captured {len(captured)} frames, out {len(pts_out) if out is not None else '?'}; "
          f"timestamps increasing: {increasing}; method preview for frames 0..{(switch or len(methods)) - 1}"
          f", nearest from frame {switch}")
    if means:
        k = 2 * a.frames // 3
        print(f"camera_appsrc: mean display level {np.mean(means[:max(1, k - 3)]):.1f} before the exposure "
              f"change, {np.mean(means[k + 3:]) if len(means) > k + 3 else float('nan'):.1f} after")
    if rc == 0 and out is not None and (len(pts_out) != len(captured) or not increasing):
        rc = 1
    return rc


if __name__ == "__main__":
    sys.exit(main())
