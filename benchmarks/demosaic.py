"""Joint colour reconstruction (`demosaic.reconstruct_cfa`): speed against the monochrome preview, quality on
Kodak images (docs/COLOUR.md "Joint reconstruction").

    PYTHONPATH=. .venv/bin/python benchmarks/demosaic.py --speed [--fse fast] # 1920 x 1080, ms per frame
    PYTHONPATH=. .venv/bin/python benchmarks/demosaic.py --quality            # Kodak, PSNR dB

--speed: one 1920 x 1080 frame of an HDR scene (../shared/data/hdr/MtTamWest.exr, else the synthetic scene)
captured by the sensor model and classified (dark policy weighted, noise fused with the profile) is read as
an RGGB mosaic; `reconstruct_cfa(method="preview")` and the monochrome `reconstruction.reconstruct_frame(
method="preview")` run on it in the same process, interleaved call by call (median wall ms of --repeat warm
calls, and the least process CPU time of one call: on a loaded machine the CPU times and their ratio vary less
than the wall times; each call gets a fresh copy of the frame, untimed); --fse: the same for method "fse" with
each preset, one warm call each.
--quality: Kodak images mosaicked (RGGB), a share --missing of the photosites DISCARDED at random; PSNR (dB,
8-bit peak) of a plain bilinear per-channel demosaic of the known photosites (normalised convolution),
the preview and FSE (--presets).
"""
from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from nrhdr_core import cfa, demosaic, reconstruction  # noqa: E402
from nrhdr_core.states import DISCARDED, VALID  # noqa: E402

DATA = Path(os.environ.get("NRHDR_SHARED_DATA", ROOT.parent / "shared" / "data"))


def hdr_frame(h, w, scene_path):
    """(values, state, profile): one frame of the scene captured and classified as nrvalidity does."""
    from nrhdr_core import profile as profiles, sensor, simulate, validity
    from nrhdr_core.simulate import Motion
    if Path(scene_path).is_file():
        from nrhdr_core import io
        scene = io.read_luminance(scene_path)
    else:
        from nrhdr_core.scene import synthetic_hdr_scene
        scene = synthetic_hdr_scene(max(h, 600), max(w, 800))
    prof = profiles.default(h, w)
    k = simulate.exposure_scale(scene, prof, 0.0)
    flux = simulate.view(scene, h, w, 0.3, Motion()) * np.float32(k)
    raw = sensor.capture(flux, prof, np.random.default_rng(1))
    values, state = validity.classify(raw, prof, dark_policy="weighted")
    return values, state, prof


def speed(a):
    values, state, prof = hdr_frame(a.height, a.width, a.scene)
    h, w = values.shape
    out = np.empty((3, h, w), np.float32)
    vm, sm = values.copy(), state.copy()
    sc = state.copy()
    mono = lambda: reconstruction.reconstruct_frame(vm, sm, method="preview", noise=prof)  # noqa: E731
    colour = lambda: demosaic.reconstruct_cfa(values, sc, "rggb", method="preview", noise=prof, out=out)  # noqa: E731

    def reset():
        np.copyto(vm, values)
        np.copyto(sm, state)
        np.copyto(sc, state)
    ts = {"mono": [], "colour": []}
    cpu = {"mono": [], "colour": []}
    for i in range(a.repeat + 1):
        for name, fn in (("mono", mono), ("colour", colour)):
            reset()
            t0 = time.perf_counter()
            c0 = time.process_time()
            fn()
            if i:
                cpu[name].append(time.process_time() - c0)
                ts[name].append(time.perf_counter() - t0)
    from numba import get_num_threads
    known = float(np.mean(state == VALID))
    mm, mc = (1e3 * float(np.median(ts[k])) for k in ("mono", "colour"))
    cm, cc = (1e3 * float(np.min(cpu[k])) for k in ("mono", "colour"))
    print(f"{w}x{h} {Path(a.scene).name if Path(a.scene).is_file() else 'synthetic'}, {known:.1%} known, "
          f"numba threads {get_num_threads()}, load {os.getloadavg()[0]:.1f}, median of {a.repeat}")
    print(f"  mono preview   (reconstruct_frame)  {mm:8.2f} ms  {1e3 / mm:6.1f} frames/s  CPU {cm:7.2f} ms")
    print(f"  colour preview (reconstruct_cfa)    {mc:8.2f} ms  {1e3 / mc:6.1f} frames/s  CPU {cc:7.2f} ms  "
          f"{mm / mc:.0%} of the mono frame rate; time ratio colour / mono {mc / mm:.2f}, CPU {cc / cm:.2f}")
    for preset in [p for p in a.fse.split(",") if p]:
        t = {}
        for name, fn in (("mono", lambda: reconstruction.reconstruct_frame(vm, sm, method="fse", preset=preset,
                                                                           noise=prof)),
                         ("colour", lambda: demosaic.reconstruct_cfa(values, sc, "rggb", method="fse", preset=preset,
                                                                     noise=prof, out=out))):
            reset()
            fn()
            reset()
            t0 = time.perf_counter()
            fn()
            t[name] = 1e3 * (time.perf_counter() - t0)
        print(f"  fse {preset}: mono {t['mono']:8.1f} ms, colour {t['colour']:8.1f} ms (one warm call each)")


def bilinear(mosaic, known, pattern):
    """Plain bilinear demosaic per channel: each channel the normalised convolution of its known
    photosites with the 3 x 3 tent [1 2 1] x [1 2 1] / 16 (5 x 5 where the 3 x 3 holds none, then the
    channel's mean)."""
    from scipy.ndimage import convolve
    h, w = mosaic.shape
    masks = cfa.channel_masks(pattern, h, w)
    t3 = np.outer([1, 2, 1], [1, 2, 1]).astype(np.float64)
    t5 = np.outer([1, 2, 3, 2, 1], [1, 2, 3, 2, 1]).astype(np.float64)
    out = np.empty((3, h, w), np.float32)
    for c in range(3):
        k = masks[c] & known
        v = np.where(k, mosaic, 0.0)
        num = convolve(v, t3, mode="mirror")
        den = convolve(k.astype(np.float64), t3, mode="mirror")
        num5 = convolve(v, t5, mode="mirror")
        den5 = convolve(k.astype(np.float64), t5, mode="mirror")
        mean = v.sum() / max(k.sum(), 1)
        est = np.where(den > 0, num / np.maximum(den, 1e-12),
                       np.where(den5 > 0, num5 / np.maximum(den5, 1e-12), mean))
        out[c] = np.where(k, mosaic, est)
    return out


def psnr(a, b, peak=255.0):
    return 10 * np.log10(peak ** 2 / np.mean((a.astype(np.float64) - b) ** 2))


def quality(a):
    from nrhdr_core import io
    presets = [p for p in a.presets.split(",") if p]
    print(f"Kodak, rggb, {a.missing:.0%} of the photosites missing at random: PSNR dB (time s)")
    print("| image | bilinear | preview | " + " | ".join(f"fse {p}" for p in presets) + " |")
    print("|---" * (3 + len(presets)) + "|")
    for name in a.images.split(","):
        path = DATA / "kodak" / f"{name}.png"
        rgb = np.ascontiguousarray(np.moveaxis(io.read_image(path, np.uint8)[:, :, :3], 2, 0), np.float32)
        h, w = rgb.shape[1:]
        m = cfa.mosaic(rgb, "rggb")
        st = np.where(np.random.default_rng(0).random((h, w)) < a.missing, DISCARDED, VALID).astype(np.uint8)
        row = [f"{psnr(bilinear(m, st == VALID, 'rggb'), rgb):.2f}"]
        for method, preset in [("preview", "fast")] + [("fse", p) for p in presets]:
            t0 = time.perf_counter()
            out = demosaic.reconstruct_cfa(m, st.copy(), "rggb", method=method, preset=preset)
            row.append(f"{psnr(out, rgb):.2f} ({time.perf_counter() - t0:.2f})")
        print(f"| {name} | " + " | ".join(row) + " |", flush=True)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--speed", action="store_true")
    ap.add_argument("--quality", action="store_true")
    ap.add_argument("--width", type=int, default=1920)
    ap.add_argument("--height", type=int, default=1080)
    ap.add_argument("--scene", default=str(DATA / "hdr" / "MtTamWest.exr"))
    ap.add_argument("--repeat", type=int, default=9)
    ap.add_argument("--images", default="kodim01,kodim03,kodim05,kodim08")
    ap.add_argument("--missing", type=float, default=0.4)
    ap.add_argument("--presets", default="fast,balanced", help="FSE presets of --quality")
    ap.add_argument("--fse", default="", help="FSE presets to time once each with --speed (e.g. fast)")
    a = ap.parse_args(argv)
    if not (a.speed or a.quality):
        ap.error("give --speed and/or --quality")
    if a.speed:
        speed(a)
    if a.quality:
        quality(a)


if __name__ == "__main__":
    main()
