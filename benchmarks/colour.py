"""Colour chain quality and speed: a Bayer sensor under the non-regular ND mask against the regular SVE layout and
an unmodified Bayer camera (docs/COLOUR.md, "Measured").

    python benchmarks/colour.py             # 384 x 256 views, 5 HDR scenes, 4 Kodak images, zone plate 256;
                                            # frames/s at 1920 x 1080
    python benchmarks/colour.py --quick     # smoke run: 96 x 64, 2 + 2 images, zone plate 64; frames/s at 320 x 180

Cameras (CFA `rggb`, `profile.default`'s sensor: 12 bit, ND 6.35, half the photosites attenuated):
- `nr-independent`: the non-regular ND mask laid over the CFA without regard to it;
- `nr-balanced`: non-regular on each of the four photosites of the 2 x 2 Bayer block, half of each attenuated;
- `sve`: the regular spatially varying exposure layout (Nayar and Mitsunaga, CVPR 2000) over the colour mosaic as
  in Assorted Pixels (Narasimhan and Nayar, TPAMI 2005): ND on every other 2 x 2 Bayer block in a checkerboard,
  so each colour plane carries a checkerboard of exposures;
- `bayer`: the unmodified Bayer camera (no ND), its codes those of the regular photosites of the others (the
  same shot and read noise), its clipped photosites filled from their bound, as for the monochrome anchor.
The layouts are the simulator's (`mask.cfa_mask`, docs/SIMULATOR.md), over the paper's non-regular mask.

Scenes: the shared HDR scenes (linear RGB, $NRHDR_SHARED_DATA/hdr) and Kodak images (sRGB decoded to linear
light, $NRHDR_SHARED_DATA/kodak), their truth what `nrhdr simulate --cfa` writes (`simulate.ClipRenderer`: the
centred view, fov 0.8, anti-aliased, exposed from the scene's luminance, median at 18 % of the regular pixels'
range); photosite flux = the truth's channel of its CFA colour (unit sensitivities); shot and read noise, no
crosstalk.
Chain: `validity.classify` (defaults: weighted dark policy) -> `demosaic.reconstruct_cfa` (methods `preview`,
`fse` (preset fast) and `fse-best` (fse preset best: the green-guided colour differences)). Colour zone plate (`scene.colour_zone_plate`: achromatic rings around 0.25 and 3 x the
regular clip, and chromatic rings around 0.25), noise-free, so that what is measured is aliasing.

Metrics: log2 PSNR of luminance per region (`metrics.rgb_clip_report`: dark < l_min x ND, bright >= the regular
clip, by the truth's luminance; both capped at the ND camera's white); mean CIEDE2000 of the tone-mapped result
against the tone-mapped truth (`tonemap.tonemap_rgb`, the profile's white, truth capped at it); false colour on
the zone plate (`metrics.false_colour_db`: 10 log10 of the mean squared CIELAB chroma error at the truth's
luminance, on the rings). Frames/s at 1920 x 1080 on the first scene, in the same run: the colour preview
chain (`validity.classify -> crosstalk.correct` (mode lut, compact; a synthetic calibration, with per-colour
amplitudes as a colour camera's and a spill table like the prototype sensor's, `stages.prototype_spill`) `-> reconstruct_cfa
(preview) -> LocalTonemap.rgb`) against the monochrome preview chain of the same sensor (the same stages with
`reconstruction.reconstruct_frame` (preview) and `LocalTonemap`), ms per stage; tone map `--operator` (default
`local`, nrtonemap's; one operator per stream and output buffers reused, as in the elements); passes
interleaved, best of `--repeat`. `--ceiling` adds the colour chain with parts of its model left out (the
calibration's per-colour amplitudes, so that crosstalk takes the monochrome compact kernel; the colour-difference
median; the crosstalk correction and the bounds): how far the frame rate could rise without them.
Writes bench_out/colour/results.json and results.md.
"""
from __future__ import annotations

import argparse
import dataclasses
import importlib.util
import json
import os
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from nrhdr_core import (cfa, chain, crosstalk, demosaic, io, mask, metrics, profile,  # noqa: E402
                        reconstruction, scene, sensor, simulate, tonemap, validity)

DATA = Path(os.environ.get("NRHDR_SHARED_DATA", ROOT.parent / "shared" / "data"))
OUT = ROOT / "bench_out" / "colour"
PATTERN = "rggb"
CAMERAS = ("nr-independent", "nr-balanced", "sve", "bayer")
ND_CAMERAS = CAMERAS[:3]
LABELS = {"nr-independent": "non-regular ND, independent of the CFA", "nr-balanced": "non-regular ND, balanced per "
          "colour", "sve": "regular SVE (Assorted Pixels)", "bayer": "anchor: unmodified Bayer camera"}
METHODS = {"preview": ("preview", "fast"), "fse": ("fse", "fast"), "fse-best": ("fse", "best")}
HDR_SCENES = ("Desk", "KernerEnvLatLong", "MtTamWest", "StillLife", "Tree")
GOALS = {"bright_gain_db": 12.0, "false_colour_db": 3.0, "fps_ratio": 0.70}


# ---- cameras ------------------------------------------------------------------------------------------------

LAYOUT_OF = {"nr-independent": "independent", "nr-balanced": "balanced", "sve": "regular", "bayer": mask.NO_ND}


def nd_mask(camera: str, h: int, w: int, seed: int = 3) -> np.ndarray:
    """bool (h, w): the camera's ND mask over the CFA (`mask.cfa_mask`; none for the unmodified camera)."""
    layout = LAYOUT_OF[camera]
    if layout == mask.NO_ND:
        return np.zeros((h, w), bool)
    return mask.cfa_mask("nonregular", h, w, layout, seed=seed)


def cameras(h, w, **fields) -> dict:
    """{camera: CameraProfile with the CFA} at h x w."""
    return {c: profile.make(nd_mask(c, h, w), cfa=PATTERN, **fields) for c in CAMERAS}


def capture_all(truth_rgb, profs, seed, shot_noise=True) -> dict:
    """Raw frames of every camera from one truth (3, H, W); the regular photosites share the Bayer camera's
    codes (the same noise), the attenuated ones are drawn once per layout."""
    flux = cfa.mosaic(truth_rgb, PATTERN)
    base = sensor.capture(flux, profs["bayer"], np.random.default_rng((seed, 0)), shot_noise=shot_noise)
    out = {"bayer": base}
    for i, c in enumerate(ND_CAMERAS):
        p = profs[c]
        nd = sensor.capture(flux, p, np.random.default_rng((seed, i + 1)), shot_noise=shot_noise)
        out[c] = np.where(p.mask, nd, base).astype(np.uint16)
    return out


# ---- reconstruction and tone mapping ---------------------------------------------------------------------------

def reconstruct_rgb(raw, prof, method, preset):
    """classify (weighted dark policy, the chain's default) -> reconstruct_cfa: linear camera RGB (3, H, W)."""
    values, state = validity.classify(raw, prof, dark_policy="weighted")
    return demosaic.reconstruct_cfa(values, state, prof.cfa, method=method, preset=preset, noise=prof)


def tonemap_rgb(rgb, white, operator):
    return tonemap.tonemap_rgb(np.ascontiguousarray(rgb, dtype=np.float32), float(white), operator=operator)


# ---- scenes -------------------------------------------------------------------------------------------------

VIEW = simulate.Motion(pan=0.0, tilt=0.0, zoom=1.0, fov=0.8)


def read_scene(path: str) -> np.ndarray:
    """Planar linear RGB of an image file: HDR files as stored, 8-bit PNGs (Kodak) sRGB decoded."""
    rgb = io.read_rgb(path)
    return metrics.srgb_decode(rgb).astype(np.float32) if Path(path).suffix.lower() == ".png" else rgb


def truth_of(rgb: np.ndarray, prof) -> np.ndarray:
    """The noise-free camera RGB flux (3, H, W) that `nrhdr simulate --cfa` writes as its truth: the centred
    view (fov 0.8) of the scene exposed from its luminance (`simulate.ClipRenderer`, one frame)."""
    return simulate.ClipRenderer(rgb, prof, 1, 0.0, VIEW).flux(0)


def load_scenes(paths, kodak, prof):
    """[(name, kind, truth flux (3, h, w) float32)] at `prof`'s size (a colour profile)."""
    return [(Path(p).stem, "kodak" if p in kodak else "hdr", truth_of(read_scene(p), prof))
            for p in list(paths) + list(kodak)]


# ---- quality -----------------------------------------------------------------------------------------------

def quality(scenes, h, w, methods, seed, operator, log=print):
    """{method: {kind: {camera: {'report': rgb_clip_report, 'de00': mean CIEDE2000}}}}."""
    profs = cameras(h, w)
    p = profs["nr-independent"]
    dark, bright, white = p.l_min * p.nd, float(p.regular_white), float(p.white)
    res = {m: {} for m in methods}
    for kind in ("hdr", "kodak"):
        sel = [(n, t) for n, k, t in scenes if k == kind]
        if not sel:
            continue
        pairs = {m: {c: [] for c in CAMERAS} for m in methods}
        de = {m: {c: [] for c in CAMERAS} for m in methods}
        for j, (name, truth) in enumerate(sel):
            t0 = time.perf_counter()
            raws = capture_all(truth, profs, seed + 100 * j)
            capped = np.minimum(truth, white)
            tm_truth = tonemap_rgb(capped, white, operator)
            for m in methods:
                meth, preset = METHODS[m]
                for c in CAMERAS:
                    rgb = reconstruct_rgb(raws[c], profs[c], meth, preset)
                    pairs[m][c].append((truth, rgb))
                    de[m][c].append(metrics.mean_ciede2000_srgb(tm_truth, tonemap_rgb(np.minimum(rgb, white),
                                                                                      white, operator)))
            log(f"  {kind} {name}: {time.perf_counter() - t0:.1f} s")
        for m in methods:
            res[m][kind] = {c: {"report": metrics.rgb_clip_report(pairs[m][c], dark, bright, white),
                                "de00": float(np.mean(de[m][c]))} for c in CAMERAS}
    return res


def zone_plate(size, methods, seed):
    """{method: {camera: {panel or 'all': false colour dB}}}, noise-free captures of `scene.colour_zone_plate`."""
    rel, panels = scene.colour_zone_plate(size)
    profs = cameras(size, 3 * size, read_noise=0.0)
    truth = rel * np.float32(profs["bayer"].regular_white)
    raws = capture_all(truth, profs, seed, shot_noise=False)
    rings = np.logical_or.reduce(list(panels.values()))
    res = {}
    for m in methods:
        meth, preset = METHODS[m]
        res[m] = {}
        for c in CAMERAS:
            rgb = reconstruct_rgb(raws[c], profs[c], meth, preset)
            r = {k: metrics.false_colour_db(truth, rgb, pm) for k, pm in panels.items()}
            r["all"] = metrics.false_colour_db(truth, rgb, rings)
            res[m][c] = r
    return res


# ---- speed -------------------------------------------------------------------------------------------------

def _sibling(name):
    """benchmarks/<name>.py as a module (its synthetic calibration, its size parser)."""
    spec = importlib.util.spec_from_file_location(f"bench_{name}", ROOT / "benchmarks" / f"{name}.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


SPILL_BY_COLOUR = (1.15, 1.0, 0.85)   # speed: per-colour amplitude factors, neighbours of R, G, B (longer spill more)
SPEED_STAGES = ("classify", "crosstalk", "reconstruction", "tone map")


def _timed(acc, i, f, *args, **kw):
    t0 = time.perf_counter()
    r = f(*args, **kw)
    acc[i] += time.perf_counter() - t0
    return r


# the colour chain with parts of its colour model left out (`--ceiling`): what the frame rate could be without them
CEILING = {
    "colour-white-crosstalk": "colour, the monochrome crosstalk kernel (the calibration without its per-colour "
                              "amplitudes)",
    "colour-white-crosstalk-no-median": "colour, the monochrome crosstalk kernel, no colour-difference median",
    "colour-no-crosstalk-median-bounds": "colour, no crosstalk correction, no median, no bounds (`use_bounds=False`)",
}


def speed(scene_path, h, w, frames, repeat, operator, seed, ceiling=False):
    """{'mono' | 'colour': {'fps': frames/s, 'ms': {stage: ms per frame}}} of the preview chains at h x w (the
    stages called as the elements call them), passes interleaved, the best of `repeat` after an untimed frame;
    `ceiling`: also the colour chain without parts of its model (CEILING; the same frames)."""
    base = profile.default(h, w, seed=3)
    stages = _sibling("stages")
    calib = stages.synthetic_calibration(base, 40)
    mono = base.replace(crosstalk=calib)
    # the colour correction with a spill table like the prototype sensor's (the mono LUT mode reads none)
    sig_e, sigma = stages.prototype_spill(float(base.clip_code) - float(base.black_level))
    calib = dataclasses.replace(calib, sig_e=sig_e, sigma=sigma)
    # a colour camera's calibration has per-colour amplitudes (`calibration.colour_spill`): here the pixel's
    # white-light amplitude times SPILL_BY_COLOUR for neighbours of R, G, B
    amp = calib.alpha[None] * np.asarray(SPILL_BY_COLOUR, np.float32)[:, None, None]
    col = base.replace(cfa=PATTERN, crosstalk=dataclasses.replace(calib, colour=np.ascontiguousarray(amp)))
    truth = truth_of(read_scene(scene_path), col)
    rng = np.random.default_rng(seed)
    raws_m = [sensor.capture(metrics.luminance(truth).astype(np.float32), mono, rng) for _ in range(frames)]
    raws_c = [sensor.capture(cfa.mosaic(truth, PATTERN), col, rng) for _ in range(frames)]
    crosstalk.compact_for(mono)
    crosstalk.compact_for(col)
    sm = chain.ChainSettings(method="preview", crosstalk="lut", operator=operator)
    # as the elements do: one LocalTonemap per stream, output buffers reused (nrreconstruct's pool, nrtonemap's
    # mapped output)
    lt_m, lt_c = tonemap.LocalTonemap(), tonemap.LocalTonemap()
    codes_m, codes_c = np.empty((h, w), np.uint8), np.empty((h, w, 3), np.uint8)
    rgb_out = np.empty((3, h, w), np.float32)

    def tone_mono(v):
        if operator == "local":
            return lt_m(v, mono.white, out=codes_m)
        return tonemap.log_tonemap(v, mono.white, out=codes_m)

    def tone_colour(rgb):
        if operator == "local":
            return lt_c.rgb(rgb, col.white, out=codes_c)
        return tonemap.tonemap_rgb(rgb, col.white, "log", out=codes_c)

    def mono_frame(raw, t):
        v, s = _timed(t, 0, validity.classify, raw, mono, dark_policy=sm.dark_policy)
        v, s = _timed(t, 1, crosstalk.correct, v, s, mono, sm.crosstalk, lut=sm.crosstalk_lut)
        _timed(t, 2, reconstruction.reconstruct_frame, v, s, method=sm.method, preset=sm.preset, noise=mono,
               fusion=sm.noise_fusion)
        _timed(t, 3, tone_mono, v)

    def colour_frame(raw, t, prof=col, correct=True, median=True, bounds=True):
        v, s = _timed(t, 0, validity.classify, raw, prof, dark_policy=sm.dark_policy)
        if correct:
            v, s = _timed(t, 1, crosstalk.correct, v, s, prof, sm.crosstalk, lut=sm.crosstalk_lut)
        filt = demosaic._chroma_filter
        if not median:                  # the median pass left out (a measurement only: no setting does this)
            demosaic._chroma_filter = lambda *args: None
        try:
            rgb = _timed(t, 2, demosaic.reconstruct_cfa, v, s, prof.cfa, method=sm.method, preset=sm.preset,
                         noise=prof, fusion=sm.noise_fusion, use_bounds=bounds, out=rgb_out)
        finally:
            demosaic._chroma_filter = filt
        _timed(t, 3, tone_colour, rgb)

    chains = {"mono": (mono_frame, raws_m), "colour": (colour_frame, raws_c)}
    if ceiling:
        white = base.replace(cfa=PATTERN, crosstalk=calib)
        crosstalk.compact_for(white)
        variants = {"colour-white-crosstalk": dict(prof=white),
                    "colour-white-crosstalk-no-median": dict(prof=white, median=False),
                    "colour-no-crosstalk-median-bounds": dict(correct=False, median=False, bounds=False)}
        for k, kw in variants.items():
            chains[k] = (lambda raw, t, kw=kw: colour_frame(raw, t, **kw), raws_c)
    best = {k: (float("inf"), None) for k in chains}
    for k, (f, raws) in chains.items():               # untimed: compiles, fills caches
        f(raws[0], [0.0] * len(SPEED_STAGES))
    for _ in range(repeat):
        for k, (f, raws) in chains.items():
            t = [0.0] * len(SPEED_STAGES)
            t0 = time.perf_counter()
            for r in raws:
                f(r, t)
            dt = time.perf_counter() - t0
            if dt < best[k][0]:
                best[k] = (dt, t)
    return {k: {"fps": frames / dt, "ms": {n: 1000 * x / frames for n, x in zip(SPEED_STAGES, t)}}
            for k, (dt, t) in best.items()}


# ---- report ------------------------------------------------------------------------------------------------

def _f(x, d=2):
    return "-" if x is None else f"{x:.{d}f}"


def quality_table(res_kind) -> str:
    lines = ["| camera | log2 PSNR of luminance, all / dark / mid / bright dB | mean CIEDE2000 |", "|---|---|---|"]
    for c in CAMERAS:
        r = res_kind[c]
        cells = " / ".join(_f(r["report"][k]["log2_psnr"]) for k in metrics.REGIONS)
        lines.append(f"| {LABELS[c]} | {cells} | {_f(r['de00'])} |")
    return "\n".join(lines)


def zone_table(res_m) -> str:
    cols = ("all",) + scene.ZONE_PLATE_PANELS
    lines = ["| camera | false colour dB: " + " / ".join(cols) + " |", "|---|---|"]
    for c in CAMERAS:
        lines.append(f"| {LABELS[c]} | " + " / ".join(_f(res_m[c][k]) for k in cols) + " |")
    return "\n".join(lines)


def speed_table(fps) -> str:
    lines = ["| chain | frames/s | " + " | ".join(f"{n} ms" for n in SPEED_STAGES) + " |",
             "|---" * (len(SPEED_STAGES) + 2) + "|"]
    labels = {"mono": "monochrome preview (anchor)", "colour": "colour preview", **CEILING}
    for k in fps:
        ms = " | ".join(f"{fps[k]['ms'][n]:.1f}" for n in SPEED_STAGES)
        ratio = "" if k == "mono" else f" ({100 * fps[k]['fps'] / fps['mono']['fps']:.0f} %)"
        lines.append(f"| {labels[k]} | {fps[k]['fps']:.1f}{ratio} | {ms} |")
    return "\n".join(lines)


def goals(q, z, fps) -> list[dict]:
    """The issue's goals per method and non-regular layout: measured value, threshold, met."""
    out = []
    for m in q:
        hdr, kodak = q[m].get("hdr"), q[m].get("kodak")
        for c in ("nr-independent", "nr-balanced"):
            if hdr:
                gain = hdr[c]["report"]["bright"]["log2_psnr"] - hdr["bayer"]["report"]["bright"]["log2_psnr"]
                out.append({"goal": f"{m}, {c}: bright log2 PSNR >= +12 dB over the unmodified Bayer camera",
                            "value": f"{gain:+.2f} dB", "met": gain >= GOALS["bright_gain_db"]})
            if m in z:
                less = z[m]["sve"]["all"] - z[m][c]["all"]
                out.append({"goal": f"{m}, {c}: false colour on the zone plate >= 3 dB below SVE",
                            "value": f"{less:+.2f} dB", "met": less >= GOALS["false_colour_db"]})
            for kind, r in (("HDR scenes", hdr), ("Kodak", kodak)):
                if r:
                    dp = r[c]["report"]["all"]["log2_psnr"] - r["sve"]["report"]["all"]["log2_psnr"]
                    dd = r[c]["de00"] - r["sve"]["de00"]
                    out.append({"goal": f"{m}, {c}: {kind} no worse than SVE (log2 PSNR all, CIEDE2000)",
                                "value": f"{dp:+.2f} dB, {dd:+.2f} dE00", "met": dp >= 0 and dd <= 0})
    if fps:
        fc, fm = fps["colour"]["fps"], fps["mono"]["fps"]
        out.append({"goal": "colour preview >= 70 % of the monochrome preview's frames/s",
                    "value": f"{100 * fc / fm:.0f} % ({fc:.1f} / {fm:.1f})",
                    "met": fc / fm >= GOALS["fps_ratio"]})
    return out


def size(text: str) -> tuple[int, int]:
    """WIDTHxHEIGHT (benchmarks/temporal.py's parser), both even: whole 2 x 2 Bayer blocks."""
    w, h = _sibling("temporal").size(text)
    if w % 2 or h % 2 or min(w, h) < 16:
        raise argparse.ArgumentTypeError(f"{text}: a Bayer frame has an even width and height, at least 16")
    return w, h


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--quick", action="store_true", help="smoke run: 96 x 64, 2 HDR scenes, 2 Kodak images, zone "
                                                         "plate 64, preview only, frames/s at 320 x 180")
    ap.add_argument("--size", type=size, default=None, help="views WIDTHxHEIGHT (default 384x256)")
    ap.add_argument("--scenes", nargs="*", default=None, help="HDR scene files (default: the shared ones)")
    ap.add_argument("--kodak", nargs="*", default=None, help="Kodak PNG files (default: kodim01-04 of the shared "
                                                             "data)")
    ap.add_argument("--methods", default=None, help="comma-separated: preview, fse, fse-best (default all; "
                                               "quick: preview)")
    ap.add_argument("--zone-size", type=int, default=None, help="zone plate panel side (default 256)")
    ap.add_argument("--operator", default="local", choices=tonemap.SDR_OPERATORS, help="tone map operator")
    ap.add_argument("--fps-size", type=size, default=None, help="frames/s at WIDTHxHEIGHT (default 1920x1080)")
    ap.add_argument("--fps-frames", type=int, default=None, help="frames per timed pass (default 4)")
    ap.add_argument("--repeat", type=int, default=3, help="timed passes per chain (best counts)")
    ap.add_argument("--no-fps", action="store_true", help="quality only")
    ap.add_argument("--ceiling", action="store_true", help="frames/s also of the colour chain without parts of its "
                                                           "model (the monochrome crosstalk kernel, no median, ...)")
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--out", default=str(OUT))
    a = ap.parse_args(argv)
    w, h = a.size or ((96, 64) if a.quick else (384, 256))
    zsize = a.zone_size or (64 if a.quick else 256)
    fw, fh = a.fps_size or ((320, 180) if a.quick else (1920, 1080))
    fframes = a.fps_frames or (2 if a.quick else 4)
    methods = (a.methods or ("preview" if a.quick else ",".join(METHODS))).split(",")
    bad = [m for m in methods if m not in METHODS]
    if bad or zsize < 8 or min(fframes, a.repeat) < 1:
        ap.error(f"--methods takes {', '.join(METHODS)} (got {a.methods!r}); --zone-size >= 8; --fps-frames and "
                 "--repeat >= 1")
    if a.scenes is None:
        paths = [str(p) for n in HDR_SCENES for p in [DATA / "hdr" / f"{n}.exr"] if p.is_file()]
        paths = paths[:2] if a.quick else paths
    else:
        paths = a.scenes
    if a.kodak is None:
        kodak = [str(p) for i in range(1, 5) for p in [DATA / "kodak" / f"kodim0{i}.png"] if p.is_file()]
        kodak = kodak[:2] if a.quick else kodak
    else:
        kodak = a.kodak
    missing = [p for p in paths + kodak if not Path(p).is_file()]
    if missing or not (paths or kodak):
        print(f"colour: file(s) not found: {', '.join(missing) or DATA} (set NRHDR_SHARED_DATA or pass --scenes/--kodak)",
              file=sys.stderr)
        return 2
    t_start = time.perf_counter()
    prof = profile.default(h, w, cfa=PATTERN)
    scenes = load_scenes(paths, kodak, prof)
    print(f"quality: {w} x {h}, {len(paths)} HDR scenes, {len(kodak)} Kodak images, methods {', '.join(methods)}",
          flush=True)
    q = quality(scenes, h, w, methods, a.seed, a.operator, log=lambda s: print(s, flush=True))
    print(f"zone plate: {zsize} x {3 * zsize}", flush=True)
    z = zone_plate(zsize, methods, a.seed)
    fps = None
    if not a.no_fps:
        print(f"frames/s: {fw} x {fh}, {fframes} frames per pass", flush=True)
        fps = speed((paths + kodak)[0], fh, fw, fframes, a.repeat, a.operator, a.seed, a.ceiling)
    g = goals(q, z, fps)
    text = (f"{w} x {h} views, CFA {PATTERN}, shot and read noise; tone map `{a.operator}`; HDR: "
             f"{', '.join(Path(p).stem for p in paths) or '-'}; Kodak: {', '.join(Path(p).stem for p in kodak) or '-'}\n")
    for m in methods:
        for kind, title in (("hdr", "HDR scenes"), ("kodak", "Kodak")):
            if kind in q[m]:
                text += f"\n**{title}, `{m}`**\n\n" + quality_table(q[m][kind]) + "\n"
        text += f"\n**Colour zone plate {zsize} x {3 * zsize}, noise-free, `{m}`**\n\n" + zone_table(z[m]) + "\n"
    if fps:
        text += (f"\n**Preview chain at {fw} x {fh}**, best of {a.repeat} passes of {fframes} frames, interleaved\n\n"
                 + speed_table(fps) + "\n")
    text += "\n| goal | measured | met |\n|---|---|---|\n" + "".join(
        f"| {x['goal']} | {x['value']} | {'yes' if x['met'] else 'no'} |\n" for x in g)
    total = time.perf_counter() - t_start
    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    info = {"quick": a.quick, "size": [w, h], "methods": methods, "hdr": [Path(p).stem for p in paths],
            "kodak": [Path(p).stem for p in kodak], "operator": a.operator, "zone_size": zsize, "seed": a.seed,
            "quality": q, "zone_plate": z, "fps_size": [fw, fh], "fps": fps, "goals": g,
            "seconds": total}
    (out / "results.json").write_text(json.dumps(info, indent=1, default=float) + "\n")
    (out / "results.md").write_text(text)
    print("\n" + text + f"\n({total:.0f} s)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
