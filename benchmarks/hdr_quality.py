"""HDR quality of the whole chain on real HDR scenes, per region, against an unmodified camera.

    python benchmarks/hdr_quality.py --quick     # 160 x 128 crops, 1 frame per scene, fse only (~2-3 min)
    python benchmarks/hdr_quality.py             # 512 x 384, 2 frames per scene, fse/linear/preview
    python benchmarks/hdr_quality.py --cost      # ms of the issue-8 stages at 1920 x 1080 beside an anchor
    python benchmarks/hdr_quality.py --snr       # flat-field SNR over exposure per dark policy (Fig. 5 style)
    python benchmarks/hdr_quality.py --dark      # the dark-region error split: regular / ND pixels, fusion
                                                 # against its inputs and oracle bounds (~1 min, no GStreamer)

The five shared HDR scenes (../shared/data/hdr/*.exr, or $NRHDR_SHARED_DATA/hdr) are simulated with shot and
read noise through a sensor with the `prototype` crosstalk preset (docs/CROSSTALK.md); that sensor is
calibrated from simulated flats (`calibration.simulate_flats` + `calibrate`, as `nrhdr simulate-flats` /
`nrhdr calibrate` do), and every configuration runs through the GStreamer chain

    filesrc ! rawvideoparse ! nrvalidity ! nrcrosstalk ! nrreconstruct ! nrexrsink      (`nrhdr launch`)

for masks (non-regular, regular 2 x 2) x dark handling (paper threshold l_min 100, l_min 400, noise-aware
`dark-policy=weighted`) x methods. Baseline: an unmodified camera (no ND pixel, same noise and exposure):
its clipped pixels are filled from their bound. Metrics (`nrhdr_core.metrics.hdr_report`): log2 PSNR with a
1 DN floor and the peak log2(white) (the same for every configuration), PU21-PSNR (white shown at 4000
cd/m^2), pixels more than 1 / 3 stops off, per region of the truth: dark < l_min x ND, bright >= the
regular clip, mid between. Truth and output are compared up to the ND pixels' white (beyond it nothing
is measured). Writes bench_out/hdr_quality/results.json and results.md.
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from nrhdr_core import (calibration, crosstalk, io, metrics, profile, reconstruction, sensor,  # noqa: E402
                        simulate, validity)

DATA = Path(os.environ.get("NRHDR_SHARED_DATA", ROOT.parent / "shared" / "data"))
OUT = ROOT / "bench_out" / "hdr_quality"
SCENES = ("KernerEnvLatLong", "Desk", "MtTamWest", "StillLife", "Tree")
POLICIES = {"threshold l_min 100": ("threshold", 100.0), "threshold l_min 400": ("threshold", 400.0),
            "noise-aware (weighted)": ("weighted", 100.0)}


def make_frames(h, w, frames, prof, model, seed, scenes):
    """Raw frames and truths of every scene, one clip: the camera pans over each scene."""
    raws, truths, names = [], [], []
    rng = np.random.default_rng(seed)
    for path in scenes:
        name = Path(path).stem
        sc = io.read_luminance(path)
        k = simulate.exposure_scale(sc, prof, 0.0)
        for i in range(frames):
            t = 0.3 + 0.4 * i / max(frames - 1, 1)
            flux = simulate.view(sc, h, w, t, simulate.Motion()) * np.float32(k)
            raws.append(sensor.capture(flux, prof, rng, sensor_model=model))
            truths.append(flux)
            names.append(name)
    return raws, truths, names


def calibrate_sensor(prof, model, folder, quick):
    """Flats + calibration; a denser sweep when the short one cannot measure the ND factor."""
    for i, n in enumerate((16 if quick else 24, 40)):
        d = folder / f"flats{i}"
        calibration.simulate_flats(d, prof, model, exposures=calibration.default_exposures(n),
                                   frames_per_exposure=2 if quick else 3, seed=11, progress=False)
        sweep = calibration.read_flats(d, progress=False)
        try:
            res = calibration.calibrate(sweep, prof.mask, progress=False)
            break
        except calibration.CalibrationError:
            if n == 40:
                raise
    return profile.save(res.profile, folder / "cam.json")


def run_chain(raw_path, cam, h, w, n, policy, l_min, method, outdir):
    from gst_plugins.runtime import gst_env
    outdir.mkdir(parents=True, exist_ok=True)
    cmd = [sys.executable, "-m", "gst_plugins.cli", "launch", "-q", "filesrc", f"location={raw_path}", "!",
           "rawvideoparse", "format=gray16-le", f"width={w}", f"height={h}", "framerate=5/1",
           f"plane-strides=<{2 * w}>", "!", "nrvalidity", f"profile={cam}", f"l-min={l_min}",
           f"dark-policy={policy}", "!", "nrcrosstalk", "!", "nrreconstruct", f"method={method}",
           "post-stats=false", "!", "nrexrsink", f"location={outdir}/f_%04d.exr"]
    t0 = time.perf_counter()
    r = subprocess.run(cmd, env=gst_env(), capture_output=True, text=True, timeout=1800)
    if r.returncode != 0:
        raise RuntimeError(f"chain failed ({policy}, {method}): {r.stderr[-2000:]}")
    dt = time.perf_counter() - t0
    return [io.read_exr(outdir / f"f_{i:04d}.exr")[0] for i in range(n)], dt


def camera_baseline(truths, h, w, seed):
    """Unmodified camera: no ND pixel, same noise and exposure; clipped pixels at their bound."""
    p0 = profile.make(np.zeros((h, w), bool))
    rng = np.random.default_rng(seed)
    outs = []
    for t in truths:
        raw = sensor.capture(t, p0, rng)
        v, s = validity.classify(raw, p0)
        lo, hi = validity.bounds(v, s)
        outs.append(reconstruction.reconstruct(v, validity.known_mask(s), method="preview", lower=lo,
                                               upper=hi))
    return outs


def score(truths, outs, prof):
    """Per-region scores of a set of frames (`metrics.clip_report`, the same as `nrhdr compare`): regions by
    l_min x ND and the regular clip, both capped at the ND camera's white."""
    r = metrics.clip_report(zip(truths, outs), prof.l_min * prof.nd, prof.regular_white, prof.white)
    r.pop("frames")
    return r


def cost() -> int:
    """Milliseconds of the issue-8 additions on one 1920 x 1080 frame (Desk), min of 5, beside an
    anchor (a copy of one float32 frame) measured in the same run."""
    import timeit
    from nrhdr_core import fse
    h, w = 1080, 1920
    prof = profile.default(h, w)
    sc = io.read_luminance(DATA / "hdr" / "Desk.exr")
    t = simulate.view(sc, h, w, 0.3, simulate.Motion()) * np.float32(simulate.exposure_scale(sc, prof, 0))
    raw = sensor.capture(t, prof, np.random.default_rng(0))
    v, s = validity.classify(raw, prof, dark_policy="weighted")
    k, nz = validity.known_mask(s), validity.noisy_mask(s)
    lo, hi = validity.bounds(v, s)
    o = v.copy()

    def tm(f, n=5):
        f()
        return min(timeit.repeat(f, number=1, repeat=n)) * 1e3
    rows = [("anchor: copy of one float32 frame", tm(lambda: v.copy())),
            ("classify, threshold", tm(lambda: validity.classify(raw, prof))),
            ("classify, weighted", tm(lambda: validity.classify(raw, prof, dark_policy="weighted"))),
            ("bounds (with the clipped-neighbour bound)", tm(lambda: validity.bounds(v, s))),
            ("fse.log_offset", tm(lambda: fse.log_offset(v, k, 2.0, lo))),
            ("data-range clamp", tm(lambda: reconstruction._clamp_to_data(o, v, k, ~k, lo))),
            (f"noise fusion accurate, the default ({100 * nz.mean():.0f} % NOISY)",
             tm(lambda: reconstruction.fuse_noisy(o, v, k, nz, prof))),
            (f"noise fusion fast ({100 * nz.mean():.0f} % NOISY)",
             tm(lambda: reconstruction.fuse_noisy(o, v, k, nz, prof, setting="fast"))),
            ("preview, whole dispatcher, weighted",
             tm(lambda: reconstruction.reconstruct(v, k, method="preview", lower=lo, upper=hi, noisy=nz,
                                                   noise=prof))),
            ("fse balanced, weighted", tm(lambda: reconstruction.reconstruct(v, k, lower=lo, upper=hi, noisy=nz,
                                                                             noise=prof), 2)),
            ("fse balanced, weighted, local_bound=0",
             tm(lambda: reconstruction.reconstruct(v, k, lower=lo, upper=hi, noisy=nz, noise=prof,
                                                   local_bound=0), 2))]
    print("| stage (1920 x 1080, Desk) | ms |\n|---|---|")
    for name, ms in rows:
        print(f"| {name} | {ms:.1f} |")
    return 0


def flat_snr() -> int:
    """SNR (20 log10(mean / std), paper Eq. 4/7) of the whole reconstructed frame of 96 x 96 flat fields
    over the exposure range, per dark policy (FSE balanced, non-regular mask), beside one noisy frame of
    an unmodified camera: the paper's Fig. 5 comparison extended to the noise-aware policy."""
    h = w = 96
    prof = profile.default(h, w)
    p0 = profile.make(np.zeros((h, w), bool))
    rng = np.random.default_rng(0)
    cols = [("threshold l_min 100", 100.0, "threshold"), ("threshold l_min 400", 400.0, "threshold"),
            ("weighted", 100.0, "weighted")]
    print("| flux DN | unmodified camera | " + " | ".join(c[0] for c in cols) + " |")
    print("|---" * (2 + len(cols)) + "|")
    for lv in 2.0 ** np.arange(1, 15):
        t = np.full((h, w), lv, np.float32)
        v0, _ = validity.classify(sensor.capture(t, p0, rng), p0)
        row = [metrics.snr_db(v0)]
        raw = sensor.capture(t, prof, rng)
        for _, lm, pol in cols:
            v, s = validity.classify(raw, prof, l_min=lm, dark_policy=pol)
            lo, hi = validity.bounds(v, s)
            k = validity.known_mask(s)
            o = reconstruction.reconstruct(v, k, lower=lo, upper=hi, noisy=validity.noisy_mask(s), noise=prof)
            row.append(metrics.snr_db(o))
        print(f"| {lv:.0f} | " + " | ".join(f"{x:.2f}" for x in row) + " |")
    return 0


def dark_split(scenes) -> int:
    """Where the dark-region error comes from (the target: within 2 dB of the unmodified camera):
    512 x 384, one view per scene, no crosstalk, FSE balanced in-process (the chain's default stages).
    The unmodified camera and the ND camera share the noise of the regular pixels (same raw code there),
    so the two differ only at the ND pixels. Log2 PSNR (1 DN floor, peak log2(white)) pooled over the
    dark pixels (truth < l_min x ND) of all scenes, split into regular and ND positions, for: the
    camera; the chain's noise fusion (accurate, fast); its inputs alone (ND measurement; FSE with the
    NOISY pixels missing); an oracle inverse-variance fusion of the FSE estimate g and the measurement m
    with the true error, w = (g - t)^2 / ((g - t)^2 + var_m(t)); the same with g from noise-free
    regular pixels (sampling error only; measured pixels keep their noisy value): how far an
    interpolate-then-fuse estimator can go. Joint FSE: the NOISY measurements enter FSE's
    fit weighted `reconstruction.noisy_weights` (x JOINT_FACTOR) instead of being missing; alone, with
    the fusions, a blend, its oracle fusion, and a leave-one-out variant (two FSE runs, each with the
    NOISY pixels of the even / odd rows as samples and the others estimated: an estimate independent
    of the pixel's own measurement, fused by the oracle)."""
    h, w = 384, 512
    p0 = profile.make(np.zeros((h, w), bool))
    print("log2 PSNR dB in dark regions (truth < l_min x ND), pooled over "
          f"{len(scenes)} scenes, {w} x {h}, no crosstalk; regular pixels share the camera's noise\n")
    for pattern in ("nonregular", "regular"):
        prof = profile.default(h, w, seed=3, pattern=pattern)
        mask = prof.mask
        peak = float(np.log2(prof.white))
        acc = {}

        def add(name, t, o, sel_nd, sel_reg):
            lt = np.log2(np.maximum(t, 1.0))
            e = (lt - np.log2(np.maximum(o, 1.0))) ** 2
            a = acc.setdefault(name, np.zeros(4))
            a += (e[sel_nd].sum(), sel_nd.sum(), e[sel_reg].sum(), sel_reg.sum())

        for si, path in enumerate(scenes):
            sc = io.read_luminance(path)
            t = simulate.view(sc, h, w, 0.3, simulate.Motion()) * np.float32(simulate.exposure_scale(sc, prof, 0))
            raw0 = sensor.capture(t, p0, np.random.default_rng(100 + si))
            raw = np.where(mask, sensor.capture(t, prof, np.random.default_rng(200 + si)), raw0).astype(np.uint16)
            v0, _ = validity.classify(raw0, p0)
            v, s = validity.classify(raw, prof, dark_policy="weighted")
            k, nz = validity.known_mask(s), validity.noisy_mask(s)
            lo, hi = validity.bounds(v, s)
            g = reconstruction.reconstruct(v, k, lower=lo, upper=hi)
            gt = reconstruction.reconstruct(np.where(k, t, 0).astype(np.float32), k, lower=lo, upper=hi)
            dark = t < prof.l_min * prof.nd
            nd_, reg = dark & mask, dark & ~mask
            t64 = t.astype(np.float64)
            vm = validity.measurement_variance(t, prof)
            fuse = reconstruction.fuse_noisy
            rows = [("unmodified camera", v0),
                    ("chain: FSE + noise fusion accurate (default)", fuse(g.copy(), v, k, nz, prof)),
                    ("chain: FSE + noise fusion fast", fuse(g.copy(), v, k, nz, prof, setting="fast")),
                    ("ND measurement alone", np.where(nz, v, g)),
                    ("FSE interpolation alone (NOISY missing)", g)]
            for name, gi in (("oracle fusion of the FSE interpolation", g),
                             ("oracle fusion of FSE from noise-free regular pixels", gt)):
                e2 = (gi.astype(np.float64) - t64) ** 2
                wgt = e2 / (e2 + vm)
                rows.append((name, np.where(k, v, np.where(nz, gi + wgt * (v - gi), gi))))
            rows.append(("FSE from noise-free regular pixels alone", np.where(k, v, gt)))
            # `reconstruct`'s own NOISY path, FSE reconstructing the NOISY pixels
            # (before) and skipping them (the default for the accurate fusion), same frame
            for name, flag in (("reconstruct(noisy=): FSE at NOISY + fusion accurate (before)", False),
                               ("reconstruct(noisy=): FSE skips NOISY + fusion accurate", True)):
                rows.append((name, reconstruction.reconstruct(v, k, lower=lo, upper=hi, noisy=nz, noise=prof,
                                                              noisy_skip=flag)))
            rows += _joint_rows(v, k, nz, lo, hi, prof, t64, vm, rows[1][1])
            for name, o in rows:
                add(name, t64, np.asarray(o, np.float64), nd_, reg)
        print(f"#### {pattern} mask\n\n| estimate | ND pixels | regular pixels | whole dark region |\n"
              "|---|---|---|---|")
        f = lambda sse, n: 10 * np.log10(peak ** 2 / (sse / n)) if n else float("nan")
        for name, (e1, n1, e2, n2) in acc.items():
            print(f"| {name} | {f(e1, n1):.2f} | {f(e2, n2):.2f} | {f(e1 + e2, n1 + n2):.2f} |")
        print()
    return 0


JOINT_FACTOR = 2.0     # measured best of 0.5 / 1 / 2 / 4 for the joint estimate alone (docs/BENCHMARKS.md)


def _joint_rows(v, k, nz, lo, hi, prof, t64, vm, acc):
    """`dark_split`'s joint-FSE rows: (name, estimate) pairs."""
    from nrhdr_core import fse
    R = reconstruction
    miss = ~k

    def joint(wts):
        gj = fse.fse_reconstruct(v, k, lo, hi, weights=wts)
        return R._apply_bounds(R._clamp_to_data(gj, v, k, miss, lo), miss, lo, hi)

    wts = R.noisy_weights(v, nz, prof, JOINT_FACTOR)
    gj = joint(wts)
    half = np.broadcast_to((np.arange(v.shape[0]) % 2 == 0)[:, None], v.shape)     # even / odd rows
    gl = np.where(half, joint(np.where(half, 0, wts)), joint(np.where(half, wts, 0)))

    def oracle(gi):
        e2 = (gi.astype(np.float64) - t64) ** 2
        return np.where(nz, gi + e2 / (e2 + vm) * (v - gi), gi)

    return [(f"joint FSE alone (NOISY weighted x{JOINT_FACTOR:g})", gj),
            ("joint FSE + noise fusion accurate (reconstruct noisy_joint=2)",
             R.reconstruct(v, k, lower=lo, upper=hi, noisy=nz, noise=prof, noisy_joint=JOINT_FACTOR)),
            ("joint FSE + noise fusion fast", R.fuse_noisy(gj.copy(), v, k, nz, prof, setting="fast")),
            ("0.3 joint FSE + 0.7 accurate fusion (best blend)", np.where(nz, 0.3 * gj + 0.7 * acc, gj)),
            ("oracle fusion of the joint FSE", oracle(gj)),
            ("leave-one-out joint FSE alone", gl),
            ("oracle fusion of the leave-one-out joint FSE", oracle(gl))]


def table(rows):
    head = ("| configuration | neg / non-finite | log2 PSNR all / dark / mid / bright dB | "
            "PU21-PSNR all / dark / mid / bright dB | > 1 stop | > 3 stops | s |")
    lines = [head, "|" + "---|" * 7]
    f = lambda x: "-" if x is None else f"{x:.2f}"
    for name, r, dt in rows:
        lines.append(f"| {name} | {r['negative']} / {r['nonfinite']} | "
                     + " / ".join(f(r[k]["log2_psnr"]) for k in ("all", "dark", "mid", "bright")) + " | "
                     + " / ".join(f(r[k]["pu21_psnr"]) for k in ("all", "dark", "mid", "bright")) + " | "
                     + f"{r['all']['off_1stop']} | {r['all']['off_3stops']} | {dt:.1f} |")
    return "\n".join(lines)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--quick", action="store_true", help="160 x 128 crops, 1 frame per scene, fse only")
    ap.add_argument("--methods", default=None, help="comma-separated methods (default: fse,linear,preview; "
                                                    "--quick: fse)")
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--scenes", nargs="+", default=None,
                    help="HDR scene files (EXR/HDR, luminance) instead of the five shared ones, e.g. held-out "
                         "scenes")
    ap.add_argument("--cost", action="store_true", help="only time the issue-8 stages at 1920 x 1080")
    ap.add_argument("--snr", action="store_true", help="only the flat-field SNR table over exposure")
    ap.add_argument("--dark", action="store_true", help="only the dark-region error split (regular / ND "
                                                        "pixels, fusion inputs, oracle bounds)")
    ap.add_argument("--out", default=str(OUT))
    a = ap.parse_args(argv)
    scenes = a.scenes or [str(DATA / "hdr" / f"{n}.exr") for n in SCENES]
    missing = [p for p in scenes if not Path(p).is_file()]
    if missing:
        print(f"hdr_quality: scene file(s) not found: {', '.join(missing)} (set NRHDR_SHARED_DATA or "
              f"pass --scenes)", file=sys.stderr)
        return 2
    if a.cost:
        return cost()
    if a.snr:
        return flat_snr()
    if a.dark:
        return dark_split(scenes)
    h, w, frames = (128, 160, 1) if a.quick else (384, 512, 2)
    methods = (a.methods or ("fse" if a.quick else "fse,linear,preview")).split(",")
    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    t_start = time.perf_counter()
    results, md = {}, []
    base_rows = None
    with tempfile.TemporaryDirectory(prefix="hdrq_") as tmp:
        tmp = Path(tmp)
        for pattern in ("nonregular", "regular"):
            prof = profile.default(h, w, seed=3, pattern=pattern)
            model = crosstalk.sensor_model_preset("prototype", h, w, seed=2)
            # both masks calibrate (the checkerboard from the sensor's outer ring): a
            # CalibrationError here is a real failure and stops the benchmark
            cam = calibrate_sensor(prof, model, tmp / pattern, a.quick)
            xt = "prototype crosstalk, calibrated"
            cprof = profile.load(cam)
            raws, truths, names = make_frames(h, w, frames, prof, model, a.seed, scenes)
            raw_path = tmp / pattern / "clip.raw"
            with io.RawVideoWriter(raw_path, w, h) as wr:
                for r in raws:
                    wr.write(r)
            if base_rows is None:
                t0 = time.perf_counter()
                base = camera_baseline(truths, h, w, a.seed + 100)
                rb = score(truths, base, cprof)
                base_rows = ("unmodified camera (no ND, same noise)", rb, time.perf_counter() - t0)
                results["camera"] = rb
            rows = [base_rows]
            for method in methods:
                for pname, (policy, lm) in POLICIES.items():
                    outs, dt = run_chain(raw_path, cam, h, w, len(raws), policy, lm, method,
                                         tmp / pattern / f"{method}_{policy}_{lm:g}")
                    r = score(truths, outs, cprof)
                    key = f"{pattern} | {method} | {pname}"
                    results[key] = r
                    rows.append((f"{method}, {pname}", r, dt))
                    f2 = lambda x: "-" if x is None else f"{x:.2f}"
                    print(f"{key}: log2 PSNR dark {f2(r['dark']['log2_psnr'])} mid {f2(r['mid']['log2_psnr'])} "
                          f"bright {f2(r['bright']['log2_psnr'])} neg {r['negative']} ({dt:.1f} s)", flush=True)
            md.append(f"### {pattern} mask ({xt})\n\n" + table(rows) + "\n")
    total = time.perf_counter() - t_start
    info = {"quick": a.quick, "size": [w, h], "scenes": scenes, "frames_per_scene": frames, "methods": methods,
            "seed": a.seed, "seconds": total, "results": results}
    (out / "results.json").write_text(json.dumps(info, indent=1) + "\n")
    text = (f"{w} x {h}, {frames} frame(s) per scene, {len(scenes)} scenes, prototype crosstalk calibrated from "
            f"simulated flats, total {total:.0f} s (chain seconds include each gst-launch start)\n\n"
            + "\n".join(md))
    (out / "results.md").write_text(text)
    print(text)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
