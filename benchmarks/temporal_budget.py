"""The temporal-budget trade on a static 1080p shot from its first frame: the reconstruction stage per frame
for the single-frame preview (the anchor) and `fse fast` with the temporal state under each budget, all in one
run, back to back on each frame (`benchmarks/temporal.py` `timed`: best of --repeat after an untimed pass).

    NRHDR_SHARED_DATA=../shared/data .venv/bin/python benchmarks/temporal_budget.py --budgets 0,120,150,240

Prints per configuration: ms mean over the shot and worst frame (and both as multiples of the preview's), median
of the second half, the frames a 30 fps live source would lose behind a leaky queue of one (`live_lost`), each
frame against the preview's same frame (timed back to back: the most, as a multiple, and the frames above it),
log2 PSNR (all pixels) at four frames and, with budget 0 (no bound) among the budgets, the frame from which the
shot stays within `QUALITY_TOL` dB of it; then per budget FSE's work a refining frame (the reports' "work",
in unknown pixels' work: the budget's, and the blocks reconstructed alone on top).
"""
from __future__ import annotations

import argparse
import importlib.util
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--budgets", default="0,120,240",
                    help="comma-separated budgets: blocks' worth of FSE work a frame (0: no bound)")
    ap.add_argument("--frames", type=int, default=30)
    ap.add_argument("--repeat", type=int, default=2)
    ap.add_argument("--size", default="1920x1080", help="WIDTHxHEIGHT")
    ap.add_argument("--scene", default=None, help="HDR scene (default: Desk.exr of the shared data, else synthetic)")
    a = ap.parse_args(argv)
    try:
        budgets = [int(b) for b in a.budgets.split(",")]
        w, h = (int(x) for x in a.size.lower().split("x"))
    except ValueError:
        ap.error(f"--budgets takes whole numbers, --size WIDTHxHEIGHT (got {a.budgets!r}, {a.size!r})")
    if min(budgets) < 0 or a.frames < 2 or a.repeat < 1 or min(w, h) < 16:
        ap.error("--budgets >= 0, --frames >= 2, --repeat >= 1, --size at least 16x16")
    spec = importlib.util.spec_from_file_location("bench_temporal", ROOT / "benchmarks" / "temporal.py")
    bt = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(bt)
    from nrhdr_core import profile, realtime
    scene = a.scene or str(bt.DATA / "hdr" / "Desk.exr")
    if not Path(scene).is_file():
        scene = "synthetic"
    sc, name = realtime.load_scene(scene, height=h)
    prof = profile.default(h, w, seed=3)
    r = bt.renderer("static", [sc], 0, prof, a.frames, 1)
    truths = [r.flux(i) for i in range(a.frames)]
    raws, _, _ = bt.capture_pair(truths, prof, 1)
    configs = [("preview", bt.PREVIEW, None)] + [(f"budget {b}", bt.SETTINGS, bt.temporal(b)) for b in budgets]
    best, psnr = bt.timed(raws, prof, configs, a.repeat, truths)
    n = a.frames
    marks = sorted({0, n // 3, 2 * n // 3, n - 1})
    print(f"static shot, {w} x {h}, {name}, {n} frames from the first, best of {a.repeat}")
    ref = np.array(psnr["budget 0"]) if "budget 0" in psnr else None
    p0 = np.array(best["preview"])
    print(f"| configuration | ms mean | worst ms | ms, frames {n // 2}-{n - 1} | lost of 150 at 30 fps | "
          f"mean / worst, x preview | per frame, x the preview's same frame: most (frame) / frames above | "
          f"within {bt.QUALITY_TOL} dB of budget 0 from frame | log2 PSNR dB, frames {' / '.join(map(str, marks))} |")
    print("|---|---|---|---|---|---|---|---|---|")
    for k, ms in best.items():
        ms, p = np.array(ms), np.array(psnr[k])
        gap = np.flatnonzero(p < ref - bt.QUALITY_TOL) if ref is not None else None
        reach = "-" if gap is None else str(int(gap[-1] + 1) if len(gap) else 0)
        print(f"| {k} | {ms.mean():.1f} | {ms.max():.1f} | {np.median(ms[n // 2:]):.1f} | {bt.live_lost(list(ms))} | "
              f"{ms.mean() / p0.mean():.2f} / {ms.max() / p0.max():.2f} | {(ms / p0).max():.2f} "
              f"({int(np.argmax(ms / p0))}) / {int(np.sum(ms > p0))} | {reach} | "
              f"{' / '.join(f'{p[i]:.2f}' for i in marks)} |")
    for b in budgets:
        tr = bt.temporal(b)
        work = []
        for v, s in classified(raws, prof, bt):
            work.append(tr.process(v, s, noise=prof)["work"])
        work = np.array(work[1:])
        print(f"budget {b}: FSE work a frame, frames 1-{n - 1}: {work.min() / 1e3:.1f} - {work.max() / 1e3:.1f} "
              f"thousand (median {np.median(work) / 1e3:.1f})")
    return 0


def classified(raws, prof, bt):
    """The raw frames classified as `benchmarks/temporal.py` `timed` classifies them."""
    from nrhdr_core import validity
    s = bt.SETTINGS
    return [validity.classify(raw, prof, mode=s.mode, l_min=s.l_min, dark_policy=s.dark_policy) for raw in raws]


if __name__ == "__main__":
    sys.exit(main())
