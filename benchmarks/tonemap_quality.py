"""SDR tone mapping: TMQI (Yeganeh and Wang 2013, `nrhdr_core.metrics.tmqi`) on the five shared HDR scenes and
ms per 1920 x 1080 frame, for nrtonemap's operators and OpenCV's (docs/TONEMAP.md).

    PYTHONPATH=. .venv/bin/python benchmarks/tonemap_quality.py            # TMQI + core timings (~2 min)
    PYTHONPATH=. .venv/bin/python benchmarks/tonemap_quality.py --element  # + nrtonemap in a pipeline
    PYTHONPATH=. .venv/bin/python benchmarks/tonemap_quality.py --chain    # + on the camera chain's output

Scenes: ../shared/data/hdr/*.exr (or $NRHDR_SHARED_DATA/hdr), luminance (`io.read_luminance`), exposed as the
simulated camera exposes them (`simulate.exposure_scale`: median at 18 % of the regular pixels' range) for
the default sensor profile, whose white (4094 x ND) is the caps' white nrvalidity sets. Operators:
log / local with the profile's white and with the automatic white (`tonemap.auto_white`, nrtonemap's
normaliser when the caps carry no white); OpenCV's createTonemapReinhard / Drago / Mantiuk with their
defaults (gamma 1) and with gamma 2.2, on the luminance as a grey RGB image, codes round(255 y) clipped.

Timing: median ms per frame of `--repeat` warm calls on one scene resampled to 1920 x 1080, each operator as
nrtonemap runs it (white included: the auto white's statistic; the local operator's state kept over
frames; OpenCV's from float luminance to uint8). `--element`: wall ms per frame of
`appsrc ! nrtonemap operator=X ! fakesink` over `--frames` pre-made 1080p buffers (everything the element
does: mapping, white, operator, logging checks). The anchor `copy` (one float32 1080p np.copyto) is measured
in the same run. `--chain`: TMQI against the noise-free scene of log / local applied to what the camera
chain outputs (640 x 480 crop, sensor noise, `chain.process_frame` with method preview), beside the same
operator on the noise-free scene. Writes bench_out/tonemap_quality/results.json and results.md.
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from nrhdr_core import chain, io, metrics, profile, sensor, simulate, tonemap  # noqa: E402

DATA = Path(os.environ.get("NRHDR_SHARED_DATA", ROOT.parent / "shared" / "data"))
OUT = ROOT / "bench_out" / "tonemap_quality"
SCENES = ("Desk", "KernerEnvLatLong", "MtTamWest", "StillLife", "Tree")
OPENCV = ("Reinhard", "Drago", "Mantiuk")


def load_scenes(prof):
    out = {}
    for name in SCENES:
        sc = io.read_luminance(DATA / "hdr" / f"{name}.exr")
        out[name] = (sc * np.float32(simulate.exposure_scale(sc, prof, 0.0))).astype(np.float32)
    return out


def opencv_operator(name: str, gamma: float):
    import cv2
    make = getattr(cv2, f"createTonemap{name}")

    def run(lum, _white=None):
        op = make(gamma)
        y = op.process(cv2.merge([lum, lum, lum]))[:, :, 0]
        return np.clip(np.round(np.nan_to_num(y) * 255.0), 0, 255).astype(np.uint8)
    return run


def operators(prof):
    """name -> (white: 'profile' / 'auto' / None, fn(lum, white) -> uint8, stateful factory or None)."""
    ops = {
        "log, profile white": ("profile", tonemap.log_tonemap),
        "log, auto white": ("auto", tonemap.log_tonemap),
        "local, profile white": ("profile", tonemap.local_tonemap),
        "local, auto white": ("auto", tonemap.local_tonemap),
    }
    for n in OPENCV:
        for g in (1.0, 2.2):
            ops[f"OpenCV {n}" + (" (default)" if g == 1.0 else " gamma 2.2")] = (None, opencv_operator(n, g))
    return ops


def white_of(kind, lum, prof):
    return prof.white if kind == "profile" else tonemap.auto_white(lum) if kind == "auto" else None


def quality(scenes, ops, prof):
    res = {}
    for name, (kind, fn) in ops.items():
        res[name] = {}
        for sn, lum in scenes.items():
            q, s, n = metrics.tmqi(lum, fn(lum, white_of(kind, lum, prof)))
            res[name][sn] = {"Q": q, "S": s, "N": n}
        res[name]["mean"] = float(np.mean([res[name][sn]["Q"] for sn in scenes]))
        print(f"{name:28s} " + " ".join(f"{res[name][sn]['Q']:.3f}" for sn in scenes)
              + f"  mean {res[name]['mean']:.3f}", flush=True)
    return res


def chain_quality(scenes, seed=0):
    """TMQI of log / local (profile white) on the noise-free 640 x 480 crop and on the chain's output."""
    rng = np.random.default_rng(seed)
    res = {}
    for sn, lum in scenes.items():
        crop = np.ascontiguousarray(lum[:480, :640])
        prof = profile.make(rng.random(crop.shape) < 0.5)
        values, _ = chain.process_frame(sensor.capture(crop, prof, rng), prof, chain.ChainSettings(method="preview"))
        for name, fn in (("log", tonemap.log_tonemap), ("local", tonemap.local_tonemap)):
            clean = metrics.tmqi(crop, fn(crop, prof.white))[0]
            noisy = metrics.tmqi(crop, fn(values, prof.white))[0]
            res.setdefault(name, {})[sn] = {"clean": clean, "chain": noisy}
            print(f"{name:6s} {sn:18s} noise-free {clean:.3f}  chain output {noisy:.3f}", flush=True)
    return res


def frame_1080(lum):
    h, w = lum.shape
    rows = (np.arange(1080) * h // 1080)
    cols = (np.arange(1920) * w // 1920)
    return np.ascontiguousarray(lum[rows][:, cols])


def median_ms(fn, repeat):
    fn()
    ts = []
    for _ in range(repeat):
        t = time.perf_counter()
        fn()
        ts.append(time.perf_counter() - t)
    return float(np.median(ts) * 1e3)


def timings(frame, ops, prof, repeat):
    out = np.empty(frame.shape, np.uint8)
    copy_dst = np.empty_like(frame)
    res = {"copy (anchor)": median_ms(lambda: np.copyto(copy_dst, frame), repeat)}
    local = tonemap.LocalTonemap(0.1)
    auto = tonemap.AutoWhite(0.1)
    for name, (kind, fn) in ops.items():
        if fn is tonemap.local_tonemap:
            def run(kind=kind):
                white = prof.white if kind == "profile" else auto.update(frame)
                local(frame, white, out=out)
        elif fn is tonemap.log_tonemap:
            def run(kind=kind):
                white = prof.white if kind == "profile" else auto.update(frame)
                tonemap.log_tonemap(frame, white, out=out)
        else:
            def run(fn=fn):
                fn(frame)
        res[name] = median_ms(run, repeat)
        print(f"{name:28s} {res[name]:7.1f} ms", flush=True)
    return res


def element_timings(frame, prof, frames):
    """Wall ms per frame of appsrc ! nrtonemap ! fakesink (caps with the profile's white)."""
    from gst_plugins.elements._gst import Gst
    import gst_plugins
    gst_plugins.register_all()
    h, w = frame.shape
    payload = np.ascontiguousarray(frame, "<f4").tobytes() + np.zeros((h, w), np.uint8).tobytes()
    res = {}
    for op in tonemap.SDR_OPERATORS:
        caps = (f"other/x-nrhdr,layout=f32-u8-planar,width={w},height={h},framerate=30/1,"
                f"white=(double){prof.white}")
        p = Gst.parse_launch(f"appsrc name=src format=time caps=\"{caps}\" ! nrtonemap operator={op} ! "
                             f"video/x-raw,format=GRAY8 ! fakesink sync=false")
        src = p.get_by_name("src")
        bufs = []
        for i in range(frames + 3):
            b = Gst.Buffer.new_wrapped(payload)
            b.pts, b.duration = i * Gst.SECOND // 30, Gst.SECOND // 30
            bufs.append(b)
        p.set_state(Gst.State.PLAYING)
        for b in bufs[:3]:                       # warm: start, negotiation, first frames
            src.emit("push-buffer", b)
        time.sleep(1.0)
        t = time.perf_counter()
        for b in bufs[3:]:
            src.emit("push-buffer", b)
        src.emit("end-of-stream")
        msg = p.get_bus().timed_pop_filtered(600 * Gst.SECOND, Gst.MessageType.EOS | Gst.MessageType.ERROR)
        dt = time.perf_counter() - t
        p.set_state(Gst.State.NULL)
        if msg is None or msg.type == Gst.MessageType.ERROR:
            raise RuntimeError(f"nrtonemap operator={op}: {msg.parse_error() if msg else 'timeout'}")
        res[f"nrtonemap operator={op}"] = dt / frames * 1e3
        print(f"nrtonemap operator={op:6s} {res[f'nrtonemap operator={op}']:7.1f} ms per frame", flush=True)
    return res


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--repeat", type=int, default=15, help="timed calls per operator (median)")
    ap.add_argument("--element", action="store_true", help="also time nrtonemap in a pipeline")
    ap.add_argument("--frames", type=int, default=60, help="frames for --element")
    ap.add_argument("--chain", action="store_true", help="also TMQI on the camera chain's output")
    ap.add_argument("--timing-scene", default="MtTamWest", choices=SCENES)
    a = ap.parse_args(argv)
    prof = profile.make(np.zeros((8, 8), bool))
    scenes = load_scenes(prof)
    ops = operators(prof)
    tonemap.warmup_local()
    q = quality(scenes, ops, prof)
    frame = frame_1080(scenes[a.timing_scene])
    t = timings(frame, ops, prof, a.repeat)
    el = element_timings(frame, prof, a.frames) if a.element else {}
    ch = chain_quality(scenes) if a.chain else {}
    OUT.mkdir(parents=True, exist_ok=True)
    info = {"scenes": list(SCENES), "profile_white": prof.white, "tmqi": q, "ms_1080p": t, "element_ms_1080p": el,
            "chain_tmqi": ch, "timing_scene": a.timing_scene, "repeat": a.repeat, "cpus": os.cpu_count()}
    (OUT / "results.json").write_text(json.dumps(info, indent=1) + "\n")
    md = ["| operator | " + " | ".join(SCENES) + " | mean TMQI | ms / 1080p frame |",
          "|---|" + "---|" * (len(SCENES) + 2)]
    for name in ops:
        md.append(f"| {name} | " + " | ".join(f"{q[name][sn]['Q']:.3f}" for sn in SCENES)
                  + f" | {q[name]['mean']:.3f} | {t[name]:.1f} |")
    md.append(f"\nAnchor: one float32 1080p copy {t['copy (anchor)']:.2f} ms.")
    for k, v in el.items():
        md.append(f"{k}: {v:.1f} ms per 1080p frame in a pipeline.")
    if ch:
        md += ["", "| TMQI, 640 x 480 crop: noise-free / chain output | " + " | ".join(SCENES) + " |",
               "|---|" + "---|" * len(SCENES)]
        for name, r in ch.items():
            md.append(f"| {name} | " + " | ".join(f"{r[sn]['clean']:.3f} / {r[sn]['chain']:.3f}" for sn in SCENES)
                      + " |")
    text = "\n".join(md) + "\n"
    (OUT / "results.md").write_text(text)
    print(text)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
