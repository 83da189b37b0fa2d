"""Where the 1080p chain's time goes, element by element, through GStreamer (docs/BENCHMARKS.md).

    PYTHONPATH=. .venv/bin/python benchmarks/chain_parts.py --clip DIR [--parts parse,validity,...] [--reps 2]

DIR holds a raw clip (`clip.raw`, GRAY16_LE) and its calibrated profile (`camera.json` with a crosstalk
calibration), e.g. made with
    nrhdr simulate-flats flats --width 1920 --height 1080 --sensor-model prototype
    nrhdr calibrate flats --mask flats/mask.png -o cal/camera.json
    (then nrhdr_core.simulate.simulate_clip(scene, DIR, profile.load('cal/camera.json'), sensor_model=...),
     as benchmarks/pipeline.py does)
Each part is a pipeline `filesrc ! rawvideoparse ! ... ! fakesink` run in this process (elements registered
in-process) after one warm-up run; reported: wall seconds and ms per frame after the first frame (fakesink
handoff times), the anchor being the parse-only pipeline. A part's cost is its ms/frame minus the previous
part's. Timings on a shared machine: compare within one run.
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))


def parts(clip: Path, w: int, h: int) -> dict:
    prof = clip / "camera.json"
    src = (f"filesrc location={clip / 'clip.raw'} ! rawvideoparse format=gray16-le width={w} height={h} "
           f"framerate=30/1 plane-strides=<{2 * w}>")
    val = f"nrvalidity profile={prof}"
    return {
        "parse": f"{src} ! fakesink name=out",
        "validity": f"{src} ! {val} ! fakesink name=out",
        "crosstalk_off": f"{src} ! {val} ! nrcrosstalk mode=off ! fakesink name=out",
        "lut_full": f"{src} ! {val} ! nrcrosstalk mode=lut lut=full ! fakesink name=out",
        "lut_compact": f"{src} ! {val} ! nrcrosstalk mode=lut lut=compact ! fakesink name=out",
        "lut_compact_tonemap": f"{src} ! {val} ! nrcrosstalk mode=lut lut=compact ! nrtonemap ! fakesink name=out",
        "chain_preview_full": f"{src} ! {val} ! nrcrosstalk mode=lut lut=full ! nrreconstruct method=preview ! "
                              f"nrtonemap ! fakesink name=out",
        "chain_preview_compact": f"{src} ! {val} ! nrcrosstalk mode=lut lut=compact ! nrreconstruct "
                                 f"method=preview ! nrtonemap ! fakesink name=out",
    }


def run(desc: str):
    from gi.repository import Gst
    p = Gst.parse_launch(desc)
    ts = []
    out = p.get_by_name("out")
    out.set_property("signal-handoffs", True)
    out.connect("handoff", lambda *a: ts.append(time.perf_counter()))
    bus = p.get_bus()
    t0 = time.perf_counter()
    p.set_state(Gst.State.PLAYING)
    m = bus.timed_pop_filtered(Gst.CLOCK_TIME_NONE, Gst.MessageType.EOS | Gst.MessageType.ERROR)
    dt = time.perf_counter() - t0
    p.set_state(Gst.State.NULL)
    if m.type == Gst.MessageType.ERROR:
        raise RuntimeError(m.parse_error()[0].message)
    per = (ts[-1] - ts[0]) / (len(ts) - 1) if len(ts) > 2 else float("nan")
    return dt, per * 1e3


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--clip", required=True, help="folder with clip.raw and a calibrated camera.json")
    ap.add_argument("--parts", default="parse,validity,crosstalk_off,lut_full,lut_compact,lut_compact_tonemap,"
                                       "chain_preview_full,chain_preview_compact")
    ap.add_argument("--reps", type=int, default=2)
    ap.add_argument("--json", default=None)
    a = ap.parse_args(argv)
    clip = Path(a.clip).resolve()
    meta = json.loads((clip / "camera.json").read_text())
    w, h = int(meta["width"]), int(meta["height"])
    import gst_plugins
    gst_plugins.register_all()
    table = parts(clip, w, h)
    res = {"width": w, "height": h, "load_avg_1min": os.getloadavg()[0], "ms_per_frame": {}}
    print(f"{w}x{h}, {a.reps} runs per part after a warm-up run; ms per frame after the first frame")
    print("| part | wall s | ms/frame (median) |\n|---|---|---|")
    for name in a.parts.split(","):
        run(table[name])
        r = [run(table[name]) for _ in range(a.reps)]
        ms = sorted(x[1] for x in r)[len(r) // 2]
        res["ms_per_frame"][name] = round(ms, 2)
        print(f"| {name} | {' / '.join(f'{x[0]:.2f}' for x in r)} | {ms:.1f} |", flush=True)
    if a.json:
        Path(a.json).write_text(json.dumps(res, indent=2) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
