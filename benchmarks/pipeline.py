"""Throughput of the chain on 640 x 480 frames of the synthesised scene: each core stage per frame, and
whole GStreamer pipelines, with anchors measured in the same run (a frame copy for the stages; a
`filesrc ! rawvideoparse ! fakesink` pass for the pipelines).

    .venv/bin/python benchmarks/pipeline.py [--frames 30] [--methods preview,linear,fse]
"""
from __future__ import annotations

import argparse
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
    a = ap.parse_args(argv)
    methods = a.methods.split(",")
    tmp = Path(tempfile.mkdtemp(prefix="nrhdr-bench-"))
    prof = profile.default(480, 640, seed=1)
    info = simulate.simulate_clip(scene.synthetic_hdr_scene(), tmp / "clip", prof, frames=a.frames,
                                  seed=1, progress=False)
    raw = np.fromfile(tmp / "clip" / "clip.raw", dtype="<u2").reshape(-1, 480, 640)
    r0 = np.ascontiguousarray(raw[a.frames // 2])
    v, s = validity.classify(r0, prof)
    known = validity.known_mask(s)
    lo, up = validity.bounds(v, s)
    print(f"# nrhdr pipeline benchmark: 640x480, {100 * (1 - known.mean()):.1f} % missing in the test frame")
    print("\n## core stages, median ms per frame (anchor: copying one float32 frame)\n")
    print("| stage | ms/frame | frames/s | x anchor |")
    print("|---|---|---|---|")
    anchor = timeit(lambda: v.copy(), 21)
    rows = [("anchor: float32 frame copy", anchor)]
    rows.append(("nrvalidity (classify)", timeit(lambda: validity.classify(r0, prof))))
    rows.append(("nrcrosstalk (no calibration: pass-through)",
                 timeit(lambda: crosstalk.correct(v.copy(), s.copy(), prof))))
    if not a.no_crosstalk:
        from nrhdr_core import calibration
        model = crosstalk.sensor_model_preset("prototype", 480, 640, seed=0)
        calibration.simulate_flats(tmp / "flats", prof, model, exposures=calibration.default_exposures(24),
                                   frames_per_exposure=2, seed=2, progress=False)
        calibration.run_calibrate(tmp / "flats", tmp / "flats" / "mask.png", tmp / "cal" / "cam.json",
                                  plots=False, progress=False)
        cprof = profile.load(tmp / "cal" / "cam.json")
        from nrhdr_core import sensor
        rx = sensor.capture(simulate.view(scene.synthetic_hdr_scene(), 480, 640, 0.5, simulate.Motion())
                            * np.float32(info["exposure_scale"]), cprof, np.random.default_rng(3), model)
        cv, cs = validity.classify(rx, cprof)
        for mode in ("lut", "kernel"):
            rows.append((f"nrcrosstalk mode={mode} (calibrated prototype sensor)",
                         timeit(lambda: crosstalk.correct(cv.copy(), cs.copy(), cprof, mode=mode), 5)))
    for m in methods:
        kw = {"preset": a.preset} if m == "fse" else {}
        rep = 3 if m in ("linear", "fse") else 7
        rows.append((f"nrreconstruct method={m}" + (f" preset={a.preset}" if m == "fse" else ""),
                     timeit(lambda: reconstruction.reconstruct(v, known, method=m, lower=lo, upper=up, **kw),
                            rep)))
    out8 = np.empty((480, 640), np.uint8)
    rows.append(("nrtonemap (GRAY8)", timeit(lambda: tonemap.log_tonemap(v, prof.white, out=out8))))
    for name, t in rows:
        print(f"| {name} | {t * 1e3:.2f} | {1 / t:.1f} | {t / anchor:.0f} |")

    try:
        from gst_plugins import runtime
    except Exception as e:  # GStreamer missing
        print(f"\n(pipelines skipped: {e})")
        return 0
    print(f"\n## whole pipelines, {a.frames} frames, wall time (anchor: filesrc ! rawvideoparse ! fakesink)\n")
    print("| pipeline | s | frames/s |")
    print("|---|---|---|")
    src = (f"filesrc location={tmp / 'clip' / 'clip.raw'} ! rawvideoparse format=gray16-le width=640 "
           f"height=480 framerate=30/1")
    prof_path = tmp / "clip" / "camera.json"
    descs = [("anchor: parse only", f"{src} ! fakesink")]
    for m in methods:
        descs.append((f"validity ! crosstalk ! reconstruct {m} ! tonemap",
                      f"{src} ! nrvalidity profile={prof_path} ! nrcrosstalk profile={prof_path} ! "
                      f"nrreconstruct method={m} preset={a.preset} ! nrtonemap ! fakesink"))
    for _, d in descs[1:]:
        runtime.run_pipeline(d)  # warm numba's on-disk caches for every method
    for name, d in descs:
        t = time.perf_counter()
        rc = runtime.run_pipeline(d)
        dt = time.perf_counter() - t
        print(f"| {name} | {dt:.2f} | {a.frames / dt:.1f} |" + ("" if rc == 0 else " (FAILED)"))
    return 0


if __name__ == "__main__":
    sys.exit(main())
