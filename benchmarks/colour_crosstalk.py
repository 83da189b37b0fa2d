"""Crosstalk on a Bayer sensor: white-light against per-colour calibration, LUT and kernel mode.

Calibrates a simulated 128 x 96 rggb sensor (crosstalk preset `prototype`) from flat sweeps under white, red,
green and blue light (`calibration.simulate_flats(light=...)`, `calibration.colour_spill`), then corrects
captures without shot or read noise (saturated red and blue flats, white flats, a StillLife crop) and prints the
mean (median) |relative error| of the attenuated photosites per channel R, G, B for each mode and calibration.

    .venv/bin/python benchmarks/colour_crosstalk.py OUT_FOLDER [--coupling 1.3,1.0,0.8]

`--coupling`: the sensor model's crosstalk per source colour (`SensorModel.colour_coupling`). The scene crop
needs ../shared/data/hdr/StillLife.exr ($NRHDR_SHARED_DATA/hdr); without it that row is skipped.
"""
from __future__ import annotations

import argparse
import dataclasses as D
import os
from pathlib import Path

import numpy as np

from nrhdr_core import calibration as C
from nrhdr_core import cfa, io
from nrhdr_core import crosstalk as X
from nrhdr_core import profile as P
from nrhdr_core import sensor
from nrhdr_core import validity as V

ROOT = Path(__file__).resolve().parents[1]
DATA = Path(os.environ.get("NRHDR_SHARED_DATA", ROOT.parent / "shared" / "data"))
H, W = 96, 128
LIGHTS = {"white": None, "red": (1, .2, .1), "green": (.2, 1, .2), "blue": (.1, .2, 1)}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("out", type=Path, help="folder for the simulated flats (replaced)")
    ap.add_argument("--coupling", default=None, help="R,G,B crosstalk per source colour")
    a = ap.parse_args(argv)
    prof = P.default(H, W, cfa="rggb")
    model = X.sensor_model_preset("prototype", H, W)
    if a.coupling:
        model = D.replace(model, colour_coupling=tuple(float(v) for v in a.coupling.split(",")))
    for i, (k, light) in enumerate(LIGHTS.items()):
        C.simulate_flats(a.out / k, prof, model, seed=i, light=light, progress=False, overwrite=True)
    white = C.calibrate(C.read_flats(a.out / "white", progress=False), prof.mask, cfa="rggb",
                        progress=False).profile
    cs = C.colour_spill(white, [C.read_flats(a.out / k, progress=False) for k in ("red", "green", "blue")])
    col = D.replace(white, crosstalk=D.replace(white.crosstalk, colour=cs.colour))
    chan = cfa.channel_index("rggb", H, W)
    quiet = D.replace(prof, read_noise=0.0)
    rng = np.random.default_rng(9)

    def err(p, mode, truth):
        raw = sensor.capture(truth, quiet, rng, sensor_model=model, shot_noise=False)
        v, s = V.classify(raw, p, "threshold", l_min=0)
        X.correct(v, s, p, mode)
        ok = ((s & V.REASON_MASK) == V.VALID) & prof.mask & (truth >= 20)
        ok[:2] = ok[-2:] = ok[:, :2] = ok[:, -2:] = False
        r = np.abs(v - truth) / np.maximum(truth, 1.0)   # scored only where truth >= 20
        return " / ".join(f"{100 * np.mean(r[ok & (chan == c)]):.1f} ({100 * np.median(r[ok & (chan == c)]):.1f})"
                          for c in range(3))

    def row(name, truth):
        print(f"{name:<16}", *(f"| {m}, {c} cal.: {err(p, m, truth)} %" for m in ("lut", "kernel")
                               for c, p in (("white", white), ("per-colour", col))))

    for name, light in {"sat-red": (1, .1, .05), "sat-blue": (.05, .1, 1), "white": (1, 1, 1)}.items():
        for level in ((50., 100., 1000., 6000.) if name == "white" else (1000., 6000.)):
            row(f"{name} {level:g} DN", level * np.asarray(light, float)[chan])
    exr = DATA / "hdr" / "StillLife.exr"
    if exr.is_file():
        rgb = io.read_rgb(exr)[:, 300:300 + 4 * H, 500:500 + 4 * W].reshape(3, H, 4, W, 4).mean((2, 4))
        scene = cfa.mosaic(rgb, "rggb").astype(np.float64)
        scene *= 4 * prof.clip_code / np.percentile(scene, 99)
        row("StillLife crop", scene)
    else:
        print(f"StillLife crop: {exr} not found (set NRHDR_SHARED_DATA)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
