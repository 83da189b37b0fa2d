"""The ND mask, ND and defect pixels found in flat-field sweeps without a mask (nrhdr_core/flats.py,
`nrhdr calibrate` without --mask), measured against sweeps of known sensors.

For each sensor model preset (crosstalk strength), noise level (read noise, frames per exposure) and mask
pattern: `calibration.simulate_flats` writes a sweep as a user would (default 40 exposures), `read_flats` reads
it, 5 hot (+300 DN offset), 5 dead (dark level throughout) and 5 stuck (code 1500 in every frame) pixels are
planted into the per-exposure statistics, then `flats.detect` runs and `calibration.calibrate` calibrates
with the mask it found and, as the anchor, with the true mask. Reported: misclassified pixels (the planted
dead/stuck pixels excluded: their kind cannot be measured), the detector's ND and the calibrated ND against
the truth, defects found / missed / false, the separation and the ambiguous share, and whether the detection
counts as confident. A second table lowers the ND to where the two populations meet (the confidence figures
against the errors).

    .venv/bin/python benchmarks/mask_detect.py [--size 128] [--quick] [--json bench_out/mask_detect.json]
"""
from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from nrhdr_core import calibration, crosstalk, flats, profile  # noqa: E402

NOISE = {"low": (2.0, 4), "mid": (10.0, 2), "high": (40.0, 2)}      # read noise (e-), frames per exposure
N_DEFECTS = 5
TRANSITION_ND = (1.1, 1.2, 1.3, 1.5, 2.0)


def plant(sweep: calibration.FlatSweep, rng) -> np.ndarray:
    """Plant N_DEFECTS hot, dead and stuck pixels into the sweep's statistics; return the truth map."""
    H, W = sweep.shape
    pos = rng.choice(H * W, 3 * N_DEFECTS, replace=False)
    truth = np.zeros((H, W), np.uint8)
    for k, p in enumerate(pos):
        y, x = divmod(int(p), W)
        m, mx, tv = sweep.mean[:, y, x], sweep.maxcode[:, y, x], sweep.tvar[:, y, x]
        if k < N_DEFECTS:                                             # hot: offset, saturates earlier
            m[:] = np.minimum(m + 300, m[-1])
            mx[:] = np.minimum(mx.astype(np.int64) + 300, mx[-1])
            truth[y, x] = flats.DEFECT_HOT
        elif k < 2 * N_DEFECTS:                                       # dead: the dark level throughout
            m[:], mx[:], tv[:] = m[0], mx[0], tv[0]
            truth[y, x] = flats.DEFECT_DEAD
        else:                                                         # stuck: one code in every frame
            m[:], mx[:], tv[:] = 1500, 1500, 0
            truth[y, x] = flats.DEFECT_STUCK
    return truth


def run_case(preset, noise, pattern, size, seed, folder, nd=6.35, calibrate=True):
    h, w = size
    read_noise, frames = NOISE[noise]
    prof = profile.default(h, w, seed=seed, pattern=pattern, nd=nd).replace(read_noise=read_noise)
    model = crosstalk.sensor_model_preset(preset, h, w, seed=seed + 1)
    out = Path(folder) / f"{preset}_{noise}_{pattern}_{nd:g}"
    calibration.simulate_flats(out, prof, model, frames_per_exposure=frames, seed=seed, progress=False)
    sweep = calibration.read_flats(out, progress=False)
    truth = plant(sweep, np.random.default_rng(seed))
    t0 = time.perf_counter()
    det = flats.detect(sweep)
    t_det = time.perf_counter() - t0
    measurable = ~np.isin(truth, (flats.DEFECT_DEAD, flats.DEFECT_STUCK))
    mis = int(np.sum(det.mask[measurable] != prof.mask[measurable]))
    planted = truth > 0
    found = int(np.sum(planted & (det.defects == truth)))
    false = int(np.sum(~planted & (det.defects > 0)))
    nd_cal, nd_anchor = float("nan"), float("nan")
    if calibrate:
        try:
            nd_cal = calibration.calibrate(sweep, det.mask, progress=False).summary["nd"]
            nd_anchor = calibration.calibrate(sweep, prof.mask, progress=False).summary["nd"]
        except calibration.CalibrationError:
            pass
    return {"preset": preset, "noise": noise, "read_noise_e": read_noise, "frames": frames, "pattern": pattern,
            "misclassified": mis, "pixels": int(measurable.sum()), "nd_true": prof.nd,
            "nd_detector": det.nd, "nd_detector_err_pct": 100 * (det.nd / prof.nd - 1),
            "nd_calibrated": nd_cal, "nd_calibrated_err_pct": 100 * (nd_cal / prof.nd - 1),
            "nd_true_mask": nd_anchor, "nd_true_mask_err_pct": 100 * (nd_anchor / prof.nd - 1),
            "defects_planted": int(planted.sum()), "defects_found": found,
            "defects_missed": int(planted.sum()) - found, "defects_false": false,
            "separation": det.separation, "ambiguous_pct": 100 * det.ambiguous, "confident": det.confident,
            "detect_s": t_det}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size", type=int, default=128, help="sensor height and width (pixels)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--quick", action="store_true", help="the prototype preset and the non-regular mask only")
    ap.add_argument("--json", default="bench_out/mask_detect.json")
    a = ap.parse_args(argv)
    presets = ["prototype"] if a.quick else ["none", "mild", "linear", "prototype"]
    patterns = ["nonregular"] if a.quick else ["nonregular", "regular", "bluenoise"]
    rows = []
    print(f"{a.size} x {a.size}, ND 6.35, {N_DEFECTS} hot / dead / stuck pixels planted, masks: {', '.join(patterns)}; "
          f"per row the sum (misclassified, defects) or the range (ND errors, separation, ambiguous) over the masks\n")
    print("| preset | noise (read e-, frames) | misclassified | ND detector err % | ND calibrated err % | "
          "anchor: ND with the true mask err % | defects found / missed / false | separation | ambiguous % | "
          "confident |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    with tempfile.TemporaryDirectory() as tmp:
        for preset in presets:
            for noise in NOISE:
                rs = [run_case(preset, noise, pattern, (a.size, a.size), a.seed, tmp) for pattern in patterns]
                rows += rs
                def rng(k, f, rs=rs):
                    return f"{f.format(min(r[k] for r in rs))} .. {f.format(max(r[k] for r in rs))}"

                def tot(k, rs=rs):
                    return sum(r[k] for r in rs)
                print(f"| {preset} | {noise} ({rs[0]['read_noise_e']:g}, {rs[0]['frames']}) | {tot('misclassified')} "
                      f"of {tot('pixels')} | {rng('nd_detector_err_pct', '{:+.2f}')} | "
                      f"{rng('nd_calibrated_err_pct', '{:+.2f}')} | {rng('nd_true_mask_err_pct', '{:+.2f}')} | "
                      f"{tot('defects_found')} / {tot('defects_missed')} / "
                      f"{tot('defects_false')} | {rng('separation', '{:.0f}')} | {rng('ambiguous_pct', '{:.3f}')} | "
                      f"{sum(r['confident'] for r in rs)} of {len(rs)} |", flush=True)
        if not a.quick:
            print("\nSmall ND factors (where the populations meet), prototype preset, high noise, non-regular mask:\n")
            print("| ND | misclassified | ND detector (err %) | separation | ambiguous % | confident |")
            print("|---|---|---|---|---|---|")
            for nd in TRANSITION_ND:
                r = run_case("prototype", "high", "nonregular", (a.size, a.size), a.seed, tmp, nd=nd, calibrate=False)
                r["table"] = "transition"
                rows.append(r)
                print(f"| {nd:g} | {r['misclassified']} of {r['pixels']} | {r['nd_detector']:.3f} "
                      f"({r['nd_detector_err_pct']:+.2f}) | {r['separation']:.1f} | {r['ambiguous_pct']:.3f} | "
                      f"{'yes' if r['confident'] else 'no'} |", flush=True)
    out = Path(a.json)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps({"size": a.size, "seed": a.seed, "nd": rows[0]["nd_true"], "rows": rows},
                              indent=1) + "\n")
    print(f"wrote {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
