"""FSE before / after in one run: the FSE of a git revision (default ``main``) against the working tree's, on
the same inputs, interleaved call by call.

    PYTHONPATH=. .venv/bin/python benchmarks/fse_kernels.py                 # ~3 min on 2 shared cores
    PYTHONPATH=. .venv/bin/python benchmarks/fse_kernels.py --before HEAD~1 --repeat 7 --cases hdr1080

The "before" FSE is the ``nrhdr_core`` of that revision (``git archive``), imported from a temporary
directory as the package ``nrhdr_core_before``; its ``fse`` is a module or a package (both entry points
are called the way that revision defines them). Cases:
  kodak     kodim01 / kodim03 grayscale (768 x 512), 50 % known (uniform random), presets fast, balanced
  kodak_win kodim01, 50 % known, balanced with a 32 x 32 window
  sparse    kodim03, 20 % known, fast (its 32 x 32 window below 30 % known)
  hdr1080   one 1920 x 1080 HDR frame (MtTamWest through the sensor model, the scene's missing pixels and
            bounds), presets fast and preview: the nrreconstruct fse stage
  vga       640 x 480 of the same scene, 50 % missing, preset preview
  desk1080  the same for ../shared/data/hdr/Desk.exr (largely clipped: the slowest scene of the five)
  synth1080 one 1920 x 1080 frame of ``scene.synthetic_hdr_scene()`` (the scene of benchmarks/pipeline.py)
            through the sensor model, ``dark_policy="weighted"`` as nrvalidity's default, preset fast with
            the NOISY pixels skipped as nrreconstruct does before the accurate fusion
Per case: max |after - before| over the image, PSNR of both (Kodak, against the original; HDR: log2 PSNR of
the reconstructed pixels against the scene flux, NOISY ones excluded for synth1080), and the wall
time of each (median of ``--repeat`` interleaved calls after one untimed warm-up each; on a shared machine
only the ratio after / before of one run is meaningful). ``--cpu`` uses the process CPU clock.
"""
from __future__ import annotations

import argparse
import importlib
import importlib.util
import io
import os
import subprocess
import sys
import tarfile
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from nrhdr_core import fse as fse_after  # noqa: E402

DATA = Path(os.environ.get("NRHDR_SHARED_DATA", ROOT.parent / "shared" / "data"))


def load_before(rev):
    """The ``fse`` of ``nrhdr_core`` at git revision ``rev``, as ``nrhdr_core_before.fse``."""
    sha = subprocess.run(["git", "rev-parse", rev], cwd=ROOT, check=True, capture_output=True,
                         text=True).stdout.strip()
    d = Path(tempfile.gettempdir()) / f"nrhdr_fse_before_{os.getuid()}" / sha
    pkg = d / "nrhdr_core"
    if not (pkg / "__init__.py").exists():
        tar = subprocess.run(["git", "archive", sha, "nrhdr_core"], cwd=ROOT, check=True,
                             capture_output=True).stdout
        d.mkdir(parents=True, exist_ok=True)
        tarfile.open(fileobj=io.BytesIO(tar)).extractall(d)
    spec = importlib.util.spec_from_file_location("nrhdr_core_before", pkg / "__init__.py",
                                                  submodule_search_locations=[str(pkg)])
    mod = importlib.util.module_from_spec(spec)
    sys.modules["nrhdr_core_before"] = mod      # numba's cache finds the module of its kernels by name
    spec.loader.exec_module(mod)
    return importlib.import_module("nrhdr_core_before.fse")


def call(mod, v, k, lo, hi, preset, kw, extra):
    """``mod``'s FSE of one frame: ``fse_reconstruct`` with ``skip=``, or the ``_fse`` of revisions whose
    public entry point had no ``skip``."""
    if "skip" in extra and hasattr(mod, "_fse"):
        return mod._fse(v, k, lo, hi, preset, False, dict(kw), **extra)
    return mod.fse_reconstruct(v, k, lo, hi, preset, **extra, **kw)


def psnr(ref, test, peak=255.0):
    mse = np.mean((np.asarray(ref, np.float64) - np.asarray(test, np.float64)) ** 2)
    return float("inf") if mse == 0 else float(10 * np.log10(peak * peak / mse))


def logpsnr(ref, test):
    """PSNR of log2 values (floored at 1 DN) over the reference's log2 range (docs/FSE.md's log PSNR)."""
    a = np.log2(np.maximum(np.asarray(ref, np.float64), 1.0))
    b = np.log2(np.maximum(np.asarray(test, np.float64), 1.0))
    return psnr(a, b, float(a.max()))


def kodak(i):
    import cv2
    p = DATA / "kodak" / f"kodim0{i}.png"
    if not p.exists():
        raise SystemExit(f"missing benchmark data {p} (set NRHDR_SHARED_DATA)")
    return cv2.imread(str(p), cv2.IMREAD_GRAYSCALE).astype(np.float32)


def hdr_frame(h, w, missing=None):
    """(values, known, lower, upper) of one HDR frame as nrreconstruct gets it (benchmarks/stages.py)."""
    from benchmarks.stages import scene_flux
    from nrhdr_core import sensor, validity
    flux, prof, _ = scene_flux(h, w, str(DATA / "hdr" / "MtTamWest.exr"))
    raw = sensor.capture(flux, prof, np.random.default_rng(1))
    values, state = validity.classify(raw, prof)
    if missing is not None:
        miss = np.random.default_rng(3).random((h, w)) < missing
        return flux.astype(np.float32), ~miss, None, None
    lo, hi = validity.bounds(values, state)
    return values, validity.known_mask(state), lo, hi, flux


def synth_frame(h, w, scene_file=None):
    """(values, known, lower, upper, skip, flux) of the synthetic scene's frame (or of `scene_file`'s)
    as nrreconstruct gets it."""
    from nrhdr_core import io, profile, scene, sensor, simulate, validity
    prof = profile.default(h, w, seed=1)
    sc = scene.synthetic_hdr_scene() if scene_file is None else io.read_luminance(str(scene_file))
    flux = simulate.view(sc, h, w, 0.5, simulate.Motion()) * np.float32(simulate.exposure_scale(sc, prof, 0.0))
    raw = sensor.capture(flux, prof, np.random.default_rng(1))
    values, state = validity.classify(raw, prof, dark_policy="weighted")
    lo, hi = validity.bounds(values, state)
    known = validity.known_mask(state)
    skip = np.ascontiguousarray(validity.noisy_mask(state) & ~known)
    return values, known, lo, hi, skip, flux


def cases(which):
    out = []
    if "kodak" in which:
        for i in (1, 3):
            img = kodak(i)
            k = np.random.default_rng(i).random(img.shape) < 0.5
            for preset in ("fast", "balanced"):
                out.append((f"kodim0{i} 50% {preset}", img, k, None, None, preset, {}, img))
    if "kodak_win" in which:
        img = kodak(1)
        k = np.random.default_rng(1).random(img.shape) < 0.5
        out.append(("kodim01 50% balanced window=32", img, k, None, None, "balanced", {"window": 32}, img))
    if "sparse" in which:
        img = kodak(3)
        k = np.random.default_rng(7).random(img.shape) < 0.2
        out.append(("kodim03 20% fast (32 x 32 window)", img, k, None, None, "fast", {}, img))
    if "hdr1080" in which:
        v, k, lo, hi, flux = hdr_frame(1080, 1920)
        miss = 1.0 - float(np.mean(k))
        for preset in ("fast", "preview"):
            out.append((f"1920x1080 HDR ({miss:.0%} missing) {preset}", v, k, lo, hi, preset, {},
                        ("log", flux, ~k)))
    if "synth1080" in which:
        v, k, lo, hi, sk, flux = synth_frame(1080, 1920)
        miss, nz = 1.0 - float(np.mean(k)), float(np.mean(sk))
        out.append((f"1920x1080 synthetic ({miss:.0%} missing, {nz:.0%} NOISY skipped) fast", v, k, lo, hi,
                    "fast", {"skip": sk}, ("log", flux, ~(k | sk))))
    if "desk1080" in which:
        v, k, lo, hi, sk, flux = synth_frame(1080, 1920, DATA / "hdr" / "Desk.exr")
        miss, nz = 1.0 - float(np.mean(k)), float(np.mean(sk))
        out.append((f"1920x1080 Desk ({miss:.0%} missing, {nz:.0%} NOISY skipped) fast", v, k, lo, hi,
                    "fast", {"skip": sk}, ("log", flux, ~(k | sk))))
    if "vga" in which:
        v, k, lo, hi = hdr_frame(480, 640, missing=0.5)[:4]
        out.append(("640x480 50% missing preview", v, k, lo, hi, "preview", {}, v))
    return out


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--before", default="main", help="git revision of the 'before' FSE")
    ap.add_argument("--repeat", type=int, default=5)
    ap.add_argument("--cases", default="kodak,kodak_win,sparse,hdr1080,synth1080,desk1080,vga")
    ap.add_argument("--cpu", action="store_true", help="process CPU clock instead of wall time")
    a = ap.parse_args(argv)
    clock = time.process_time if a.cpu else time.perf_counter
    before = load_before(a.before)
    mods = {"before": before, "after": fse_after}
    print(f"FSE {a.before} (before) vs working tree (after); {a.repeat} interleaved calls, median "
          f"{'CPU' if a.cpu else 'wall'} ms; load {os.getloadavg()[0]:.1f}", flush=True)
    print("| case | max abs diff | PSNR before | PSNR after | ms before | ms after | after / before |")
    print("|---|---|---|---|---|---|---|")
    for name, v, k, lo, hi, preset, kw, truth in cases(set(a.cases.split(","))):
        res = {}
        ts = {m: [] for m in mods}
        kw = dict(kw)
        extra = {"skip": kw.pop("skip")} if "skip" in kw else {}
        for m, mod in mods.items():   # warm-up (compilation) and the outputs
            res[m] = call(mod, v, k, lo, hi, preset, kw, extra)
        for _ in range(a.repeat):
            for m, mod in mods.items():
                t = clock()
                call(mod, v, k, lo, hi, preset, kw, extra)
                ts[m].append(clock() - t)
        tb, ta = (1e3 * float(np.median(ts[m])) for m in ("before", "after"))
        d = float(np.max(np.abs(res["after"].astype(np.float64) - res["before"])))
        pb = pa = "-"
        if isinstance(truth, tuple):   # HDR: log2 PSNR of the reconstructed pixels against the scene flux
            _, flux, m = truth
            pb, pa = (f"{logpsnr(flux[m], res[x][m]):.3f} (log)" for x in ("before", "after"))
        elif truth is not None:
            pk = 255.0 if truth.max() <= 255 else float(truth.max())
            pb, pa = f"{psnr(truth, res['before'], pk):.3f}", f"{psnr(truth, res['after'], pk):.3f}"
        print(f"| {name} | {d:.3g} | {pb} | {pa} | {tb:.1f} | {ta:.1f} | {ta / tb:.3f} |", flush=True)


if __name__ == "__main__":
    main()
