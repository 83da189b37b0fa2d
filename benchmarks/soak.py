"""Soak test of the whole chain in one process: N frames (default 10 000, 160 x 120) pushed through
`appsrc ! nrvalidity ! nrcrosstalk ! nrreconstruct ! nrtonemap ! appsink`, resident memory (RSS) sampled
along the way, every output frame and timestamp checked. Anchor in the same run: the same frames through
`appsrc ! identity ! videoconvert ! appsink` (GStreamer's own cost and memory behaviour).

    .venv/bin/python benchmarks/soak.py [--frames 10000] [--width 160 --height 120] [--method preview]
        [--post-stats] [--anchor-frames N]
    .venv/bin/python benchmarks/soak.py --stop-start 20 [--stop-after 30] [--width 160 --height 120]

`--stop-start CYCLES`: the stop/start case instead: `pipelines/live_record_and_preview.sh` is started, stopped
with SIGINT to its process group (a terminal's Ctrl-C) once the recording holds `--stop-after` frames, and
started again, CYCLES times; after each stop the recording must be a clip folder (clip.json, clip.raw, camera.json + mask) whose
frames equal the clip's byte for byte, with no temporary or lock file left. Prints the start latency (start
to the first recorded frame), the stop latency (SIGINT to exit), the frames kept and the failures.

Prints fps, RSS at the start of the measured window and at the end, the RSS slope (KB per 1000 frames, least
squares over the samples after the warm-up) and whether frames and timestamps were exact. Exit status 1 when
a frame is missing, duplicated, reordered, has a wrong timestamp, or the pipeline reported an error.
"""
from __future__ import annotations

import argparse
import shutil
import os
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
os.environ.setdefault("GST_REGISTRY_FORK", "no")


def rss_kb() -> int:
    with open("/proc/self/status") as f:
        for line in f:
            if line.startswith("VmRSS:"):
                return int(line.split()[1])
    return 0


def make_frames(prof, n_distinct: int, seed: int = 0) -> list[bytes]:
    """A few distinct raw frames of the synthesised scene (panning), cycled by the soak."""
    from nrhdr_core import scene, sensor, simulate
    sc = scene.synthetic_hdr_scene()
    k = simulate.exposure_scale(sc, prof, 0.0)
    rng = np.random.default_rng(seed)
    out = []
    for i in range(n_distinct):
        flux = simulate.view(sc, prof.height, prof.width, i / max(n_distinct - 1, 1), simulate.Motion()) * k
        out.append(np.ascontiguousarray(sensor.capture(flux, prof, rng), "<u2").tobytes())
    return out


def soak(Gst, desc: str, caps: str, frames: list[bytes], n: int, fps: int, sample_every: int,
         read_bus: bool) -> dict:
    """Push n buffers (pts i/fps) through `appsrc ! desc ! appsink`, pulling in a second thread; returns
    counts, timestamp errors, RSS samples [(frame, kB)], wall seconds."""
    pipeline = Gst.parse_launch(f"appsrc name=src format=time is-live=false block=true max-bytes=4000000 "
                                f"! {desc} ! appsink name=sink sync=false max-buffers=8")
    src, sink = pipeline.get_by_name("src"), pipeline.get_by_name("sink")
    src.set_property("caps", Gst.Caps.from_string(caps))
    dur = Gst.SECOND // fps
    res = {"out": 0, "bad_ts": 0, "first_bad": None, "error": None, "rss": [], "eos": False}

    def puller():
        while True:
            smp = sink.try_pull_sample(5 * Gst.SECOND)
            if smp is None:
                if sink.is_eos():
                    res["eos"] = True
                    return
                if res["error"] is not None:
                    return
                continue
            b = smp.get_buffer()
            i = res["out"]
            if b.pts != i * dur or b.duration != dur:
                res["bad_ts"] += 1
                if res["first_bad"] is None:
                    res["first_bad"] = (i, b.pts, b.duration)
            res["out"] += 1

    bus = pipeline.get_bus()
    if pipeline.set_state(Gst.State.PLAYING) == Gst.StateChangeReturn.FAILURE:
        msg = bus.pop_filtered(Gst.MessageType.ERROR)
        res["error"] = msg.parse_error()[0].message if msg else "state change failed"
        pipeline.set_state(Gst.State.NULL)
        return res
    t = threading.Thread(target=puller, daemon=True)
    t.start()
    t0 = time.perf_counter()
    for i in range(n):
        buf = Gst.Buffer.new_wrapped(frames[i % len(frames)])
        buf.pts, buf.duration = i * dur, dur
        if src.emit("push-buffer", buf) != Gst.FlowReturn.OK:
            break
        if i % sample_every == 0:
            res["rss"].append((i, rss_kb()))
            if read_bus:   # an application that reads its bus (pop_filtered would discard the rest: only
                while True:  # the reading app touches the bus; an error also stops push-buffer)
                    msg = bus.pop()
                    if msg is None:
                        break
                    if msg.type == Gst.MessageType.ERROR:
                        res["error"] = msg.parse_error()[0].message
                if res["error"] is not None:
                    break
    src.emit("end-of-stream")
    t.join(timeout=120)
    res["seconds"] = time.perf_counter() - t0
    res["rss"].append((n, rss_kb()))
    msg = bus.pop_filtered(Gst.MessageType.ERROR)
    if msg is not None and res["error"] is None:
        res["error"] = msg.parse_error()[0].message
    pipeline.set_state(Gst.State.NULL)
    return res


def slope_kb_per_1000(samples, skip_frames: int) -> float:
    pts = [(f, r) for f, r in samples if f >= skip_frames]
    if len(pts) < 3:
        return float("nan")
    x = np.array([p[0] for p in pts], float)
    y = np.array([p[1] for p in pts], float)
    return float(np.polyfit(x, y, 1)[0] * 1000)


def report(name: str, r: dict, n: int, warm: int) -> bool:
    rss = r["rss"]
    after = [kb for f, kb in rss if f >= warm] or [rss[-1][1]]
    ok = r["error"] is None and r["out"] == n and r["bad_ts"] == 0 and r["eos"]
    print(f"{name}: {r['out']}/{n} frames in {r['seconds']:.1f} s = {r['out'] / max(r['seconds'], 1e-9):.0f} fps; "
          f"RSS {after[0] / 1024:.1f} MB at frame {warm} -> {rss[-1][1] / 1024:.1f} MB at the end "
          f"(max {max(kb for _, kb in rss) / 1024:.1f} MB), slope {slope_kb_per_1000(rss, warm):+.1f} kB per "
          f"1000 frames; timestamps {'exact' if r['bad_ts'] == 0 else 'WRONG: %d, first %s' % (r['bad_ts'], r['first_bad'])}"
          f"{'' if r['eos'] else ', NO EOS'}{'' if r['error'] is None else ', ERROR: ' + r['error']}")
    return ok


def stop_start(cycles: int, stop_after: int, width: int, height: int, fps: int) -> int:
    """The stop/start cycle case (see the module docstring); exit status 1 on any failed cycle."""
    import json
    import signal
    import subprocess
    from nrhdr_core import profile, scene, simulate
    from gst_plugins import runtime
    tmp = Path(tempfile.mkdtemp(prefix="nrhdr-soak-stop-"))
    clip = tmp / "clip"
    n_clip = 11
    simulate.simulate_clip(scene.synthetic_hdr_scene(), clip, profile.default(height, width, seed=1),
                           frames=n_clip, fps=fps, progress=False)
    raws = np.fromfile(clip / "clip.raw", "<u2").reshape(n_clip, height, width)
    fb = raws[0].nbytes
    env = runtime.gst_env()
    env["PYTHONPATH"] = os.pathsep.join([str(ROOT), env.get("PYTHONPATH", "")])
    env.update(FRAMES="1000000000", LOOP="true")
    env.pop("DISPLAY", None)
    env.pop("WAYLAND_DISPLAY", None)
    starts, stops, kept, failures = [], [], [], []
    print(f"soak stop/start: {cycles} cycles of pipelines/live_record_and_preview.sh ({width}x{height} at {fps} "
          f"fps), SIGINT after {stop_after} recorded frames")
    for c in range(cycles):
        out = tmp / f"rec{c}"
        part = out / ".clip.raw.part"
        t0 = time.monotonic()
        p = subprocess.Popen(["bash", str(ROOT / "pipelines" / "live_record_and_preview.sh"), str(clip), str(out)],
                             env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                             start_new_session=True)
        first = None
        try:
            while p.poll() is None and time.monotonic() - t0 < 300:
                size = part.stat().st_size if part.exists() else 0
                if first is None and size >= fb:
                    first = time.monotonic() - t0
                if size >= stop_after * fb:
                    break
                time.sleep(0.01)
            t1 = time.monotonic()
            os.killpg(p.pid, signal.SIGINT)
            log = p.communicate(timeout=120)[0]
            stops.append(time.monotonic() - t1)
        finally:
            if p.poll() is None:
                os.killpg(p.pid, signal.SIGKILL)
                p.wait()
        starts.append(first if first is not None else float("nan"))
        why = []
        if p.returncode != 130:
            why.append(f"exit status {p.returncode}")
        names = sorted(f.name for f in out.iterdir()) if out.is_dir() else []
        if names != ["camera.json", "camera_mask.png", "clip.json", "clip.raw"]:
            why.append(f"folder holds {names}")
        left = [f.name for f in tmp.iterdir() if f.name.startswith(".")]
        if left:
            why.append(f"left beside it: {left}")
        if (out / "clip.raw").is_file():
            data = np.fromfile(out / "clip.raw", "<u2")
            if data.size % (fb // 2):
                why.append("a partial frame")
            else:
                got = data.reshape(-1, height, width)
                bad = [i for i, f in enumerate(got) if not np.array_equal(f, raws[i % n_clip])]
                if bad:
                    why.append(f"frames {bad[:5]} differ from the clip")
                if json.loads((out / "clip.json").read_text()).get("frames") != len(got):
                    why.append("clip.json's frame count is wrong")
                kept.append(len(got))
        if why:
            failures.append((c, why, log[-2000:]))
        shutil.rmtree(out, ignore_errors=True)
    shutil.rmtree(tmp, ignore_errors=True)

    def fig(v):
        v = np.asarray(v, float)
        return f"median {np.nanmedian(v):.2f} s, max {np.nanmax(v):.2f} s" if v.size else "-"
    print(f"  start -> first recorded frame: {fig(starts)}")
    print(f"  SIGINT -> exit (recording finished): {fig(stops)}")
    print(f"  frames kept per cycle: min {min(kept, default=0)}, max {max(kept, default=0)} "
          f"(asked {stop_after}; frames arriving while the stop travels are kept too)")
    print(f"  cycles ok: {cycles - len(failures)} of {cycles}")
    for c, why, log in failures:
        print(f"  cycle {c} FAILED: {'; '.join(why)}\n{log}")
    return 1 if failures else 0


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=10000)
    ap.add_argument("--anchor-frames", type=int, default=None, help="frames for the anchor (default: --frames)")
    ap.add_argument("--width", type=int, default=160)
    ap.add_argument("--height", type=int, default=120)
    ap.add_argument("--fps", type=int, default=30)
    ap.add_argument("--method", default="preview", choices=("preview", "nearest", "linear", "fse"))
    ap.add_argument("--preset", default="preview")
    ap.add_argument("--crosstalk", default="lut", choices=("lut", "kernel", "off"))
    ap.add_argument("--post-stats", action="store_true",
                    help="nrreconstruct post-stats=true with a bus nobody reads (a leak would show here)")
    ap.add_argument("--stop-start", type=int, default=0, metavar="CYCLES",
                    help="run the stop/start cycle case instead (pipelines/live_record_and_preview.sh)")
    ap.add_argument("--stop-after", type=int, default=30, help="frames recorded before each SIGINT")
    a = ap.parse_args(argv)
    if a.stop_start:
        return stop_start(a.stop_start, max(a.stop_after, 1), a.width, a.height, a.fps)
    if a.frames < 10:
        ap.error("--frames must be >= 10")

    import gi
    gi.require_version("Gst", "1.0")
    gi.require_version("GstApp", "1.0")
    import gst_plugins
    gst_plugins.register_all()
    from gi.repository import Gst, GstApp  # noqa: F401
    from nrhdr_core import crosstalk, profile

    tmp = Path(tempfile.mkdtemp(prefix="nrhdr-soak-"))
    prof = profile.default(a.height, a.width, seed=1)
    prof = prof.replace(crosstalk=crosstalk.identity_calibration(prof.mask))   # exercise the LUT path
    profile.save(prof, tmp / "cam.json")
    frames = make_frames(prof, 24)
    caps = f"video/x-raw,format=GRAY16_LE,width={a.width},height={a.height},framerate={a.fps}/1"
    every = max(a.frames // 200, 10)
    warm = min(1000, a.frames // 10)
    print(f"soak: {a.frames} frames {a.width}x{a.height}, nrreconstruct method={a.method} preset={a.preset}, "
          f"nrcrosstalk mode={a.crosstalk}, post-stats={'true (bus unread)' if a.post_stats else 'default (false)'}; "
          f"RSS sampled every {every} frames, slope after frame {warm} (shared machine: figures are noisy)")
    na = a.anchor_frames or a.frames
    anc = soak(Gst, "identity ! videoconvert ! video/x-raw,format=GRAY8", caps, frames, na, a.fps, every,
               read_bus=True)
    ok_a = report("anchor  appsrc ! identity ! videoconvert ! appsink", anc, na, min(1000, na // 10))
    chain = (f"nrvalidity profile={tmp / 'cam.json'} ! nrcrosstalk mode={a.crosstalk} ! "
             f"nrreconstruct method={a.method} preset={a.preset}"
             f"{' post-stats=true' if a.post_stats else ''} ! nrtonemap ! video/x-raw,format=GRAY8")
    res = soak(Gst, chain, caps, frames, a.frames, a.fps, every, read_bus=False)
    ok = report("nrhdr   appsrc ! nrvalidity ! nrcrosstalk ! nrreconstruct ! nrtonemap ! appsink", res,
                a.frames, warm)
    for f in tmp.iterdir():
        f.unlink()
    tmp.rmdir()
    return 0 if ok and ok_a else 1


if __name__ == "__main__":
    sys.exit(main())
