"""Crosstalk on a Bayer sensor: white-light against per-colour calibration, LUT (full and compact) and kernel
mode, and the speed of the colour settings at 1080p.

Calibrates a simulated 128 x 96 rggb sensor (crosstalk preset `prototype`) from flat sweeps under white, red,
green and blue light (`calibration.simulate_flats(light=...)`, `calibration.colour_spill`), then corrects
captures without shot or read noise (saturated red and blue flats, white flats, a StillLife crop) and prints the
mean (median) |relative error| of the attenuated photosites per channel R, G, B for each setting and
calibration (`lut full` / `lut compact` / `kernel`; white: the calibration without its per-colour amplitudes),
and the mean |compact - full| / full of the per-colour calibration's lut settings.

`--speed`: ms per 1920 x 1080 frame of `crosstalk.correct` mode lut with the compact LUT on a monochrome
profile (the anchor), and with the compact and the full LUT on a colour profile whose calibration has
per-colour amplitudes (a synthetic 40-knot table with the simulated sensor's spill table and amplitudes tiled),
alternating, median of `--repeats`, with the load average.

    .venv/bin/python benchmarks/colour_crosstalk.py OUT_FOLDER [--coupling 1.3,1.0,0.8] [--speed]

`--passes`: CPU time (`time.process_time`: every thread's, so that the figures hold on a shared machine) per
1920 x 1080 frame of each pass of the colour compact setting (`_colour_compact_planes`, `_colour_compact_clipped`,
`_colour_compact_correct`) and of the monochrome compact kernel (`_lut_kernel_compact`, the anchor), on a
smooth coloured scene (R : G : B = 1.2 : 1 : 0.7, a gradient and a clipped patch) with a synthetic 40-knot table
and a spill table like the prototype sensor's (`stages.prototype_spill`: 1 % / 1.2 % / 0.3 % coupling, blooming
beyond the clip), interleaved, minimum of `--repeats`; with the share of VALID
pixels whose corrected code left its compact-LUT segment (read again).

    .venv/bin/python benchmarks/colour_crosstalk.py OUT_FOLDER --passes [--scene PATH.exr]

`--scene`: the passes on an HDR scene instead (`benchmarks/colour.py`'s 1080p frame of it and its synthetic
40-knot calibration with per-colour amplitudes 1.15 / 1.0 / 0.85 and the same spill table; the anchor on the
scene's luminance).

`--coupling`: the sensor model's crosstalk per source colour (`SensorModel.colour_coupling`). The scene crop
needs ../shared/data/hdr/StillLife.exr ($NRHDR_SHARED_DATA/hdr); without it that row is skipped.
"""
from __future__ import annotations

import argparse
import dataclasses as D
import os
import sys
import time
from pathlib import Path

import numpy as np
from numba import get_num_threads

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
    ap.add_argument("--speed", action="store_true", help="also time the colour settings at 1920 x 1080")
    ap.add_argument("--passes", action="store_true", help="only the CPU time of the colour compact passes")
    ap.add_argument("--repeats", type=int, default=7, help="timed calls per setting (--speed, --passes)")
    ap.add_argument("--scene", default=None, help="--passes on this HDR scene (.exr) instead of the synthetic one")
    a = ap.parse_args(argv)
    if a.scene and not a.passes:
        ap.error("--scene goes with --passes")
    if a.passes:
        passes(a.repeats, a.scene)
        return 0
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

    settings = (("lut full", "lut", "full"), ("lut compact", "lut", "compact"), ("kernel", "kernel", "full"))

    def corrected(p, mode, lut, raw):
        v, s = V.classify(raw, p, "threshold", l_min=0)
        X.correct(v, s, p, mode, lut=lut)
        return v, s

    def scored(truth, s):
        ok = ((s & V.REASON_MASK) == V.VALID) & prof.mask & (truth >= 20)
        ok[:2] = ok[-2:] = ok[:, :2] = ok[:, -2:] = False
        return ok

    def per_channel(r, ok):
        return " / ".join(f"{100 * np.mean(r[ok & (chan == c)]):.1f} ({100 * np.median(r[ok & (chan == c)]):.1f})"
                          for c in range(3))

    def row(name, truth):
        raw = sensor.capture(truth, quiet, rng, sensor_model=model, shot_noise=False)
        cells, out = [], {}
        for label, mode, lut in settings:
            for c, p in (("white", white), ("per-colour", col)):
                v, s = out[label, c] = corrected(p, mode, lut, raw)
                r = np.abs(v - truth) / np.maximum(truth, 1.0)   # scored only where truth >= 20
                cells.append(f"| {label}, {c} cal.: {per_channel(r, scored(truth, s))} %")
        (vf, sf), (vc, sc) = out["lut full", "per-colour"], out["lut compact", "per-colour"]
        d = np.abs(vc - vf) / np.maximum(vf, 1.0)
        cells.append(f"| per-colour compact vs full: {per_channel(d, scored(truth, sf))} %"
                     f"{'' if np.array_equal(sf, sc) else ' (states differ)'}")
        print(f"{name:<16}", *cells)

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
    if a.speed:
        speed(col.crosstalk, a.repeats)
    return 0


def speed(small, repeats: int) -> None:
    """ms per 1920 x 1080 frame: mono compact (anchor), colour compact, colour full, alternating."""
    sys.path.insert(0, str(ROOT / "benchmarks"))
    from stages import synthetic_calibration
    h, w = 1080, 1920
    prof = P.default(h, w, cfa="rggb")
    table = synthetic_calibration(prof, 40)
    reps = (-(-h // small.colour.shape[1]), -(-w // small.colour.shape[2]))   # the tile keeps the Bayer phase
    colour = np.ascontiguousarray(np.tile(small.colour, (1,) + reps)[:, :h, :w])
    cal = D.replace(table, sig_e=small.sig_e, sigma=small.sigma, colour=colour)
    mono = D.replace(prof, cfa="none").replace(crosstalk=table)
    colr = prof.replace(crosstalk=cal)
    rng = np.random.default_rng(0)
    raw = np.clip(prof.black_level + rng.gamma(1.5, 600.0, (h, w)), 0, prof.clip_code).astype(np.uint16)
    v0, s0 = V.classify(raw, prof, "threshold")
    runs = {"mono lut compact (anchor)": (mono, "compact"), "colour lut compact (fast)": (colr, "compact"),
            "colour lut full (accurate)": (colr, "full")}
    for p, lut in runs.values():          # compile / derive the compact LUT first
        X.compact_for(p)
        X.correct(v0.copy(), s0.copy(), p, "lut", lut=lut)
    ms = {k: [] for k in runs}
    for i in range(repeats):
        for k, (p, lut) in runs.items():
            if "full" in k and i >= max(2, repeats // 3):
                continue                  # ~1.5 s a call: a few suffice
            v, s = v0.copy(), s0.copy()
            t0 = time.perf_counter()
            X.correct(v, s, p, "lut", lut=lut)
            ms[k].append(1e3 * (time.perf_counter() - t0))
    load = os.getloadavg()
    anchor = np.median(ms["mono lut compact (anchor)"])
    print(f"speed, 1920 x 1080, {os.cpu_count()} CPUs, load average {load[0]:.2f} {load[1]:.2f} {load[2]:.2f}:")
    for k, t in ms.items():
        print(f"  {k:<28} {np.median(t):8.1f} ms (min {np.min(t):.1f}, {len(t)} calls) "
              f"= {np.median(t) / anchor:.1f} x anchor")


def passes(repeats: int, scene: str | None = None) -> None:
    """CPU ms per 1920 x 1080 frame of the colour compact passes and of the monochrome compact kernel."""
    sys.path.insert(0, str(ROOT / "benchmarks"))
    from stages import prototype_spill, synthetic_calibration
    h, w = 1080, 1920
    prof = P.default(h, w, seed=3)
    table = synthetic_calibration(prof, 40)
    sig_e, sigma = prototype_spill(float(prof.clip_code) - float(prof.black_level))
    table = D.replace(table, sig_e=sig_e, sigma=sigma)
    amp = np.ascontiguousarray(table.alpha[None] * np.asarray((1.15, 1.0, 0.85), np.float32)[:, None, None])
    colr = prof.replace(cfa="rggb", crosstalk=D.replace(table, colour=amp))
    mono = prof.replace(crosstalk=table)
    rng = np.random.default_rng(0)
    if scene is None:
        xx = np.arange(w)[None, :].repeat(h, 0)
        lum = (200 + 3000 * (xx / w) ** 2).astype(np.float32)
        lum[300:500, 600:900] = 60000
        rgb = np.stack([lum * 1.2, lum, lum * 0.7])
    else:
        import colour as cb
        from nrhdr_core import metrics
        rgb = cb.truth_of(cb.read_scene(scene), colr)
        lum = metrics.luminance(rgb).astype(np.float32)
    raw = sensor.capture(cfa.mosaic(rgb, "rggb"), colr, rng)
    v0, s0 = V.classify(raw, colr)
    vm, sm = V.classify(sensor.capture(lum, mono, rng), mono)
    c, cm = X.compact_for(colr).record(), X.compact_for(mono).record()
    sb, pairs, blk = X.spill_basis(colr.crosstalk), X.colour_pairs(colr.crosstalk, "rggb"), cfa.block("rggb")
    src = np.empty((X.SRC_PLANES, h, w), np.float32)
    tgt = np.empty((X.TGT_PLANES, h, w), np.float32)
    ncl = np.empty(h, np.int64)
    vp, sp = v0.copy(), s0.copy()
    X._colour_compact_planes(vp, sp, c, sb.basis, sb.inv_de, src, tgt, ncl)
    nd, cf = float(colr.nd), colr.crosstalk.clip_flux
    runs = {"_colour_compact_planes": lambda: X._colour_compact_planes(v0.copy(), s0.copy(), c, sb.basis, sb.inv_de,
                                                                       src, tgt, ncl),
            "_colour_compact_clipped": lambda: X._colour_compact_clipped(vp, sp, src, tgt, sb.basis, sb.inv_de, nd,
                                                                         blk, ncl, get_num_threads()),
            "_colour_compact_correct": lambda: X._colour_compact_correct(vp.copy(), sp, c, cf, src, tgt, sb.weight,
                                                                         pairs, blk, ncl),
            "_lut_kernel_compact (anchor)": lambda: X._lut_kernel_compact(vm.copy(), sm.copy(), cm,
                                                                          mono.crosstalk.clip_flux)}
    for f in runs.values():
        f()
    ms = {k: [] for k in runs}
    for _ in range(repeats):
        for k, f in runs.items():
            t0 = time.process_time()
            f()
            ms[k].append(1e3 * (time.process_time() - t0))
    again = np.isfinite(tgt[X._TGT_O0]) & ((sp & V.REASON_MASK) == V.VALID)
    anchor = min(ms["_lut_kernel_compact (anchor)"])
    load = os.getloadavg()
    valid = max(1, int(np.sum((sp & V.REASON_MASK) == V.VALID)))
    print(f"CPU ms per 1920 x 1080 frame (all threads), {os.cpu_count()} CPUs, load average {load[0]:.2f}; "
          f"{100 * np.mean((s0 & V.REASON_MASK) == V.CLIPPED):.1f} % CLIPPED, "
          f"{100 * again.sum() / valid:.1f} % of VALID read again:")
    for k, t in ms.items():
        print(f"  {k:<30} {min(t):7.1f} ms (median {np.median(t):.1f}) = {min(t) / anchor:.2f} x anchor")
    total = sum(min(ms[k]) for k in list(ms)[:3])
    print(f"  {'colour compact, three passes':<30} {total:7.1f} ms = {total / anchor:.2f} x anchor")


if __name__ == "__main__":
    raise SystemExit(main())
