"""Mask benchmark (docs/PAPER.md): the paper's core claim, non-regular sampling + FSE against the
regular checkerboard, measured for several mask designs on the same inputs in one run.

    .venv/bin/python benchmarks/masks.py --quick     # ~1-2 min on 2 cores: 256 px crops, fewer images
    .venv/bin/python benchmarks/masks.py             # full: Kodak 01-08 at 768 x 512, 5 HDR scenes
    .venv/bin/python benchmarks/masks.py --images 'other/*.png'   # 8-bit images the project never saw

Masks (nrhdr_core.mask): random (the paper's iid), cell2 (2 of 4 per 2 x 2 cell, Jonscher et al.),
cell2diag (a checkerboard with random phase per 2 x 2 cell), bluenoise (error diffusion of 50 % grey with a
randomised threshold; `bluenoise:J` sets the jitter J), voidcluster (Ulichney's void-and-cluster on a 128 x 128
tile; `voidcluster:S` sets the filter width S), regular (checkerboard). All exactly half attenuated.
Cases (the mask's attenuated pixels are the missing ones for 8-bit content: 50 % known):
  zoneplate  N x N zone plate, local frequency rising to 0.45 cycles/pixel (then constant)
  texture    three gratings at 0.38-0.45 cycles/pixel (sparse in Fourier, aliased by the checkerboard)
  kodak      grayscale Kodak images (or --images), PSNR over 255
  hdr        shared EXR scenes captured by the non-regular sensor (ND 6.35, l_min 100, shot + read noise),
             the 95th percentile 2 stops over the regular pixels' clipping; log-PSNR against the clipped truth;
             `hdr+xt`: the prototype crosstalk preset, LUT-compensated after a flat-field calibration per mask
Reconstruction: FSE preset balanced (`--preset`), domain linear for 8-bit content, the default for HDR.
Writes bench_out/masks/results.json and results.md (the table docs/PAPER.md quotes).
"""
from __future__ import annotations

import argparse
import glob
import json
import os
import platform
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from nrhdr_core import chain, figures, mask as masks, metrics, reconstruction  # noqa: E402

DATA = Path(os.environ.get("NRHDR_SHARED_DATA", ROOT.parent / "shared" / "data"))
OUT = ROOT / "bench_out" / "masks"


def make(spec: str, h: int, w: int, seed: int) -> np.ndarray:
    name, _, arg = spec.partition(":")
    if name == "bluenoise" and arg:
        return masks.bluenoise_mask(h, w, seed=seed, jitter=float(arg))
    if name == "voidcluster" and arg:
        return masks.voidcluster_mask(h, w, seed=seed, sigma=float(arg))
    return masks.make_mask(name, h, w, seed=seed)


def kodak_images(pattern, quick):
    import cv2
    if pattern:
        files = sorted(glob.glob(pattern))
    else:
        files = [str(DATA / "kodak" / f"kodim0{i}.png") for i in range(1, 9)]
        files = [f for f in files if Path(f).exists()]
    if quick:
        files = files[::2]
    out = []
    for f in files:
        g = cv2.imread(f, cv2.IMREAD_GRAYSCALE)
        if g is None:
            raise SystemExit(f"{f}: not a readable image")
        g = g.astype(np.float32)
        if quick:
            y0, x0 = (g.shape[0] - 256) // 2, (g.shape[1] - 256) // 2
            g = g[max(y0, 0):max(y0, 0) + 256, max(x0, 0):max(x0, 0) + 256]
        out.append((Path(f).stem, g))
    return out


def run_8bit(specs, images, preset, seeds):
    rows = []
    for name, img in images:
        h, w = img.shape
        for spec in specs:
            ps = []
            for s in seeds:
                m = make(spec, h, w, s)
                r = reconstruction.reconstruct(img, ~m, method="fse", preset=preset, domain="linear")
                ps.append(metrics.psnr(img, np.clip(r, 0, 255), peak=255.0))
            rows.append({"image": name, "mask": spec, "psnr": float(np.mean(ps))})
    return rows


def run_hdr(specs, scenes, size, preset, crosstalk_on, seed=0):
    from nrhdr_core import calibration, crosstalk, profile, sensor, validity
    rows = []
    for sp in scenes:
        lum = figures.load_hdr_scene(sp, size)
        h, w = lum.shape
        for spec in specs:
            prof = profile.make(make(spec, h, w, seed + 1))
            flux = lum * (4.0 * prof.regular_white / float(np.percentile(lum[lum > 0], 95)))
            model, cal = None, prof
            if crosstalk_on:
                model = crosstalk.sensor_model_preset("prototype", h, w, seed=seed + 2)
                with tempfile.TemporaryDirectory(prefix="nrhdr_masks_") as tmp:
                    calibration.simulate_flats(Path(tmp) / "f", prof, model, frames_per_exposure=2,
                                               seed=seed + 3, progress=False)
                    sweep = calibration.read_flats(Path(tmp) / "f", progress=False)
                try:
                    cal = calibration.calibrate(sweep, prof.mask, nd_nominal=prof.nd, progress=False).profile
                except calibration.CalibrationError as e:
                    rows.append({"image": Path(sp).stem, "mask": spec, "crosstalk": True, "log_psnr": None,
                                 "error": str(e).split(": ", 1)[-1]})
                    continue
            raw = sensor.capture(flux, prof, np.random.default_rng(seed + 4), sensor_model=model)
            v, s = validity.classify(raw, cal, "threshold")
            if crosstalk_on:
                crosstalk.correct(v, s, cal, mode="lut")
            k = validity.known_mask(s)
            lo, up = validity.bounds(v, s)
            r = reconstruction.reconstruct(v, k, method="fse", preset=preset, lower=lo, upper=up)
            truth = np.minimum(flux, cal.white)
            rows.append({"image": Path(sp).stem, "mask": spec, "crosstalk": bool(crosstalk_on),
                         "log_psnr": metrics.log_psnr(truth, np.clip(r, 0, cal.white)),
                         "known_pct": round(100 * float(k.mean()), 2)})
    return rows


def run_dr(specs, h, w, seed=0):
    """Crosstalk against the mask: calibrate the prototype preset (flat sweep, `nrhdr calibrate`'s code) per
    mask and report the effective ND (Eq. 8) and the dynamic-range gain at 40 % / 20 % known (section 4.2).
    Also the mean number of regular 4-neighbours of an attenuated pixel (the source of the spill, 3.1)."""
    from scipy.ndimage import correlate
    from nrhdr_core import calibration, crosstalk, profile
    rows = []
    for spec in specs:
        m = make(spec, h, w, seed + 1)
        nreg = correlate((~m).astype(float), np.array([[0, 1, 0], [1, 0, 1], [0, 1, 0]], float), mode="mirror")
        row = {"mask": spec, "regular_4nb_of_attenuated": round(float(nreg[m].mean()), 3)}
        prof = profile.make(m)
        model = crosstalk.sensor_model_preset("prototype", h, w, seed=seed + 2)
        with tempfile.TemporaryDirectory(prefix="nrhdr_masks_dr_") as tmp:
            calibration.simulate_flats(Path(tmp) / "f", prof, model, seed=seed + 3, progress=False)
            sweep = calibration.read_flats(Path(tmp) / "f", progress=False)
        try:
            s = calibration.calibrate(sweep, m, nd_nominal=prof.nd, progress=False).summary
            row.update({k: s[k] for k in ("nd", "nd_eff_median", "nd_eff_min", "dr_gain_stops_40",
                                          "dr_gain_stops_20")})
        except calibration.CalibrationError as e:
            row["error"] = str(e).split(": ", 1)[-1]
        rows.append(row)
    return rows


def dr_table(rows):
    keys = ("regular_4nb_of_attenuated", "nd", "nd_eff_median", "nd_eff_min", "dr_gain_stops_40",
            "dr_gain_stops_20")
    lines = ["| mask | regular 4-neighbours of an attenuated pixel | ND measured | ND_eff median | ND_eff min | "
             "DR gain 40 % known (stops) | DR gain 20 % known |", "|---" * 7 + "|"]
    for r in rows:
        vals = [str(r.get(k, "n/a")) for k in keys]
        lines.append(f"| {r['mask']} | " + " | ".join(vals) + " |" + (f" calibration failed: {r['error']}"
                                                                       if "error" in r else ""))
    return "\n".join(lines)


def table(rows, key, specs):
    imgs = list(dict.fromkeys(r["image"] for r in rows))
    lines = ["| image | " + " | ".join(specs) + " |", "|---" * (len(specs) + 1) + "|"]
    for im in imgs + ["**mean**"]:
        vals = []
        for sp in specs:
            sel = [r[key] for r in rows if r["mask"] == sp and (im == "**mean**" or r["image"] == im)]
            vals.append(f"{np.mean(sel):.2f}" if sel and None not in sel else "n/a")
        lines.append(f"| {im} | " + " | ".join(vals) + " |")
    return "\n".join(lines)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--masks", nargs="+",
                    default=["random", "cell2", "cell2diag", "bluenoise:0.3", "bluenoise", "bluenoise:1.0",
                             "voidcluster", "voidcluster:1.0", "regular"])
    ap.add_argument("--images", help="glob of 8-bit images instead of Kodak 01-08")
    ap.add_argument("--preset", default="balanced")
    ap.add_argument("--seeds", type=int, default=1, help="mask seeds averaged per case")
    ap.add_argument("--no-hdr", action="store_true", help="skip the HDR scenes and the crosstalk table")
    ap.add_argument("--dr-only", action="store_true", help="only the crosstalk / dynamic-range table")
    ap.add_argument("-o", "--output", default=str(OUT))
    a = ap.parse_args(argv)
    t0 = time.time()
    chain.warmup(chain.ChainSettings(method="fse"), stages=("reconstruction",))
    seeds = list(range(a.seeds))
    n = 256 if a.quick else 512
    res = {"quick": a.quick, "preset": a.preset, "masks": a.masks, "machine": platform.platform(),
           "cpus": os.cpu_count()}
    if a.dr_only:
        res["crosstalk_dr"] = run_dr(a.masks, *((96, 128) if a.quick else (192, 256)))
        print(dr_table(res["crosstalk_dr"]))
        return 0
    synth = [("zoneplate", figures.zone_plate(n)), ("texture", figures.hf_texture(n))]
    res["synthetic"] = run_8bit(a.masks, synth, a.preset, seeds)
    print(f"[{time.time() - t0:.0f} s] synthetic done", file=sys.stderr, flush=True)
    imgs = kodak_images(a.images, a.quick)
    res["kodak"] = run_8bit(a.masks, imgs, a.preset, seeds) if imgs else []
    print(f"[{time.time() - t0:.0f} s] natural images done ({len(imgs)})", file=sys.stderr, flush=True)
    res["hdr"] = []
    scenes = sorted((DATA / "hdr").glob("*.exr"))
    if a.quick:
        scenes = scenes[:2]
    if scenes and not a.no_hdr:
        size = 192 if a.quick else 384
        res["hdr"] = run_hdr(a.masks, scenes, size, a.preset, False)
        res["hdr"] += run_hdr(a.masks, scenes, size, a.preset, True)
    print(f"[{time.time() - t0:.0f} s] hdr done ({len(scenes)} scenes)", file=sys.stderr, flush=True)
    res["crosstalk_dr"] = [] if a.no_hdr else run_dr(a.masks, *((96, 128) if a.quick else (192, 256)))
    res["seconds"] = round(time.time() - t0, 1)
    md = [f"Masks benchmark ({'quick' if a.quick else 'full'}, FSE {a.preset}, {res['seconds']} s)", "",
          "Synthetic, PSNR dB (8-bit):", "", table(res["synthetic"], "psnr", a.masks), "",
          f"Natural images ({len(imgs)}), PSNR dB (8-bit):", "", table(res["kodak"], "psnr", a.masks)]
    if res["hdr"]:
        for xt in (False, True):
            rows = [r for r in res["hdr"] if r["crosstalk"] == xt]
            md += ["", f"HDR scenes, noise{' + prototype crosstalk (LUT-compensated)' if xt else ''}, "
                       f"log-PSNR dB:", "", table(rows, "log_psnr", a.masks)]
    if res["crosstalk_dr"]:
        md += ["", "Prototype crosstalk preset, calibrated per mask (Eq. 8, section 4.2):", "",
               dr_table(res["crosstalk_dr"])]
    out = Path(a.output)
    out.mkdir(parents=True, exist_ok=True)
    (out / "results.json").write_text(json.dumps(res, indent=1) + "\n")
    (out / "results.md").write_text("\n".join(md) + "\n")
    print("\n".join(md))
    print(f"\n(written: {out / 'results.json'}, {out / 'results.md'})")
    return 0


if __name__ == "__main__":
    sys.exit(main())
