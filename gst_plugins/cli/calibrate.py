"""`nrhdr calibrate`: crosstalk, ND and sensor calibration from a flat-field sweep (nrhdr_core.calibration,
paper 3.2, 4; docs/CROSSTALK.md); `nrhdr simulate-flats`: a simulated sweep to calibrate."""
from __future__ import annotations

import json
import sys
from pathlib import Path

from nrhdr_core.cfa import CFAS

from .args import CODE_LEVEL, ND, SEED, SIZE, add_allow_outside, number, recorded_cfa, sensor_kind


def _light(text: str):
    """--light r,g,b: three numbers (checked by calibration.check_light)."""
    import argparse
    try:
        v = tuple(float(c) for c in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(f"need three numbers r,g,b, got {text!r}") from None
    if len(v) != 3:
        raise argparse.ArgumentTypeError(f"need three numbers r,g,b, got {text!r}")
    return v


def check_sweep_cfa(folder, cfa: str, option: str = "FLATS") -> None:
    """ValueError when a sweep's truth.json (written by `nrhdr simulate-flats`) records another CFA than `cfa`
    (--cfa): a Bayer mosaic calibrated as a monochrome sensor, or the reverse. Sweeps without truth.json (a
    real camera's) carry no CFA to check."""
    recorded = recorded_cfa(Path(folder) / "truth.json")
    if recorded is not None and recorded != cfa:
        raise ValueError(f"{option} {folder}: its truth.json records a sweep of {sensor_kind(recorded)} sensor "
                         f"(cfa {recorded}), --cfa is {cfa}: give --cfa {recorded}")


def cmd_calibrate(a) -> int:
    from nrhdr_core import calibration, flats, io
    check_sweep_cfa(a.flats, a.cfa)
    for folder in a.colour_flats or ():
        check_sweep_cfa(folder, a.cfa, "--colour-flats")
    find = None if a.mask else flats.finder(a.clip_code, a.bit_depth, a.accept_low_confidence, cfa=a.cfa)
    try:
        s = calibration.run_calibrate(a.flats, a.mask, a.output, nd_nominal=a.nd_nominal, l_min=a.l_min,
                                      clip_code=a.clip_code, bit_depth=a.bit_depth, plots=not a.no_plots,
                                      progress=not a.quiet, overwrite=a.force,
                                      allow_outside=a.allow_outside_paths, find_mask=find, cfa=a.cfa,
                                      colour_flats=a.colour_flats)
    except (calibration.CalibrationError, io.OutputExistsError) as e:
        print(f"nrhdr calibrate: error: {e}", file=sys.stderr)
        return 2
    if a.json:
        print(json.dumps(s, indent=2))
    else:
        print(f"wrote {s['profile']}: ND {s['nd']:.3f} ({s['nd_stops']:.2f} stops)"
              + (f", nominal {s['nd_nominal']} ({s['nd_vs_nominal_pct']:+.1f} %)" if s.get("nd_nominal") else ""))
        if "mask_detection" in s:
            _print_detection(s["mask_detection"])
        if "colour" in s:
            print("  crosstalk per colour (factor per CFA class <- neighbour colour): "
                  + ", ".join(f"{k} {v:.3f}" for k, v in s["colour"]["factor"].items()))
            for name, r in s["colour"]["check"].items():
                print(f"  {name}: attenuated R/G/B mean error " + " / ".join(
                    f"{v:+.1f}" if v is not None else "-" for v in r["white"]) + " % with the white-light LUT, "
                    + " / ".join(f"{v:+.1f}" if v is not None else "-" for v in r["colour"]) + " % per colour")
        print(f"  black {s['black_level']:.1f}, clip code {s['clip_code']}, gain {s['gain_dn_per_e']:.4f} DN/e-, "
              f"read noise {s['read_noise_e']:.2f} e-, full well {s['full_well_e']:.0f} e-")
        print(f"  effective ND (Eq. 8): median {s['nd_eff_median']}, 5-95 % {s['nd_eff_p5']} .. {s['nd_eff_p95']}")
        print(f"  dynamic-range gain: {s['dr_gain_stops_40']} stops at 40 % known, {s['dr_gain_stops_20']} "
              f"stops at 20 % known (paper: 2.1 / 2.4)")
        for p in s.get("plots", []):
            print(f"  plot {p}")
    return 0


def _print_detection(d: dict) -> None:
    df = d["defects"]
    print(f"  mask from the flats: {d['attenuated_share'] * 100:.2f} % attenuated, ND {d['nd']:.3f} by population "
          f"response; separation {d['separation']:.1f} sigma (>= {d['min_separation']:g} needed), ambiguous "
          f"{d['ambiguous_pixels']} pixels ({d['ambiguous_share'] * 100:.3f} %, "
          f"<= {d['max_ambiguous_share'] * 100:g} %)"
          + ("" if d["confident"] else ": LOW CONFIDENCE, accepted"))
    print(f"  defect pixels: {df['hot']} hot, {df['dead']} dead, {df['stuck']} stuck")


def cmd_simulate_flats(a) -> int:
    from nrhdr_core import calibration, crosstalk, io
    from nrhdr_core import profile as profiles
    try:
        if a.profile:
            prof = profiles.load(a.profile, allow_outside=a.allow_outside_paths)
            if a.cfa != "none" and a.cfa != prof.cfa:
                raise ValueError(f"--cfa {a.cfa} disagrees with the profile's cfa {prof.cfa!r}")
        else:
            prof = profiles.default(a.height, a.width, seed=a.mask_seed, nd=a.nd,
                                    **({} if a.cfa == "none" else {"cfa": a.cfa}))
        model = crosstalk.sensor_model_preset(a.sensor_model, prof.height, prof.width, seed=a.sensor_seed)
    except (ValueError, profiles.ProfileError) as e:
        print(f"nrhdr simulate-flats: error: {e}", file=sys.stderr)
        return 2
    try:
        exp = calibration.default_exposures(a.exposures, nd=prof.nd)
        truth = calibration.simulate_flats(a.output, prof, model, exposures=exp, frames_per_exposure=a.frames,
                                           seed=a.seed, fmt=a.format, progress=not a.quiet, overwrite=a.force,
                                           light=a.light)
    except (ValueError, io.OutputExistsError) as e:
        print(f"nrhdr simulate-flats: error: {e}", file=sys.stderr)
        return 2
    print(f"wrote {len(exp) * a.frames} flat frames ({len(exp)} exposures x {a.frames}) to {a.output}/ "
          f"with exposures.csv, mask.png and truth.json (ND {truth['nd']}, sensor model {a.sensor_model}"
          + (f", cfa {truth['cfa']}, light {truth['light']}" if "cfa" in truth else "") + ")")
    print(f"calibrate: nrhdr calibrate {a.output} --mask {Path(a.output) / 'mask.png'}"
          + (f" --cfa {truth['cfa']}" if "cfa" in truth else "") + " -o camera.json")
    return 0


def add_calibrate(sub) -> None:
    p = sub.add_parser("calibrate", help="crosstalk/ND calibration from a flat-field sweep (paper 3.2, 4)",
                       description="Calibrate ND, crosstalk LUT and neighbour kernel from a folder of flat "
                                   "frames + exposures.csv (file,exposure_s); writes a camera profile, plots "
                                   "and a summary. Without --mask the ND mask, the ND and the defect pixels "
                                   "are found in the flats first.")
    p.add_argument("flats", help="folder with 16-bit TIFF/PNG frames and exposures.csv")
    p.add_argument("--mask", help="ND mask PNG (255 = attenuated); without it the ND pixels, the ND and the "
                                  "defect pixels are found in the flats (docs/CROSSTALK.md, 'Without a mask')")
    p.add_argument("--accept-low-confidence", action="store_true",
                   help="without --mask: use the mask found in the flats even when the two populations are not "
                        "well separated")
    p.add_argument("-o", "--output", required=True, help="camera profile JSON to write")
    p.add_argument("--nd-nominal", type=ND, help="nominal ND factor (reported against the measured one)")
    p.add_argument("--l-min", type=CODE_LEVEL, default=100.0, help="l_min for the profile and the valid ratio")
    p.add_argument("--clip-code", type=number(1, 65535, integer=True),
                   help="override the clip code (default: from the saturated frames)")
    p.add_argument("--bit-depth", type=number(1, 16, integer=True), help="ADC bits (default: from the largest code)")
    p.add_argument("--cfa", default="none", choices=CFAS,
                   help="the sensor's colour filter array (Bayer phase; default none: monochrome): the profile's "
                        "cfa, and without --mask the ND pixels are found within each colour plane")
    p.add_argument("--colour-flats", nargs="+", metavar="FOLDER",
                   help="with --cfa: sweeps of the same sensor under coloured light (e.g. red, green, blue) that "
                        "calibrate the crosstalk per colour neighbourhood (docs/COLOUR.md)")
    p.add_argument("--json", action="store_true", help="print the summary as JSON")
    p.add_argument("--no-plots", action="store_true")
    p.add_argument("-q", "--quiet", action="store_true", help="no progress bar")
    p.add_argument("--force", action="store_true",
                   help="replace an existing profile (and its mask, calibration, plots) at --output")
    add_allow_outside(p)
    p.set_defaults(func=cmd_calibrate)


def add_simulate_flats(sub) -> None:
    from nrhdr_core import crosstalk
    p = sub.add_parser("simulate-flats", help="write a simulated flat-field sweep (for calibrate)")
    p.add_argument("output", help="folder to write")
    p.add_argument("--profile", help="camera profile to simulate (default: the paper-like default)")
    p.add_argument("--width", type=SIZE, default=640)
    p.add_argument("--height", type=SIZE, default=480)
    p.add_argument("--nd", type=ND, default=6.35)
    p.add_argument("--mask-seed", type=SEED, default=0)
    p.add_argument("--cfa", default="none", choices=CFAS,
                   help="colour filter array of the default profile (Bayer phase; default none: monochrome)")
    p.add_argument("--light", type=_light,
                   help="r,g,b: coloured light (colour profiles): a photosite's flux is the light's channel of "
                        "its CFA colour x the exposure (default white 1,1,1)")
    p.add_argument("--sensor-model", default="prototype", help=f"one of {crosstalk.PRESETS}")
    p.add_argument("--exposures", type=number(6, 10000, integer=True), default=40,
                   help="number of exposures (incl. dark), at least 6")
    p.add_argument("--frames", type=number(2, 10000, integer=True), default=4,
                   help="frames per exposure, at least 2 (temporal noise)")
    p.add_argument("--format", choices=("tiff", "png"), default="tiff")
    p.add_argument("--seed", type=SEED, default=0, help="noise seed")
    p.add_argument("--sensor-seed", type=SEED, default=0,
                   help="seed of the sensor's pixel-to-pixel variation: use the same value with "
                        "'nrhdr simulate --sensor-seed' to calibrate the sensor that recorded a clip")
    p.add_argument("-q", "--quiet", action="store_true")
    p.add_argument("--force", action="store_true",
                   help="replace the sweep files in an existing folder (other files there are kept)")
    add_allow_outside(p)
    p.set_defaults(func=cmd_simulate_flats)
