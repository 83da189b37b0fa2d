"""Throughput of the chain on frames of the synthesised scene: each core stage per frame, and whole
GStreamer pipelines, with anchors measured in the same run (a frame copy for the stages; a
`filesrc ! rawvideoparse ! fakesink` pass for the pipelines); with `--live`, the live camera stand-in
(`nrcamsrc`, 30 fps, loop over the clip) through the chain into `fakesink sync=true qos=true`: frames
rendered and dropped and the latency the pipeline reports, per reconstruction setting.

    .venv/bin/python benchmarks/pipeline.py [--frames 30] [--methods preview,linear,fse]
    .venv/bin/python benchmarks/pipeline.py --width 1920 --height 1080 --methods preview,fse --live
    .venv/bin/python benchmarks/pipeline.py --width 1920 --height 1080 --methods preview \
        --scene ../shared/data/hdr/MtTamWest.exr --live --live-methods preview,auto

`--scene`: an HDR file (big clipped areas: MtTamWest.exr) instead of the synthesised scene, for every clip.
`--dark-policy threshold`: nrvalidity's hard l_min in the whole pipelines (the default, weighted, keeps
too-dark attenuated pixels as NOISY measurements for the noise fusion).
The stage rows include nrreconstruct's own frame path (`reconstruction.reconstruct_frame`: masks, bounds,
reconstruction, NOISY fusion, write-back, in place), which is what the element costs per frame.
"""
from __future__ import annotations

import argparse
import atexit
import re
import shutil
import statistics
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from nrhdr_core import crosstalk, profile, reconstruction, scene, simulate, tonemap, validity  # noqa: E402


def timeit(fn, repeat=7):
    fn()  # warm-up / JIT
    ts = []
    for _ in range(repeat):
        t = time.perf_counter()
        fn()
        ts.append(time.perf_counter() - t)
    return statistics.median(ts)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=30)
    ap.add_argument("--methods", default="preview,nearest,linear,fse")
    ap.add_argument("--preset", default="fast")
    ap.add_argument("--no-crosstalk", action="store_true", help="skip the calibrated crosstalk stages")
    ap.add_argument("--width", type=int, default=640)
    ap.add_argument("--height", type=int, default=480)
    ap.add_argument("--live", action="store_true",
                    help="also run nrcamsrc live at --fps through the chain into fakesink sync=true for "
                         "--live-methods, reporting frames rendered/dropped and the latency")
    ap.add_argument("--dark-policy", choices=("weighted", "threshold"), default="weighted",
                    help="nrvalidity dark-policy in the whole-pipeline runs (threshold: the paper's hard l_min, "
                         "no NOISY pixels to fuse)")
    ap.add_argument("--noise-fusion", choices=("auto", "accurate", "fast"), default="auto",
                    help="nrreconstruct noise-fusion in the whole-pipeline runs")
    ap.add_argument("--queues", action="store_true",
                    help="also run each chain with a queue between elements (a streaming thread per element)")
    ap.add_argument("--live-methods", default="preview,auto,fse:fast,fse:best",
                    help="method[:preset] list for --live")
    ap.add_argument("--live-seconds", type=float, default=5.0, help="length of each live run")
    ap.add_argument("--fps", type=int, default=30, help="frame rate of the live runs")
    ap.add_argument("--skip-stages", action="store_true", help="only the pipelines")
    ap.add_argument("--no-launch", action="store_true",
                    help="skip the gst-launch-1.0 runs of each pipeline (the last column)")
    ap.add_argument("--scene", default="synthetic",
                    help="HDR scene file for the clips (default: the synthesised scene)")
    a = ap.parse_args(argv)
    methods = a.methods.split(",")
    W, H = a.width, a.height
    tmp = Path(tempfile.mkdtemp(prefix="nrhdr-bench-"))
    atexit.register(shutil.rmtree, tmp, True)   # clips, flats and calibration: ~0.9 GB at 1080p
    prof = profile.default(H, W, seed=1)
    from nrhdr_core import realtime
    sc, scene_name = realtime.load_scene(a.scene) if a.scene != "synthetic" else (scene.synthetic_hdr_scene(),
                                                                                  "synthetic")
    info = simulate.simulate_clip(sc, tmp / "clip", prof, frames=a.frames, seed=1, progress=False)
    raw = np.fromfile(tmp / "clip" / "clip.raw", dtype="<u2").reshape(-1, H, W)
    r0 = np.ascontiguousarray(raw[a.frames // 2])
    v, s = validity.classify(r0, prof)
    known = validity.known_mask(s)
    lo, up = validity.bounds(v, s)
    print(f"# nrhdr pipeline benchmark: {W}x{H}, scene {scene_name}, {100 * (1 - known.mean()):.1f} % missing "
          f"in the test frame")
    print("\n## core stages, median ms per frame (anchor: copying one float32 frame)\n")
    print("| stage | ms/frame | frames/s | x anchor |")
    print("|---|---|---|---|")
    def tm(fn, repeat=7):
        return float("nan") if a.skip_stages else timeit(fn, repeat)

    anchor = tm(lambda: v.copy(), 21)
    rows = [("anchor: float32 frame copy", anchor)]
    cprof_path = None
    rows.append(("nrvalidity (classify)", tm(lambda: validity.classify(r0, prof))))
    rows.append(("nrcrosstalk (no calibration: pass-through)",
                 tm(lambda: crosstalk.correct(v.copy(), s.copy(), prof))))
    if not a.no_crosstalk:
        from nrhdr_core import calibration
        model = crosstalk.sensor_model_preset("prototype", H, W, seed=0)
        calibration.simulate_flats(tmp / "flats", prof, model, exposures=calibration.default_exposures(24),
                                   frames_per_exposure=2, seed=2, progress=False)
        calibration.run_calibrate(tmp / "flats", tmp / "flats" / "mask.png", tmp / "cal" / "cam.json",
                                  plots=False, progress=False)
        cprof = profile.load(tmp / "cal" / "cam.json")
        cprof_path = tmp / "cal" / "cam.json"
        from nrhdr_core import sensor
        rx = sensor.capture(simulate.view(sc, H, W, 0.5, simulate.Motion())
                            * np.float32(info["exposure_scale"]), cprof, np.random.default_rng(3), model)
        cv, cs = validity.classify(rx, cprof)
        for mode in ("lut", "kernel"):
            rows.append((f"nrcrosstalk mode={mode}{' lut=full' if mode == 'lut' else ''} (calibrated prototype sensor)",
                         tm(lambda: crosstalk.correct(cv.copy(), cs.copy(), cprof, mode=mode), 5)))
        if hasattr(crosstalk, "compact_for"):   # nrcrosstalk's default LUT form
            crosstalk.compact_for(cprof)
            rows.append(("nrcrosstalk mode=lut lut=compact (calibrated prototype sensor)",
                         tm(lambda: crosstalk.correct(cv.copy(), cs.copy(), cprof, mode="lut", lut="compact"), 5)))
    for m in methods:
        kw = {"preset": a.preset} if m == "fse" else {}
        rep = 3 if m in ("linear", "fse") else 7
        rows.append((f"nrreconstruct method={m}" + (f" preset={a.preset}" if m == "fse" else ""),
                     tm(lambda: reconstruction.reconstruct(v, known, method=m, lower=lo, upper=up, **kw),
                            rep)))
    # nrreconstruct's frame as the element runs it (nrvalidity's default dark-policy=weighted: NOISY pixels
    # fused with the profile's noise), in place on a fresh copy of the classified frame each call
    vw_, sw_ = validity.classify(r0, prof, dark_policy="weighted")
    vw, sw = vw_.copy(), sw_.copy()

    def frame(m, kw):
        np.copyto(vw, vw_)
        np.copyto(sw, sw_)
        reconstruction.reconstruct_frame(vw, sw, method=m, noise=prof, **kw)
    copy2 = tm(lambda: (np.copyto(vw, vw_), np.copyto(sw, sw_)))
    for m in methods:
        if m not in ("preview", "fse"):
            continue
        kw = {"preset": a.preset} if m == "fse" else {}
        t = tm(lambda: frame(m, kw), 3 if m == "fse" else 7)
        rows.append((f"nrreconstruct method={m}" + (f" preset={a.preset}" if m == "fse" else "")
                     + " (element frame path, NOISY fusion)", t - copy2))
        if m == "preview" and hasattr(reconstruction, "_reconstruct_frame_general"):
            t = tm(lambda: (np.copyto(vw, vw_), np.copyto(sw, sw_), reconstruction._reconstruct_frame_general(
                vw, sw, "preview", "fast", True, prof)), 7)
            rows.append(("nrreconstruct method=preview (the general frame path of the other methods)", t - copy2))
    out8 = np.empty((H, W), np.uint8)
    rows.append(("nrtonemap (GRAY8)", tm(lambda: tonemap.log_tonemap(v, prof.white, out=out8))))
    for name, t in rows if not a.skip_stages else []:
        print(f"| {name} | {t * 1e3:.2f} | {1 / t:.1f} | {t / anchor:.0f} |")

    try:
        from gst_plugins import runtime
    except Exception as e:  # GStreamer missing
        print(f"\n(pipelines skipped: {e})")
        return 0
    if cprof_path is not None:  # the pipelines read a clip of the crosstalk sensor with its calibration
        simulate.simulate_clip(sc, tmp / "xclip", cprof, frames=a.frames, seed=1,
                               sensor_model=model, progress=False)
        clip_dir, prof_path, xt = tmp / "xclip", cprof_path, "nrcrosstalk mode=lut (calibrated)"
    else:
        clip_dir, prof_path, xt = tmp / "clip", tmp / "clip" / "camera.json", "nrcrosstalk (pass-through)"
    print(f"\n## whole pipelines, {a.frames} frames {W}x{H}, wall time (anchor: filesrc ! rawvideoparse ! "
          f"fakesink; {xt})\n")
    print("| pipeline | s | frames/s | frames/s after start-up | gst-launch-1.0, frames/s after start-up |")
    print("|---|---|---|---|---|")
    src = (f"filesrc location={clip_dir / 'clip.raw'} ! rawvideoparse format=gray16-le width={W} "
           f"height={H} framerate=30/1 plane-strides=<{2 * W}>")
    chain = (f"nrvalidity profile={prof_path} dark-policy={a.dark_policy} ! nrcrosstalk profile={prof_path} "
             f"mode=lut")
    descs = [("anchor: parse only", f"{src} ! fakesink")]
    for m in methods:
        descs.append((f"validity ! crosstalk ! reconstruct {m} ! tonemap",
                      f"{src} ! {chain} ! nrreconstruct method={m} preset={a.preset} post-stats=true "
                      f"noise-fusion={a.noise_fusion} ! nrtonemap ! fakesink"))
    if a.queues:   # one streaming thread per element: the stages overlap on the cores
        q = " ! queue max-size-buffers=2 max-size-time=0 max-size-bytes=0 ! "
        for m in methods:
            descs.append((f"the same, {m}, a queue between elements",
                          f"{src}{q}{chain.replace(' ! ', q)}{q}nrreconstruct method={m} preset={a.preset} "
                          f"post-stats=true noise-fusion={a.noise_fusion}{q}nrtonemap ! fakesink"))
    for _, d in descs[1:]:
        runtime.run_pipeline(d)  # warm numba's on-disk caches for every method
    for name, d in descs:
        times = []

        def on_message(msg, times=times):
            st = msg.get_structure()
            if st is not None and st.get_name() == "nrhdr-frame-stats":
                times.append(time.perf_counter())

        t = time.perf_counter()
        rc = runtime.run_pipeline(d, on_message=on_message)
        dt = time.perf_counter() - t
        warm = f"{(len(times) - 1) / (times[-1] - times[0]):.1f}" if len(times) > 2 else "-"
        gl = launch_rate(d, a.frames) if not a.no_launch else float("nan")
        print(f"| {name} | {dt:.2f} | {a.frames / dt:.1f} | {warm} | {gl:.1f} |" + ("" if rc == 0 else " (FAILED)"))
    if a.live:
        live_runs(a, clip_dir, prof_path, chain)
    return 0


_FRAME_LINE = re.compile(r" frame \d+ pts ")     # nrreconstruct's per-frame log line


def launch_rate(desc: str, frames: int, skip: int = 2) -> float:
    """Frames/s of `desc` run by gst-launch-1.0 (as `nrhdr launch` and pipelines/*.sh run it) after
    start-up: from the timestamps of nrreconstruct's per-frame log lines (GST_DEBUG=nrreconstruct:6), the
    first `skip` frames left out. NaN for a pipeline without nrreconstruct. The in-process column runs
    the same pipeline under this Python process's own main loop; the two differ by more than the run-to-run
    noise at 1080p (docs/BENCHMARKS.md)."""
    import shlex
    import subprocess

    from gst_plugins import runtime
    if "nrreconstruct" not in desc:
        return float("nan")
    env = dict(runtime.gst_env(), GST_DEBUG="nrreconstruct:6", GST_DEBUG_NO_COLOR="1")
    r = subprocess.run(["gst-launch-1.0", "-q"] + shlex.split(desc.replace(" post-stats=true", "")), env=env,
                       capture_output=True, text=True)
    if r.returncode != 0:
        return float("nan")
    ts = []
    for line in r.stderr.splitlines():
        if "nrreconstruct" in line and _FRAME_LINE.search(line):
            h, m, sec = line.split()[0].split(":")
            ts.append(int(h) * 3600 + int(m) * 60 + float(sec))
    ts = ts[skip:]
    return (len(ts) - 1) / (ts[-1] - ts[0]) if len(ts) > 2 and ts[-1] > ts[0] else float("nan")


def live_runs(a, clip_dir, prof_path, chain) -> None:
    """nrcamsrc (live, a.fps, looping over the clip) ! queue leaky ! chain ! fakesink sync=true qos=true."""
    import collections

    import gst_plugins
    gst_plugins.register_all()
    from gi.repository import Gst
    n = int(round(a.live_seconds * a.fps))
    print(f"\n## live: nrcamsrc at {a.fps} fps, {n} frames ({a.live_seconds:.0f} s), "
          f"{a.width}x{a.height} -> queue leaky=downstream max-size-buffers=1 -> chain -> "
          f"fakesink sync=true qos=true max-lateness=20 ms\n")
    print("| nrreconstruct | frames produced | reconstructed | rendered | dropped | latency reported (ms) "
          "| reconstruct ms (median) | auto chose |")
    print("|---|---|---|---|---|---|---|---|")
    for spec in a.live_methods.split(","):
        method, _, preset = spec.partition(":")
        preset = preset or a.preset
        desc = (f"nrcamsrc name=cam location={clip_dir} loop=true fps={a.fps} num-buffers={n} ! "
                f"queue leaky=downstream max-size-buffers=1 ! {chain} ! nrreconstruct method={method} "
                f"preset={preset} post-stats=true ! nrtonemap ! fakesink name=out sync=true qos=true max-lateness=20000000")
        p = Gst.parse_launch(desc)
        bus = p.get_bus()
        stats = []
        p.set_state(Gst.State.PLAYING)
        err = None
        deadline = time.monotonic() + a.live_seconds * 4 + 60
        while time.monotonic() < deadline:
            m = bus.timed_pop(100 * Gst.MSECOND)
            if m is None:
                continue
            if m.type == Gst.MessageType.LATENCY:
                p.recalculate_latency()
            elif m.type == Gst.MessageType.ELEMENT and m.get_structure().get_name() == "nrhdr-frame-stats":
                s = m.get_structure()
                stats.append((s.get_value("seconds"), s.get_value("chosen")))
            elif m.type == Gst.MessageType.ERROR:
                err = m.parse_error()[0].message
                break
            elif m.type == Gst.MessageType.EOS:
                break
        q = Gst.Query.new_latency()
        out = p.get_by_name("out")
        lat = q.parse_latency()[1] / 1e6 if out.sinkpad.peer_query(q) else float("nan")
        rendered = out.get_property("stats").get_value("rendered")
        lost_at_cam = p.get_by_name("cam").get_property("dropped")
        p.set_state(Gst.State.NULL)
        med = statistics.median(x[0] for x in stats) * 1e3 if stats else float("nan")
        chose = ""
        if method == "auto":
            c = collections.Counter(x[1] for x in stats)
            chose = ", ".join(f"{k} {v}" for k, v in c.most_common())
        produced = n + lost_at_cam
        print(f"| {method}{'' if method != 'fse' else ' ' + preset} | {produced} | {len(stats)} | {rendered} "
              f"| {produced - rendered} | {lat:.0f} | {med:.1f} | {chose} |" + (f" ERROR: {err}" if err else ""))


if __name__ == "__main__":
    sys.exit(main())
