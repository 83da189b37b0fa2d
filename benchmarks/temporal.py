"""Video quality and speed of the chain per clip kind: single-frame against temporal reconstruction against an
unmodified camera, on simulated clips of the shared HDR scenes.

    python benchmarks/temporal.py             # 384 x 288, 8 frames per clip; frames/s at 1920 x 1080
    python benchmarks/temporal.py --quick     # smoke run: 96 x 72, 4 frames, 2 scenes; frames/s at 320 x 180

Clip kinds (`CLIPS`, rendered by `simulate.ClipRenderer`, docs/SIMULATOR.md), fov 0.8 of each scene:
static; slow pan (3 % of the scene width over the clip); fast motion (a pan of 25 % of the width and 5 % of
the height, plus six objects, patches of the scene's texture and bright and dark discs, of 15 % of the
height crossing the view at 3 % of its width per frame); cut (the slow pan, then from the middle frame the
next scene). Scenes: GoldenGate, memorial and venice_sunset under ../shared/data/hdr ($NRHDR_SHARED_DATA/hdr)
where present, else every scene there; `--scenes` names others ('synthetic' for the synthesised one).

Each clip is captured with shot and read noise (no crosstalk) by the non-regular ND camera
(`profile.default`, ND 6.35) and by an unmodified camera (no ND pixel) whose regular pixels carry the same
noise (the ND camera's regular pixels are the unmodified camera's codes, as in hdr_quality.py --dark). The
ND camera's frames run through `chain.process_frame` (default settings: weighted dark policy, fse fast),
alone per frame ("temporal off") and with `nrhdr_core.temporal.TemporalReconstructor` (state reset per clip,
"temporal on"; skipped with a note where this tree has no `nrhdr_core.temporal`); the unmodified camera's
are classified and their clipped pixels filled from their bound (preview), as in hdr_quality.py.

Metrics (`metrics.clip_report`, as `nrhdr compare` and hdr_quality.py): log2 PSNR (1 DN floor, peak
log2(white), truth and output capped at the ND camera's white) per region of the truth (dark < l_min x ND,
bright >= the regular clip, mid between), the mean over all frames of all scenes; flicker: the RMS over
consecutive frame pairs of the change of the log2 error in stops, at pixels not bright in either truth,
pooled over pairs and scenes; per frame and region, log2 PSNR temporal on minus off (the frames where on
is furthest below off are listed). Speed: each clip kind of the first scene (or `--fps-scene`) at 1920 x
1080, classified, then the reconstruction stage alone per frame in sequence, for the single-frame preview
method (the anchor), fse fast and fse fast with the temporal state, the three back to back on each frame
(best of `--repeat` timed passes after an untimed one): ms per frame in the steady state (median of the
second half of the clip) and over the clip, and frames/s.
Writes bench_out/temporal/results.json and results.md.
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import os
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from nrhdr_core import (chain, metrics, profile, realtime, reconstruction, sensor, simulate,  # noqa: E402
                        validity)

try:
    from nrhdr_core.temporal import TemporalReconstructor
except ModuleNotFoundError as e:           # a tree without the temporal mode: temporal "off" only
    if e.name != "nrhdr_core.temporal":
        raise
    TemporalReconstructor = None

DATA = Path(os.environ.get("NRHDR_SHARED_DATA", ROOT.parent / "shared" / "data"))
OUT = ROOT / "bench_out" / "temporal"
PREFERRED = ("GoldenGate", "memorial", "venice_sunset")
FOV = 0.8
CLIPS = {   # name: (camera path, objects?, cut?)
    "static": (simulate.Motion(pan=0.0, tilt=0.0, zoom=1.0, fov=FOV), False, False),
    "slow pan": (simulate.Motion(pan=0.03, tilt=0.0, zoom=1.0, fov=FOV), False, False),
    "fast motion": (simulate.Motion(pan=0.25, tilt=0.05, zoom=1.0, fov=FOV), True, False),
    "cut": (simulate.Motion(pan=0.03, tilt=0.0, zoom=1.0, fov=FOV), False, True),
}
OBJECTS, OBJECT_SIZE, OBJECT_SPEED = 6, 0.15, 0.03    # count, share of the height, share of the width per frame
SETTINGS = chain.ChainSettings()                      # weighted dark policy, fse fast
PREVIEW = chain.ChainSettings(method="preview")


def default_scenes() -> list[str]:
    d = DATA / "hdr"
    found = [p for n in PREFERRED for p in (d / f"{n}.exr", d / f"{n}.hdr") if p.is_file()]
    return [str(p) for p in found] or [str(p) for p in sorted(d.glob("*.exr"))]


def renderer(kind, scenes, j, prof, frames, seed):
    """`simulate.ClipRenderer` of clip kind `kind` over scene j (the cut goes to scene j + 1)."""
    motion, moving, cut = CLIPS[kind]
    h, w = prof.height, prof.width
    objects = (simulate.random_objects(OBJECTS, h, w, frames, OBJECT_SPEED * w, max(OBJECT_SIZE * h, 1.0),
                                       "mixed", seed + j) if moving else ())
    cut_frame = max(frames // 2, 1) if cut and frames > 1 else None
    other = scenes[(j + 1) % len(scenes)] if len(scenes) > 1 else None     # None: the scene turned by 180 degrees
    return simulate.ClipRenderer(scenes[j], prof, frames, 0.0, motion, objects, cut_frame,
                                 other if cut_frame is not None else None)


def temporal(budget=None):
    """The temporal state for `SETTINGS`' reconstruction (`budget`: blocks' worth of FSE work a frame; None:
    the chain's default, as nrreconstruct temporal-budget)."""
    return TemporalReconstructor(method=SETTINGS.method, preset=SETTINGS.preset, use_bounds=SETTINGS.use_bounds,
                                 fusion=SETTINGS.noise_fusion,
                                 budget=SETTINGS.temporal_budget if budget is None else budget)


class Recorded:
    """A temporal state that keeps the report of every frame (`chain.process_frame` calls `process`)."""

    def __init__(self, tr):
        self.tr, self.reports = tr, []

    def reset(self):
        self.tr.reset()
        self.reports = []

    def process(self, values, state, noise=None):
        r = self.tr.process(values, state, noise=noise)
        self.reports.append(r)
        return r


def capture_pair(truths, prof, seed):
    """Raw frames of the ND camera and of the unmodified camera; the regular pixels share their codes."""
    p0 = profile.make(np.zeros((prof.height, prof.width), bool))
    r0, r1 = np.random.default_rng((seed, 0)), np.random.default_rng((seed, 1))
    nd, cam = [], []
    for t in truths:
        c = sensor.capture(t, p0, r0)
        cam.append(c)
        nd.append(np.where(prof.mask, sensor.capture(t, prof, r1), c).astype(np.uint16))
    return nd, cam, p0


def run_chain(raws, prof, settings, temporal=None):
    """Each raw frame through the chain, in order; with `temporal` (reset first) as the elements run it."""
    outs = []
    if temporal is not None:
        temporal.reset()
    for r in raws:
        if temporal is None:
            v, _ = chain.process_frame(r, prof, settings)
        else:
            v, _ = chain.process_frame(r, prof, settings, temporal=temporal)
        outs.append(v)
    return outs


def camera(raws, p0):
    """The unmodified camera's output: clipped pixels filled from their bound (hdr_quality.camera_baseline)."""
    outs = []
    for raw in raws:
        v, s = validity.classify(raw, p0)
        lo, hi = validity.bounds(v, s)
        outs.append(reconstruction.reconstruct(v, validity.known_mask(s), method="preview", lower=lo, upper=hi))
    return outs


class Flicker:
    """RMS over consecutive frames of the change of the log2 error (stops; 1 DN floor, capped at `white`),
    at the pixels below `bright` in both truths; pooled over every pair added."""

    def __init__(self, white, bright):
        self.white, self.bright = white, bright
        self.sse, self.n = 0.0, 0

    def add_clip(self, truths, outs):
        err = [np.log2(np.clip(np.asarray(o, np.float64), 1.0, self.white))
               - np.log2(np.clip(np.asarray(t, np.float64), 1.0, self.white)) for t, o in zip(truths, outs)]
        for i in range(1, len(err)):
            m = (truths[i] < self.bright) & (truths[i - 1] < self.bright)
            d = err[i][m] - err[i - 1][m]
            self.sse += float(np.sum(d * d))
            self.n += int(m.sum())

    def value(self):
        return float(np.sqrt(self.sse / self.n)) if self.n else None


def frame_regions(truth, out, prof) -> dict:
    """log2 PSNR per region of one frame, as `metrics.clip_report` scores it (None: the region is empty)."""
    white = prof.white
    r = metrics.hdr_report(np.minimum(truth, white), np.minimum(np.asarray(out, np.float64), white),
                           prof.l_min * prof.nd, prof.regular_white, white=white, peak_stops=float(np.log2(white)))
    return {k: (r[k]["log2_psnr"] if r[k]["pixels"] else None) for k in metrics.REGIONS}


def quality(scenes, names, h, w, frames, seed, configs):
    """({clip kind: {config: report with 'flicker'}} over all scenes, per frame and region temporal on
    against off: a list of {clip, scene, frame, region, on, off, delta})."""
    prof = profile.default(h, w, seed=3)
    res = {}
    per_frame = []
    for kind in CLIPS:
        pairs = {c: [] for c in configs}
        flick = {c: Flicker(prof.white, prof.regular_white) for c in configs}
        for j in range(len(scenes)):
            t0 = time.perf_counter()
            truths = [renderer(kind, scenes, j, prof, frames, seed).flux(i) for i in range(frames)]
            nd, cam, p0 = capture_pair(truths, prof, seed + 100 * j)
            by = {}
            starts = set()
            for c in configs:
                if c == "camera":
                    outs = camera(cam, p0)
                elif c == "on":
                    rec = Recorded(temporal())
                    outs = run_chain(nd, prof, SETTINGS, rec)
                    starts = {i for i, r in enumerate(rec.reports) if r.get("start") == "preview"}
                else:
                    outs = run_chain(nd, prof, SETTINGS, None)
                by[c] = outs
                pairs[c] += zip(truths, outs)
                flick[c].add_clip(truths, outs)
            if "on" in by:
                for i, t in enumerate(truths):
                    on, off = frame_regions(t, by["on"][i], prof), frame_regions(t, by["off"][i], prof)
                    per_frame += [{"clip": kind, "scene": names[j], "frame": i, "region": k, "on": on[k],
                                   "off": off[k], "delta": on[k] - off[k], "preview": i in starts}
                                  for k in metrics.REGIONS
                                  if on[k] is not None and off[k] is not None]
            print(f"  {kind}, {names[j]}: {time.perf_counter() - t0:.1f} s", flush=True)
        res[kind] = {}
        for c in configs:
            r = metrics.clip_report(pairs[c], prof.l_min * prof.nd, prof.regular_white, prof.white)
            r["flicker"] = flick[c].value()
            res[kind][c] = r
    return res, per_frame


def timed(raws, prof, configs, repeat, truths=None):
    """The reconstruction stage alone on the classified raw frames, in sequence: ({config: ms per frame},
    {config: log2 PSNR all per frame against `truths`, or None}). `configs`: (name, settings, temporal state
    or None: `reconstruct_frame`); each frame timed for every configuration back to back (the same moment
    of the shared machine's load), best of `repeat` passes after an untimed pass (it compiles, fills the
    caches and scores the outputs)."""
    classified = [validity.classify(raw, prof, mode=SETTINGS.mode, l_min=SETTINGS.l_min,
                                    dark_policy=SETTINGS.dark_policy) for raw in raws]
    n = len(raws)
    best = {name: [float("inf")] * n for name, _, _ in configs}
    psnr = {name: [0.0] * n for name, _, _ in configs} if truths is not None else None
    for rep in range(repeat + 1):
        for _, _, tr in configs:
            if tr is not None:
                tr.reset()
        for i, (v0, s0) in enumerate(classified):
            for name, st, tr in configs:
                v, s = v0.copy(), s0.copy()
                t0 = time.perf_counter()
                if tr is None:
                    reconstruction.reconstruct_frame(v, s, method=st.method, preset=st.preset,
                                                     use_bounds=st.use_bounds, noise=prof, fusion=st.noise_fusion)
                else:
                    tr.process(v, s, noise=prof)
                dt = (time.perf_counter() - t0) * 1e3
                if rep:
                    best[name][i] = min(best[name][i], dt)
                elif psnr is not None:
                    psnr[name][i] = frame_regions(truths[i], v, prof)["all"]
    return best, psnr


def speed(scene_list, h, w, frames, seed, repeat):
    """{clip kind: {config: {"ms": [per frame], "steady": ms, "mean": ms}}} at h x w on the first scene: the
    reconstruction stage alone (`reconstruct_frame` for preview and fse fast, the temporal state's `process`
    for temporal on) on the classified frames, each frame timed for every configuration back to back (the
    same moment of the shared machine's load), best of `repeat` passes per frame after an untimed pass.
    "steady": the median over the second half of the clip (a steady shot's reused state), "mean": over all
    frames."""
    prof = profile.default(h, w, seed=3)
    configs = [("preview", PREVIEW, None), ("off", SETTINGS, None)]
    if TemporalReconstructor is not None:
        configs.append(("on", SETTINGS, temporal()))
    res = {}
    for kind in CLIPS:
        r = renderer(kind, scene_list, 0, prof, frames, seed)
        raws, _, _ = capture_pair([r.flux(i) for i in range(frames)], prof, seed)
        best, _ = timed(raws, prof, configs, repeat)
        res[kind] = {name: {"ms": ms, "steady": float(np.median(ms[frames // 2:])), "mean": float(np.mean(ms))}
                     for name, ms in best.items()}
        print(f"  {kind}: " + ", ".join(f"{k} {v['steady']:.1f} ms steady, {v['mean']:.1f} ms mean"
                                        for k, v in res[kind].items()), flush=True)
    return res


QUALITY_TOL = 0.1     # dB: a frame of the budgeted shot within this of the unbounded temporal output has its quality
LIVE_FPS, LIVE_FRAMES = 30.0, 150     # the live source: frames a second, frames (5 s)


def live_lost(ms, fps=LIVE_FPS, frames=LIVE_FRAMES) -> int:
    """Frames a live source of `fps` loses in `frames` frames before a stage that takes ms[k] ms for the
    k-th frame it processes (the last value for the later ones), behind a leaky queue of one buffer (a new
    frame replaces the one waiting; the stage takes the waiting frame when it is free)."""
    period = 1e3 / fps
    free, waiting, done, lost = 0.0, None, 0, 0
    for i in range(frames):
        t = i * period
        while waiting is not None and free <= t:          # the stage takes the waiting frame
            start = max(free, waiting)
            free = start + ms[min(done, len(ms) - 1)]
            done += 1
            waiting = None
        if free <= t:                                       # idle: processed at once
            free = t + ms[min(done, len(ms) - 1)]
            done += 1
        else:
            lost += waiting is not None                     # the older waiting frame is dropped
            waiting = t
    return lost


def shot(scene_list, h, w, frames, seed, repeat, budget):
    """A static shot from its first frame at h x w (the first scene): per frame the reconstruction stage's ms
    (best of `repeat` after an untimed pass) and log2 PSNR (all pixels) against the truth, for preview,
    fse fast, fse fast with the temporal state under `budget` (blocks' worth of FSE work a frame; the
    default) and without a bound (budget 0), back to back on each frame. Returns {config: {"ms", "psnr",
    "mean", "worst", "steady", "lost"}} and "frames_to_quality": the first frame from which the budgeted
    shot stays within QUALITY_TOL dB of the unbounded one."""
    prof = profile.default(h, w, seed=3)
    configs = [("preview", PREVIEW, None), ("off", SETTINGS, None), ("on", SETTINGS, temporal(budget)),
               ("unbounded", SETTINGS, temporal(0))]
    r = renderer("static", scene_list, 0, prof, frames, seed)
    truths = [r.flux(i) for i in range(frames)]
    raws, _, _ = capture_pair(truths, prof, seed)
    best, psnr = timed(raws, prof, configs, repeat, truths)
    res = {name: {"ms": ms, "psnr": psnr[name], "mean": float(np.mean(ms)), "worst": float(np.max(ms)),
                  "worst_frame": int(np.argmax(ms)), "steady": float(np.median(ms[frames // 2:])),
                  "lost": live_lost(ms)} for name, ms in best.items()}
    gap = np.array(psnr["on"]) < np.array(psnr["unbounded"]) - QUALITY_TOL
    res["frames_to_quality"] = int(np.flatnonzero(gap)[-1] + 1) if gap.any() else 0
    res["budget"] = budget
    print("  shot: " + ", ".join(f"{k} {res[k]['mean']:.1f} ms mean, {res[k]['worst']:.1f} worst"
                                 for k in ("preview", "off", "on", "unbounded")), flush=True)
    return res


def shot_table(res, h, w, frames) -> str:
    """The static shot from its first frame: ms mean / worst / steady (and mean and worst as multiples of the
    preview's), frames a live 30 fps source loses, log2 PSNR of the first and the last frame."""
    cols = [("preview", "preview (anchor)"), ("off", "fse fast"),
            ("on", f"fse fast, temporal on (budget {res['budget']})"), ("unbounded", "fse fast, temporal on, budget 0")]
    rows = [("ms per frame, mean over the shot", lambda r: f"{r['mean']:.1f}"),
            ("worst frame, ms (frame)", lambda r: f"{r['worst']:.1f} ({r['worst_frame']})"),
            ("mean / worst frame, x the preview's", lambda r: f"{r['mean'] / res['preview']['mean']:.2f} / "
                                                            f"{r['worst'] / res['preview']['worst']:.2f}"),
            ("steady, ms (median of the second half)", lambda r: f"{r['steady']:.1f}"),
            (f"frames lost of {LIVE_FRAMES} at a live {LIVE_FPS:.0f} fps source (leaky queue of one)",
             lambda r: str(r["lost"])),
            ("log2 PSNR all, first / last frame (dB)", lambda r: f"{r['psnr'][0]:.2f} / {r['psnr'][-1]:.2f}")]
    lines = [f"| static shot, {w} x {h}, {frames} frames from the first | " + " | ".join(c[1] for c in cols) + " |",
             "|---" * (len(cols) + 1) + "|"]
    for label, f in rows:
        lines.append(f"| {label} | " + " | ".join(f(res[c]) for c, _ in cols) + " |")
    lines.append(f"\ntemporal on reaches the unbounded temporal quality (within {QUALITY_TOL} dB, log2 PSNR all) "
                 f"from frame {res['frames_to_quality']} on.")
    return "\n".join(lines)


LABELS = {"off": "single-frame (temporal off)", "on": "temporal on", "camera": "unmodified camera, same noise"}


def quality_table(res, configs) -> str:
    """One row per clip kind, the outputs side by side: log2 PSNR all / dark / mid / bright (dB); flicker."""
    f = lambda x: "-" if x is None else f"{x:.2f}"
    lines = ["| clip | " + " | ".join(LABELS[c] for c in configs) + " |", "|---" * (len(configs) + 1) + "|"]
    for kind, by in res.items():
        cells = []
        for c in configs:
            r = by[c]
            fl = "-" if r["flicker"] is None else f"{r['flicker']:.3f}"
            cells.append(" / ".join(f(r[k]["log2_psnr"]) for k in metrics.REGIONS) + f"; {fl}")
        lines.append(f"| {kind} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def speed_table(res, h, w, frames) -> str:
    """ms per frame of the reconstruction stage (frames/s): the steady state (median of the second half)
    and the mean over the clip."""
    cols = [("preview", "preview (anchor)"), ("off", "fse fast, temporal off"), ("on", "fse fast, temporal on")]
    cols = [c for c in cols if any(c[0] in by for by in res.values())]
    lines = [f"| clip ({w} x {h}, {frames} frames): ms steady / mean (frames/s) | "
             + " | ".join(c[1] for c in cols) + " |", "|---" * (len(cols) + 1) + "|"]
    for kind, by in res.items():
        lines.append(f"| {kind} | " + " | ".join(
            f"{by[c]['steady']:.1f} / {by[c]['mean']:.1f} ({1e3 / by[c]['steady']:.1f})" for c, _ in cols) + " |")
    return "\n".join(lines)


def worst_frames(per_frame, n=3) -> str:
    """The frames and regions where temporal on falls furthest below temporal off (log2 PSNR dB)."""
    rows = sorted(per_frame, key=lambda r: r["delta"])[:n]
    return "\n".join(f"- {r['clip']}, {r['scene']}, frame {r['frame']}, {r['region']}: on {r['on']:.2f}, off "
                     f"{r['off']:.2f} ({r['delta']:+.2f} dB)" for r in rows)


def size(text: str) -> tuple[int, int]:
    try:
        w, h = (int(x) for x in text.lower().split("x"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not WIDTHxHEIGHT") from None
    if not (8 <= w <= 8192 and 8 <= h <= 8192):
        raise argparse.ArgumentTypeError(f"{text}: width and height must be in 8..8192")
    return w, h


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--quick", action="store_true", help="smoke run: 96 x 72, 4 frames, 2 scenes, frames/s at "
                                                         "320 x 180 over 3 frames")
    ap.add_argument("--size", type=size, default=None, help="quality clips WIDTHxHEIGHT (default 384x288)")
    ap.add_argument("--frames", type=int, default=None, help="frames per clip (default 8)")
    ap.add_argument("--fps-size", type=size, default=None, help="frames/s at WIDTHxHEIGHT (default 1920x1080)")
    ap.add_argument("--fps-frames", type=int, default=None, help="frames per timed clip (default 8)")
    ap.add_argument("--repeat", type=int, default=2, help="timed passes per configuration (best counts)")
    ap.add_argument("--shot-frames", type=int, default=None,
                    help="frames of the static shot timed from its first frame (default 30; --quick 6)")
    ap.add_argument("--no-fps", action="store_true", help="quality only")
    ap.add_argument("--fps-scene", default=None, help="scene of the frames/s clips (default: the first scene)")
    ap.add_argument("--scenes", nargs="+", default=None,
                    help="HDR scene files, or 'synthetic' (default: GoldenGate, memorial, venice_sunset in the "
                         "shared data where present, else all of its HDR scenes)")
    ap.add_argument("--temporal-budget", type=int, default=None,
                    help=f"temporal on: blocks' worth of FSE work a frame (nrreconstruct temporal-budget; default "
                         f"{chain.TEMPORAL_BUDGET}, 0 = no bound)")
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--out", default=str(OUT))
    a = ap.parse_args(argv)
    global SETTINGS
    if a.temporal_budget is not None and a.temporal_budget < 0:
        ap.error("--temporal-budget must be >= 0")
    SETTINGS = dataclasses.replace(chain.ChainSettings(), temporal_budget=chain.TEMPORAL_BUDGET
                                   if a.temporal_budget is None else a.temporal_budget)
    (w, h) = a.size or ((96, 72) if a.quick else (384, 288))
    frames = a.frames or (4 if a.quick else 8)
    (fw, fh) = a.fps_size or ((320, 180) if a.quick else (1920, 1080))
    fframes = a.fps_frames or (3 if a.quick else 8)
    sframes = a.shot_frames or (6 if a.quick else 30)
    if min(frames, fframes, a.repeat, sframes) < 1:
        ap.error("--frames, --fps-frames, --shot-frames and --repeat must be >= 1")
    paths = a.scenes or default_scenes()
    if a.quick and not a.scenes:
        paths = paths[:2]
    missing = [p for p in paths if p != "synthetic" and not Path(p).is_file()]
    if missing or not paths:
        print(f"temporal: scene file(s) not found: {', '.join(missing) or DATA / 'hdr'} (set NRHDR_SHARED_DATA "
              f"or pass --scenes)", file=sys.stderr)
        return 2
    if a.fps_scene is not None and a.fps_scene != "synthetic" and not Path(a.fps_scene).is_file():
        print(f"temporal: --fps-scene {a.fps_scene}: no such file", file=sys.stderr)
        return 2
    loaded = [realtime.load_scene(p, height=h) for p in paths]
    scenes, names = [s for s, _ in loaded], [n for _, n in loaded]
    configs = ["off"] + (["on"] if TemporalReconstructor is not None else []) + ["camera"]
    note = ("" if TemporalReconstructor is not None else
            "nrhdr_core.temporal is not in this tree: temporal off and the unmodified camera only\n\n")
    print(note + f"quality: {w} x {h}, {frames} frames per clip, scenes {', '.join(names)}", flush=True)
    t_start = time.perf_counter()
    q, per_frame = quality(scenes, names, h, w, frames, a.seed, configs)
    text = (note + f"{w} x {h}, {frames} frames per clip, scenes {', '.join(names)}, shot and read noise, "
            f"chain defaults (weighted, fse fast; temporal-budget {SETTINGS.temporal_budget}); log2 PSNR all / dark / "
            "mid / bright dB; flicker in stops\n\n"
            + quality_table(q, configs) + "\n")
    if per_frame:
        worse = [r for r in per_frame if r["delta"] < 0]
        text += (f"\nper frame and region, temporal on below off: {len(worse)} of {len(per_frame)}; the "
                 f"furthest:\n" + worst_frames(per_frame) + "\n")
        later = [r for r in per_frame if not r["preview"]]
        if len(later) < len(per_frame):       # the budget started shots (and cuts) from the preview
            text += (f"\nthe same outside the frames that start from the preview (a shot's first, a cut's; "
                     f"temporal-budget {SETTINGS.temporal_budget}): {sum(r['delta'] < 0 for r in later)} of "
                     f"{len(later)}; the furthest:\n" + worst_frames(later) + "\n")
    sp = sh = None
    if not a.no_fps:
        fscenes = list(scenes)
        fname = names[0]
        if a.fps_scene is not None:       # first, the others stay for the cut
            fs, fname = realtime.load_scene(a.fps_scene, height=fh)
            fscenes = [fs] + [s for s, n in zip(scenes, names) if n != fname]
        elif paths[0] == "synthetic":     # at the size of the timed frames
            fscenes[0] = realtime.load_scene("synthetic", height=fh)[0]
        print(f"frames/s: {fw} x {fh}, {fframes} frames per clip, {fname}", flush=True)
        sp = speed(fscenes, fh, fw, fframes, a.seed, a.repeat)
        text += (f"\nreconstruction stage, {fname}, ms per frame (best of {a.repeat} per frame, configurations back "
                 f"to back):\n\n" + speed_table(sp, fh, fw, fframes) + "\n")
        if TemporalReconstructor is not None:
            print(f"static shot: {fw} x {fh}, {sframes} frames from the first, {fname}", flush=True)
            sh = shot(fscenes, fh, fw, sframes, a.seed, a.repeat, SETTINGS.temporal_budget)
            text += (f"\nstatic shot from its first frame, {fname}, reconstruction stage (best of {a.repeat} per "
                     f"frame, configurations back to back):\n\n" + shot_table(sh, fh, fw, sframes) + "\n")
    total = time.perf_counter() - t_start
    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    info = {"quick": a.quick, "size": [w, h], "frames": frames, "scenes": names, "seed": a.seed,
            "temporal": TemporalReconstructor is not None, "quality": q, "fps_size": [fw, fh],
            "fps_frames": fframes, "fps_scene": fname if sp else None, "fps": sp, "shot": sh,
            "per_frame": per_frame,
            "seconds": total}
    (out / "results.json").write_text(json.dumps(info, indent=1) + "\n")
    (out / "results.md").write_text(text)
    print("\n" + text + f"\n({total:.0f} s)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
