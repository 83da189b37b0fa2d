"""Per-stage cost of the chain, in-process, at camera resolution (docs/BENCHMARKS.md).

    PYTHONPATH=. .venv/bin/python benchmarks/stages.py --width 1920 --height 1080
    PYTHONPATH=. .venv/bin/python benchmarks/stages.py --width 640 --height 480 --missing 0.5
    PYTHONPATH=. .venv/bin/python benchmarks/stages.py --only validity,crosstalk --threads 1 --cpu --min

One frame of an HDR scene (../shared/data/hdr/MtTamWest.exr, or a synthetic scene when absent) is captured
by the sensor model at the requested size and pushed through the stages the elements run:
classify (nrvalidity; the default mode with both dark policies, and mode best), crosstalk `lut` (full and
compact table) and `kernel` with a calibration of `--knots` knots per pixel (nrcrosstalk),
known mask + bounds (nrreconstruct's preparation), each reconstruction method, write-back of the filled
pixels, tone mapping (nrtonemap). `--missing p` replaces the scene's missing pixels by a uniform random
mask with share p (no bounds) for the reconstruction stages.

Each figure is the median ms per frame of `--repeat` warm calls (JIT excluded). Anchors measured in the
same run: `copy` = one float32 frame np.copyto (the cost of touching a frame once), and the machine's
copy bandwidth in GB/s (a 256 MB np.copyto). On a shared machine the ratios to the anchors are the
figures to compare; `--json` writes all figures. On a busy machine, `--threads 1 --cpu --min` gives the
single-core CPU cost of every stage (process CPU clock), which other jobs disturb far less than wall time
of a 2-thread run (a parallel region waits for its slowest thread).
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from nrhdr_core import crosstalk, profile as profiles, reconstruction, sensor, tonemap, validity  # noqa: E402

DATA = Path(os.environ.get("NRHDR_SHARED_DATA", ROOT.parent / "shared" / "data"))


STAT = np.median
CLOCK = time.perf_counter


def timeit(fn, repeat, setup=None):
    """Median (or with --min, the fastest) wall ms of `repeat` calls after one warm-up call; `setup`
    runs untimed before each call."""
    if setup is not None:
        setup()
    fn()
    ts = []
    for _ in range(repeat):
        if setup is not None:
            setup()
        t0 = CLOCK()
        fn()
        ts.append(CLOCK() - t0)
    return 1e3 * float(STAT(ts))


def scene_flux(h, w, scene_path):
    from nrhdr_core import simulate
    from nrhdr_core.simulate import Motion
    if scene_path and Path(scene_path).is_file():
        if str(scene_path).endswith(".npy"):   # a luminance array (machines without OpenImageIO)
            scene = np.load(scene_path).astype(np.float32)
        else:
            from nrhdr_core import io
            scene = io.read_luminance(scene_path)
        name = Path(scene_path).name
    else:
        from nrhdr_core.scene import synthetic_hdr_scene
        scene = synthetic_hdr_scene(max(h, 600), max(w, 800))
        name = "synthetic"
    prof = profiles.default(h, w)
    k = simulate.exposure_scale(scene, prof, 0.0)
    return simulate.view(scene, h, w, 0.3, Motion()) * np.float32(k), prof, name


def prototype_spill(top: float):
    """(sig_e, sigma) of a spill table shaped like the `prototype` sensor model's (crosstalk.sensor_model_preset):
    coupling 1 % to left/right, 1.2 % to up/down, 0.3 % to diagonal neighbours, linear in the source's
    signal, and blooming of sources beyond `top` (the regular clip, DN) mostly along columns; rank 2, as
    `crosstalk.spill_basis` takes it. For timing the colour correction with a spill that is not zero."""
    kern = crosstalk.make_kernel(0.010, 0.012, 0.003)
    k_d = np.array([kern[1 + dy, 1 + dx] for dy, dx in crosstalk.DIRS])
    shape = np.array([0.0 if dx else 1.0 if dy else 0.3 for dy, dx in crosstalk.DIRS])
    e = float(top) * np.array([0.0, 0.125, 0.5, 2.0, 7.5])
    bloom = np.array([0.0, 0.0, 0.0, 0.004, 0.01]) * e
    sigma = k_d[:, None] * e[None] + shape[:, None] * bloom[None]
    return e.astype(np.float32), np.ascontiguousarray(sigma, np.float32)


def synthetic_calibration(prof, knots: int, seed: int = 0):
    """A calibration with `knots` knots per pixel (like calibration.py's flat sweeps): per-pixel gains of
    +-3 %, knots spread geometrically up to the pixel's clipping point. For timing the LUT path only."""
    rng = np.random.default_rng(seed)
    h, w = prof.mask.shape
    top = float(prof.clip_code) - float(prof.black_level)
    flux = np.concatenate([[0.0], top * prof.nd * np.geomspace(1e-3, 1.0, knots - 1)])
    s = np.where(prof.mask, prof.nd, 1.0)[:, :, None]
    gain = (1.0 + 0.03 * rng.standard_normal((h, w)))[:, :, None]
    codes = (flux[None, None, :] / s * gain).astype(np.float32)
    n = np.sum(codes < top, axis=2).astype(np.int32)
    n = np.maximum(n, 2)
    q, qs, qo = crosstalk.quantize_codes(codes, int(prof.clip_code) + 1)
    return crosstalk.CrosstalkCalibration(
        codes_q=np.ascontiguousarray(q), qscale=qs, qoffset=qo, n_knots=n, knot_flux=flux.astype(np.float64),
        clip_flux=np.full((h, w), np.nan, np.float32), nd=float(prof.nd), black_level=float(prof.black_level),
        clip_code=int(prof.clip_code), sig_e=np.array([0.0, 1.0], np.float32), sigma=np.zeros((8, 2), np.float32),
        alpha=np.ones((h, w), np.float32), info={"synthetic": True})


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--width", type=int, default=1920)
    ap.add_argument("--height", type=int, default=1080)
    ap.add_argument("--missing", type=float, default=None,
                    help="uniform random missing share for the reconstruction stages (default: the scene's)")
    ap.add_argument("--scene", default=str(DATA / "hdr" / "MtTamWest.exr"))
    ap.add_argument("--knots", type=int, default=40)
    ap.add_argument("--dark-policy", default="weighted", choices=validity.DARK_POLICIES,
                    help="nrvalidity's dark policy for the frame stages (default weighted, the elements' "
                         "default: NOISY pixels fused with the profile's noise)")
    ap.add_argument("--only", default="", help="comma-separated stage groups to run: validity, crosstalk (the "
                                               "frame stages up to the crosstalk correction); default: all")
    ap.add_argument("--repeat", type=int, default=5)
    ap.add_argument("--fse-repeat", type=int, default=3)
    ap.add_argument("--skip", default="", help="comma-separated stage names to skip (e.g. nearest,fse_fast)")
    ap.add_argument("--json", default=None, help="write the figures to this file")
    ap.add_argument("--threads", type=int, default=None, help="numba threads (default: numba's default)")
    ap.add_argument("--cpu", action="store_true",
                    help="time with the process CPU clock instead of the wall clock: with --threads 1 the "
                         "single-core cost, robust against other jobs on a shared machine")
    ap.add_argument("--min", action="store_true",
                    help="report the fastest call instead of the median (a loaded shared machine)")
    a = ap.parse_args(argv)
    global STAT, CLOCK
    STAT = np.min if a.min else np.median
    if a.cpu:
        CLOCK = time.process_time
    if a.threads:
        from numba import set_num_threads
        set_num_threads(a.threads)
    skip = {s.strip() for s in a.skip.split(",") if s.strip()}
    only = {s.strip() for s in a.only.split(",") if s.strip()}
    if only - {"validity", "crosstalk"}:
        ap.error(f"--only takes validity and crosstalk, got {a.only!r}")
    h, w = a.height, a.width
    from numba import get_num_threads
    flux, prof, scene_name = scene_flux(h, w, a.scene)
    rng = np.random.default_rng(1)
    raw = sensor.capture(flux, prof, rng)
    prof_x = prof.replace(crosstalk=synthetic_calibration(prof, a.knots))
    res = {"width": w, "height": h, "scene": scene_name, "threads": int(get_num_threads()),
           "cpus": os.cpu_count(), "knots": a.knots, "statistic": "min" if a.min else "median",
           "clock": "process CPU" if a.cpu else "wall", "ms": {},
           "load_avg_1min": os.getloadavg()[0]}
    ms = res["ms"]

    def rec(name, t):
        ms[name] = round(t, 3)
        print(f"  {name:<28s} {t:9.2f} ms   {t / ms['copy']:7.1f} x copy", flush=True)

    # ---- anchors -----------------------------------------------------------------------------------
    src = np.random.default_rng(2).random((h, w), dtype=np.float32)
    dst = np.empty_like(src)
    ms["copy"] = round(timeit(lambda: np.copyto(dst, src), max(a.repeat, 11)), 3)
    big = np.ones(64 * 1024 * 1024, np.float32)
    bigd = np.empty_like(big)
    t_big = timeit(lambda: np.copyto(bigd, big), 3)
    res["copy_gbps"] = round(2 * big.nbytes / (t_big * 1e-3) / 1e9, 2)   # read + write
    big = bigd = None   # free 512 MB
    print(f"{w}x{h} scene={scene_name} numba threads={res['threads']} cpus={res['cpus']} "
          f"statistic={res['statistic']} clock={res['clock']} load={res['load_avg_1min']:.1f}")
    print(f"  {'copy (anchor)':<28s} {ms['copy']:9.2f} ms   copy bandwidth {res['copy_gbps']} GB/s")

    # ---- validity -----------------------------------------------------------------------------------
    values = np.empty((h, w), np.float32)
    state = np.empty((h, w), np.uint8)
    rec("classify", timeit(lambda: validity.classify(raw, prof, values=values, state=state), a.repeat))
    if not only or "validity" in only:
        rec("classify weighted", timeit(lambda: validity.classify(raw, prof, values=values, state=state,
                                                                  dark_policy="weighted"), a.repeat))
        rec("classify best", timeit(lambda: validity.classify(raw, prof, mode="best", values=values, state=state),
                                    a.repeat))
        validity.classify(raw, prof, values=values, state=state)
    v0, s0 = values.copy(), state.copy()

    # ---- crosstalk lut --------------------------------------------------------------------------------
    vx, sx = v0.copy(), s0.copy()

    def reset_x():
        np.copyto(vx, v0)
        np.copyto(sx, s0)
    if not only or "crosstalk" in only:
        rec("crosstalk_lut", timeit(lambda: crosstalk.correct(vx, sx, prof_x, mode="lut"), a.repeat, reset_x))
        # ---- crosstalk kernel mode (neighbour spill model; the synthetic calibration's spill table is 0) --
        rec("crosstalk_kernel", timeit(lambda: crosstalk.correct(vx, sx, prof_x, mode="kernel"), a.repeat,
                                       reset_x))
        # ---- crosstalk lut, compact form (nrcrosstalk lut=compact, its default) ----------------------------
        t0 = CLOCK()
        crosstalk.compact_for(prof_x)                     # derived once, when the element starts
        res["compact_derive_s"] = round(CLOCK() - t0, 2)
        print(f"  {'(compact LUT derivation)':<28s} {res['compact_derive_s']:9.2f} s", flush=True)
        rec("crosstalk_lut_compact", timeit(lambda: crosstalk.correct(vx, sx, prof_x, mode="lut", lut="compact"),
                                            a.repeat, reset_x))
    if only:
        if a.json:
            Path(a.json).write_text(json.dumps(res, indent=2) + "\n")
        return res

    # ---- reconstruction inputs -------------------------------------------------------------------------
    if a.missing is not None:
        miss = np.random.default_rng(3).random((h, w)) < a.missing
        v1 = flux.astype(np.float32)
        s1 = np.where(miss, np.uint8(validity.DISCARDED), np.uint8(validity.VALID)).astype(np.uint8)
    else:
        v1, s1 = v0, s0
    res["missing_share"] = round(float(np.mean(validity.missing_mask(s1))), 4)
    print(f"  (missing share for the reconstruction stages: {res['missing_share']:.3f})")

    def prep_numpy():
        m = validity.missing_mask(s1)
        int(np.count_nonzero(m))
        k = validity.known_mask(s1)
        lo, hi = validity.bounds(v1, s1)
        return k, lo, hi
    rec("prep_numpy (mask+bounds)", timeit(prep_numpy, a.repeat))
    if hasattr(validity, "prepare"):
        kb = np.empty((h, w), bool)
        lob = np.empty((h, w), np.float32)
        hib = np.empty((h, w), np.float32)
        rec("prep_fused (prepare)",
            timeit(lambda: validity.prepare(v1, s1, known=kb, lower=lob, upper=hib), a.repeat))
    known, lower, upper = prep_numpy()

    methods = [("preview", "preview", None), ("nearest", "nearest", None),
               ("fse_preview", "fse", "preview"), ("fse_fast", "fse", "fast")]
    outs = {}
    for name, method, preset in methods:
        if name in skip:
            continue
        kw = {} if preset is None else {"preset": preset}
        rep = a.repeat if method != "fse" else a.fse_repeat
        fn = (lambda m=method, kw=kw: outs.__setitem__(
            m + str(kw), reconstruction.reconstruct(v1, known, method=m, lower=lower, upper=upper, **kw)))
        rec(name, timeit(fn, rep))

    # ---- write-back (the element: filled pixels into the frame, RECONSTRUCTED bit) -----------------------
    out = reconstruction.reconstruct(v1, known, method="preview", lower=lower, upper=upper)
    vw, sw = v1.copy(), s1.copy()

    def writeback():
        m = validity.missing_mask(sw)
        np.copyto(vw, out, where=m)
        np.bitwise_or(sw, np.uint8(validity.RECONSTRUCTED), out=sw, where=m)
    rec("writeback_numpy", timeit(writeback, a.repeat, lambda: np.copyto(sw, s1)))
    if hasattr(validity, "write_back"):
        rec("writeback_fused", timeit(lambda: validity.write_back(vw, sw, out), a.repeat,
                                      lambda: np.copyto(sw, s1)))
    if hasattr(reconstruction, "reconstruct_frame"):
        # the element's whole frame path (prepare + in-place preview + write-back)
        def frame_setup():
            np.copyto(vw, v1)
            np.copyto(sw, s1)
        for name, method, preset in methods:
            if name in skip or method == "fse" and name != "fse_fast":
                continue
            kw = {} if preset is None else {"preset": preset}
            rec(f"frame_{name}", timeit(lambda m=method, kw=kw: reconstruction.reconstruct_frame(vw, sw, method=m, **kw),
                                        a.repeat if method != "fse" else a.fse_repeat, frame_setup))
        # nrreconstruct's frame exactly as the element runs it: states from nrvalidity's default
        # dark policy, NOISY pixels fused with the profile's noise; the fused preview path against the
        # general path (prepare, reconstruct, write-back), same bits, same run
        if a.missing is None:
            vn, sn = validity.classify(raw, prof, dark_policy=a.dark_policy)
        else:
            vn, sn = v1, s1
        res["noisy_share"] = round(float(np.mean(validity.noisy_mask(sn))), 4)
        print(f"  (dark policy {a.dark_policy}: missing share {np.mean(validity.missing_mask(sn)):.3f}, "
              f"NOISY share {res['noisy_share']:.3f})")

        def frame_setup_n():
            np.copyto(vw, vn)
            np.copyto(sw, sn)
        rec("element_preview (fused)", timeit(
            lambda: reconstruction.reconstruct_frame(vw, sw, method="preview", noise=prof), a.repeat, frame_setup_n))
        rec("element_preview (general)", timeit(
            lambda: reconstruction._reconstruct_frame_general(vw, sw, "preview", "balanced", True, prof),
            a.repeat, frame_setup_n))
        if hasattr(reconstruction, "_preview_frame"):
            rec("element_preview no fusion", timeit(
                lambda: reconstruction.reconstruct_frame(vw, sw, method="preview"), a.repeat, frame_setup_n))
            nz = validity.noisy_mask(sn)
            kn = validity.known_mask(sn)
            g = vn.copy()
            if nz.any():
                rec("  of which fuse_noisy", timeit(
                    lambda: reconstruction.fuse_noisy(g, vn, kn, nz, prof), a.repeat))
            vv0, ss0 = vn.copy(), np.zeros_like(sn)
            rec("element_preview none missing", timeit(
                lambda: reconstruction.reconstruct_frame(vv0, ss0, method="preview", noise=prof), a.repeat))

    # ---- tone mapping --------------------------------------------------------------------------------
    img8 = np.empty((h, w), np.uint8)
    rec("tonemap", timeit(lambda: tonemap.log_tonemap(out, prof.white, out=img8), a.repeat))

    chain = ["classify", "crosstalk_lut", "prep_numpy (mask+bounds)", "preview", "writeback_numpy", "tonemap"]
    if "frame_preview" in ms:
        chain = ["classify", "crosstalk_lut", "frame_preview", "tonemap"]
    if "element_preview (fused)" in ms:
        chain = ["classify", "crosstalk_lut", "element_preview (fused)", "tonemap"]
    if all(c in ms for c in chain):
        tot = sum(ms[c] for c in chain)
        res["chain_preview_ms"] = round(tot, 2)
        print(f"  chain with preview ({' + '.join(chain)}): {tot:.1f} ms = {1e3 / tot:.1f} frames/s")
    if "crosstalk_lut_compact" in ms and all(c in ms for c in chain):   # nrcrosstalk's default form
        tot = sum(ms["crosstalk_lut_compact" if c == "crosstalk_lut" else c] for c in chain)
        res["chain_preview_compact_ms"] = round(tot, 2)
        print(f"  chain with preview and the compact LUT: {tot:.1f} ms = {1e3 / tot:.1f} frames/s")
    if a.json:
        Path(a.json).write_text(json.dumps(res, indent=2) + "\n")
    return res


if __name__ == "__main__":
    main()
