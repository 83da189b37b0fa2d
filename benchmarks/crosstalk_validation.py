"""Crosstalk validation (docs/CROSSTALK.md): one command,

    .venv/bin/python benchmarks/crosstalk_validation.py            # ~30 s on 2 cores
    .venv/bin/python benchmarks/crosstalk_validation.py --quick    # smaller sensors, 2 scenes

For simulated sensors with known crosstalk it writes a flat-field sweep as a user would capture it (16-bit
TIFF + exposures.csv), runs the same code as `nrhdr calibrate`, and reports
- the recovered ND against the truth and the calibrated 3 x 3 kernel against the model's;
- the residual crosstalk error before and after correction ("off", "lut", "kernel") on flat fields and on
  natural scenes (the shared EXR scenes, noise-free captures so that only crosstalk remains; plus a noisy
  capture), for all known pixels, attenuated ones, and attenuated pixels at strong edges;
- for the prototype-like preset, the paper's figures: ND 6.35 (2.7 stops), ND_eff of an example pixel 3.87,
  dynamic-range gain 2.1 / 2.4 stops at 40 % / 20 % known pixels.
Sensors: `prototype` (the preset: non-uniform, signal-dependent, blooming, PRNU/DSNU), `linear` (uniform
linear 1 % kernel), `none`, and `independent`: a plain scipy convolution with a different, non-conserving
kernel and ND 8, written here without the project's sensor model (as an outside tester would), once
conserving (centre 1 - sum of the kernel) and once not (`independent-nc`, centre 1).
Writes docs/img/crosstalk_*.png and benchmarks/results/crosstalk_validation.json, the committed results, only
from a complete run (all default sensors at the default size, natural scenes found, not --quick). Any other
run writes to bench_out/crosstalk_validation/ instead (or to --json / --img, which must not exist yet unless
--force). Files are made in a temporary folder and moved in at the end: never a partial result.
"""
from __future__ import annotations

import argparse
import json
import math
import os
import shutil
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from nrhdr_core import calibration, crosstalk, io, profile, sensor, validity  # noqa: E402

SCENES_DIR = Path(os.environ.get("NRHDR_SHARED_DATA", ROOT.parent / "shared" / "data")) / "hdr"
MIN_FLUX = 20.0
SENSORS = ["prototype", "linear", "independent", "independent-nc", "none"]
DEFAULT_SIZE = (192, 256)
EVAL_MODES = ("off", "lut", "lut-compact", "kernel")   # lut-compact: the LUT's fast setting (compact form)
DEFAULT_JSON = ROOT / "benchmarks" / "results" / "crosstalk_validation.json"
DEFAULT_IMG = ROOT / "docs" / "img"
PARTIAL_DIR = ROOT / "bench_out" / "crosstalk_validation"


class IndependentModel:
    """An outside tester's sensor: a plain scipy convolution of the light after the ND filters with a
    3 x 3 kernel (edges 1.5 % along rows, 2 % along columns, corners 0.5 %). Centre 1 - sum (conserving, the
    textbook model of docs/hdr-references.md) or 1 (`conserving=False`: every pixel gains light)."""

    def __init__(self, edge_h=0.015, edge_v=0.02, corner=0.005, conserving=True):
        self.kernel = crosstalk.make_kernel(edge_h, edge_v, corner)
        self.conserving = conserving

    def apply(self, e, prof, rng=None):
        from scipy.ndimage import correlate
        k = self.kernel.copy()
        k[1, 1] = 1.0 - self.kernel.sum() if self.conserving else 1.0
        return correlate(np.asarray(e, np.float64), k, mode="constant", cval=0.0)

    def truth(self):
        return {"name": "independent", "kernel": self.kernel.tolist(), "conserving": self.conserving}


def make_sensor(name, h, w, seed=0):
    if name in ("independent", "independent-nc"):
        prof = profile.default(h, w, seed=seed + 11, nd=8.0)
        return prof, IndependentModel(conserving=(name == "independent"))
    prof = profile.default(h, w, seed=seed + 1)
    return prof, crosstalk.sensor_model_preset(name, h, w, seed=seed + 2)


def load_scene(path, h, w):
    lum = io.read_luminance(path).astype(np.float64)
    f = max(1, min(lum.shape[0] // h, lum.shape[1] // w))
    H, W = lum.shape[0] // f * f, lum.shape[1] // f * f
    lum = lum[:H, :W].reshape(H // f, f, W // f, f).mean(axis=(1, 3))
    y0, x0 = (lum.shape[0] - h) // 2, (lum.shape[1] - w) // 2
    if y0 < 0 or x0 < 0:
        from scipy.ndimage import zoom
        lum = zoom(lum, max(h / lum.shape[0], w / lum.shape[1]) + 1e-3, order=1)
        y0, x0 = (lum.shape[0] - h) // 2, (lum.shape[1] - w) // 2
    return np.maximum(lum[y0:y0 + h, x0:x0 + w], 0.0)


def expose(lum, prof):
    """Scale so that the 99.5th percentile sits at 1.2 x the attenuated pixels' nominal range."""
    top = prof.clip_code - prof.black_level
    p = float(np.percentile(lum, 99.5))
    return lum * (1.2 * prof.nd * top / max(p, 1e-12))


def edge_map(flux):
    from scipy.ndimage import maximum_filter, minimum_filter
    return maximum_filter(flux, 3) > 2.0 * np.maximum(minimum_filter(flux, 3), 1e-9)


def errors(values, state, truth, mask, edges):
    # relative errors are meaningless where quantisation dominates: pixels with truth >= MIN_FLUX DN only
    known = validity.known_mask(state) & (truth >= MIN_FLUX)
    rel = np.abs(values - truth) / np.maximum(truth, 1e-6)
    out = {}
    for key, sel in (("all", known), ("attenuated", known & mask), ("att_edges", known & mask & edges)):
        r = rel[sel]
        out[key] = {"n": int(sel.sum()),
                    "mean_pct": round(float(np.mean(r)) * 100, 3) if r.size else None,
                    "median_pct": round(float(np.median(r)) * 100, 3) if r.size else None,
                    "p95_pct": round(float(np.percentile(r, 95)) * 100, 3) if r.size else None,
                    "bias_pct": round(float(np.mean((values[sel] - truth[sel]) / truth[sel])) * 100, 3)
                    if r.size else None}
    out["known_pct"] = round(float(known.mean()) * 100, 2)
    return out


def evaluate(raw, cal_prof, truth, mask):
    edges = edge_map(truth)
    res = {}
    for mode in EVAL_MODES:
        v, s = validity.classify(raw, cal_prof, mode="threshold")
        if mode == "lut-compact":   # nrcrosstalk mode=lut lut=compact (the fast setting)
            crosstalk.correct(v, s, cal_prof, mode="lut", lut="compact")
        else:
            crosstalk.correct(v, s, cal_prof, mode=mode)
        res[mode] = errors(v, s, truth, mask, edges)
    return res


def run_sensor(name, h, w, scenes, work, seed=0, frames=4):
    t0 = time.time()
    prof, model = make_sensor(name, h, w, seed)
    flats = work / f"flats_{name}"
    truth = calibration.simulate_flats(flats, prof, model, frames_per_exposure=frames, seed=seed, progress=False)
    summary = calibration.run_calibrate(flats, flats / "mask.png", work / f"cal_{name}" / "camera.json",
                                        nd_nominal=prof.nd, plots=(name == "prototype"), progress=False)
    cal = profile.load(work / f"cal_{name}" / "camera.json")
    out = {"sensor": name, "size": [w, h], "nd_true": prof.nd, "nd_measured": summary["nd"],
           "nd_paper_references": summary["nd_paper_references"],
           "nd_error_pct": round(100 * (summary["nd"] / prof.nd - 1), 3), "summary": summary}
    if model is not None:
        tk = np.asarray(model.truth()["kernel"]) * 100
        if isinstance(model, crosstalk.SensorModel) and model.spread is not None:
            tk = tk * float(np.mean(model.spread))
        out["kernel_true_pct"] = np.round(tk, 3).tolist()
    out["kernel_measured_pct"] = summary["kernel_estimate"]
    # noise-free captures: only crosstalk (and quantisation) remains
    clean = prof.replace(read_noise=0.0)
    rng = np.random.default_rng(seed + 100)
    top = prof.clip_code - prof.black_level
    flat_res = {}
    for phi in (0.5, 2.0, 4.0):
        f = np.full((h, w), phi * top)
        raw = sensor.capture(f, clean, rng, sensor_model=model, shot_noise=False)
        flat_res[f"phi_{phi:g}"] = evaluate(raw, cal, f, prof.mask)
    out["flats"] = flat_res
    sc = {}
    for sp in scenes:
        flux = expose(load_scene(sp, h, w), prof)
        raw = sensor.capture(flux, clean, rng, sensor_model=model, shot_noise=False)
        r = evaluate(raw, cal, flux, prof.mask)
        raw_n = sensor.capture(flux, prof, rng, sensor_model=model)
        r["noisy"] = evaluate(raw_n, cal, flux, prof.mask)
        sc[sp.stem] = r
    out["scenes"] = sc
    out["seconds"] = round(time.time() - t0, 1)
    if name == "prototype":
        out["plots"] = summary.get("plots", [])
    return out


def agg(scenes, mode, key, field="mean_pct", noisy=False):
    vals = [(s["noisy"] if noisy else s)[mode][key][field] for s in scenes.values()]
    vals = [v for v in vals if v is not None]
    return round(float(np.mean(vals)), 3) if vals else None


def report(results):
    lines = ["| sensor | ND true | ND measured (error) | ND paper refs | kernel true (%, h/v/corner) | "
             "kernel measured |", "|---|---|---|---|---|---|"]
    for r in results:
        kt = r.get("kernel_true_pct")
        km = r["kernel_measured_pct"]
        f = (lambda k: f"{k[1][0]:.2f}/{k[0][1]:.2f}/{k[0][0]:.2f}" if k else "0")
        lines.append(f"| {r['sensor']} | {r['nd_true']} | {r['nd_measured']:.4f} ({r['nd_error_pct']:+.2f} %) | "
                     f"{r['nd_paper_references']} | {f(kt)} | {f(km)} |")
    lines += ["", "Residual error of known pixels (truth >= 20 DN) vs truth, |relative error| in %, noise-free "
              "captures: flats: mean over pixels and 3 levels; natural scenes: mean over pixels (median in "
              "brackets), averaged over the scenes; all known / attenuated / attenuated at strong edges (3x3 "
              "max/min > 2); last column: attenuated, noisy capture.", "",
              "| sensor | mode | flats all | flats att | scenes all | scenes att | scenes att edges | "
              "scenes att (noisy) |", "|---|---|---|---|---|---|---|---|"]
    for r in results:
        for mode in EVAL_MODES:
            fl = r["flats"]
            if any(mode not in v for v in fl.values()):
                continue
            fa = round(float(np.mean([v[mode]["all"]["mean_pct"] for v in fl.values()])), 3)
            ft = [v[mode]["attenuated"]["mean_pct"] for v in fl.values() if v[mode]["attenuated"]["mean_pct"] is not None]
            ft = round(float(np.mean(ft)), 3) if ft else None
            sc = r["scenes"]
            def mm(key, noisy=False):
                return f"{agg(sc, mode, key, noisy=noisy)} ({agg(sc, mode, key, 'median_pct', noisy)})"
            lines.append(f"| {r['sensor']} | {mode} | {fa} | {ft} | {mm('all')} | {mm('attenuated')} | "
                         f"{mm('att_edges')} | {mm('attenuated', True)} |")
    proto = next((r for r in results if r["sensor"] == "prototype"), None)
    if proto:
        s = proto["summary"]
        lines += ["", "| prototype preset vs paper | paper | measured |", "|---|---|---|",
                  f"| ND | 6.35 (2.67 stops) | {s['nd']:.3f} ({s['nd_stops']:.2f} stops) |",
                  f"| ND_eff example pixel (Eq. 8) | 3.87 | {s['nd_eff_example']} (median {s['nd_eff_median']}, "
                  f"5-95 % {s['nd_eff_p5']}..{s['nd_eff_p95']}, min {s['nd_eff_min']}) |",
                  f"| all attenuated pixels valid up to ND_eff | 2.5 | {s['nd_eff_min']} |",
                  f"| DN_scaled at 40 % known | 18000 | {s['dn_scaled_40']} |",
                  f"| DR gain at 40 % known | 2.1 stops | {s['dr_gain_stops_40']} |",
                  f"| DN_scaled at 20 % known | 21500 | {s['dn_scaled_20']} |",
                  f"| DR gain at 20 % known | 2.4 stops | {s['dr_gain_stops_20']} |"]
    return "\n".join(lines)


def copy_plots(results, img_dir):
    proto = next((r for r in results if r["sensor"] == "prototype"), None)
    if not proto:
        return
    for p in proto.get("plots", []):
        p = Path(p)
        dest = img_dir / ("crosstalk_" + p.name.split("_calib_")[-1])
        shutil.copyfile(p, dest)


def plot_modes(results, img_dir):
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    fig, ax = plt.subplots(figsize=(7, 3.6), dpi=90)
    names = [r["sensor"] for r in results]
    x = np.arange(len(names))
    for i, mode in enumerate(("off", "lut", "kernel")):
        vals = [agg(r["scenes"], mode, "att_edges") or 0 for r in results]
        ax.bar(x + (i - 1) * 0.27, vals, 0.27, label=mode)
    ax.set_xticks(x, names)
    ax.set_ylabel("mean |rel. error| (%)")
    ax.set_title("Attenuated pixels at strong edges, natural scenes (noise-free)")
    ax.legend()
    fig.tight_layout()
    fig.savefig(img_dir / "crosstalk_modes.png")
    plt.close(fig)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--quick", action="store_true", help="96x128 sensors, 2 scenes")
    ap.add_argument("--size", type=int, nargs=2, metavar=("H", "W"), default=DEFAULT_SIZE)
    ap.add_argument("--sensors", nargs="+", default=SENSORS)
    ap.add_argument("--json", help="results file (default: benchmarks/results/crosstalk_validation.json for a "
                                   "complete run, else bench_out/crosstalk_validation/crosstalk_validation.json)")
    ap.add_argument("--img", help="plot folder (default: docs/img for a complete run, else "
                                  "bench_out/crosstalk_validation/img)")
    ap.add_argument("--force", action="store_true", help="replace an existing --json / --img plots")
    a = ap.parse_args(argv)
    h, w = (96, 128) if a.quick else tuple(a.size)
    scenes = sorted(SCENES_DIR.glob("*.exr"))
    if not scenes:
        print(f"note: no EXR scenes in {SCENES_DIR}; natural-scene rows are skipped", file=sys.stderr)
    if a.quick:
        scenes = scenes[:2]
    why = [m for m, bad in (("--quick", a.quick), (f"size {h}x{w} is not {DEFAULT_SIZE}", (h, w) != tuple(DEFAULT_SIZE)),
                            ("not all sensors", not set(SENSORS) <= set(a.sensors)),
                            (f"no natural scenes in {SCENES_DIR}", not scenes)) if bad]
    complete = not why
    json_path = Path(a.json) if a.json else (DEFAULT_JSON if complete else PARTIAL_DIR / "crosstalk_validation.json")
    img_dir = Path(a.img) if a.img else (DEFAULT_IMG if complete else PARTIAL_DIR / "img")
    if not complete:
        print(f"note: partial run ({'; '.join(why)}): the committed results are left alone; writing "
              f"{json_path} and {img_dir}/", file=sys.stderr)
    plot_names = ["crosstalk_modes.png"] + (["crosstalk_curves.png", "crosstalk_nd_eff.png",
                                             "crosstalk_valid_ratio.png"] if "prototype" in a.sensors else [])
    explicit = [p for p, given in ((json_path, a.json), *((img_dir / n, a.img) for n in plot_names)) if given]
    clash = [str(p) for p in explicit if p.exists()]
    if clash and not a.force:
        print(f"crosstalk_validation: error: {', '.join(clash)} exist(s); choose new paths or pass --force",
              file=sys.stderr)
        return 2
    results = []
    with tempfile.TemporaryDirectory(prefix="nrhdr_xt_") as tmp:
        work = Path(tmp)
        stage = work / "_out"
        stage.mkdir()
        for name in a.sensors:
            print(f"[{name}] {w}x{h}: flats, calibration, evaluation ...", file=sys.stderr, flush=True)
            results.append(run_sensor(name, h, w, scenes, work))
        copy_plots(results, stage)
        plot_modes(results, stage)
        for r in results:
            r["summary"].pop("plots", None)
            r["summary"].pop("profile", None)
            r["summary"].pop("flats", None)
            r.pop("plots", None)
        (stage / "results.json").write_text(json.dumps(results, indent=1) + "\n")
        # everything computed: move into place (same-folder temp + rename per file)
        img_dir.mkdir(parents=True, exist_ok=True)
        json_path.parent.mkdir(parents=True, exist_ok=True)
        for p in sorted(stage.glob("crosstalk_*.png")):
            t = img_dir / f".{p.name}.tmp"
            shutil.copyfile(p, t)
            os.replace(t, img_dir / p.name)
        t = json_path.with_name(f".{json_path.name}.tmp")
        shutil.copyfile(stage / "results.json", t)
        os.replace(t, json_path)
    print(report(results))
    print(f"\n(raw results: {json_path}; plots: {img_dir}/)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
