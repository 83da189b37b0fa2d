"""`nrhdr warmup`: compile every numba kernel of the chain once, into numba's on-disk cache (next to the
sources, `nrhdr_core/__pycache__`), so that no pipeline compiles on its first frames (issue #7: the first
`make demo` used to run at 1 frame/s while numba compiled inside gst-launch, silently). Run by
scripts/setup.sh after install; elements that still compile report it (Gst INFO log + bus INFO message)."""
from __future__ import annotations

import sys
import time


def _stages():
    """(element, what, callable) for every stage of the chain, in pipeline order."""
    import numpy as np

    from nrhdr_core import crosstalk, reconstruction, tonemap, validity

    def fse_presets():
        from nrhdr_core import fse
        rng = np.random.default_rng(0)
        v = rng.random((32, 32)).astype(np.float32)
        k = rng.random((32, 32)) < 0.5
        nan = np.full_like(v, np.nan)
        for preset in fse.FSE_PRESETS:
            fse.fse_reconstruct(v.copy(), k, lower=nan, upper=nan, preset=preset)

    def other_methods():
        v = np.random.default_rng(1).random((16, 16)).astype(np.float32)
        k = np.ones((16, 16), bool)
        k[4:8, 4:8] = False
        for m in ("nearest", "linear"):
            reconstruction.reconstruct(v, k, method=m)

    def pipelines():
        """The elements on a tiny live-less stream: compiles the signatures the elements use at run time
        (mapped, possibly strided frames), not only the warm-up calls'."""
        import tempfile
        from pathlib import Path

        from nrhdr_core import profile
        from gst_plugins import runtime
        with tempfile.TemporaryDirectory(prefix="nrhdr-warmup-") as d:
            cam = Path(d) / "cam.json"
            profile.save(profile.default(48, 64, seed=1), cam)
            for m in ("preview", "fse preset=preview", "fse preset=fast", "fse preset=balanced",
                      "fse preset=best", "nearest", "linear"):
                rc = runtime.run_pipeline(
                    f"nrcamsrc scene=synthetic profile={cam} frames=2 is-live=false num-buffers=2 ! "
                    f"nrvalidity profile={cam} ! nrcrosstalk ! nrreconstruct method={m} ! tee name=t "
                    f"t. ! queue ! nrtonemap ! fakesink "
                    f"t. ! queue ! nrtonemap ! video/x-raw,format=GRAY16_LE ! fakesink")
                if rc >= 128:           # stopped by a signal (run_pipeline: 128 + n)
                    raise KeyboardInterrupt
                if rc != 0:
                    raise RuntimeError(f"warm-up pipeline with method={m} failed")
            # an odd width: GStreamer pads GRAY16 rows to 4 bytes, so frames arrive as strided views
            odd = Path(d) / "odd.json"
            profile.save(profile.default(47, 63, seed=1), odd)
            rc = runtime.run_pipeline(f"nrcamsrc scene=synthetic profile={odd} frames=2 is-live=false "
                                      f"num-buffers=2 ! nrvalidity profile={odd} ! nrreconstruct "
                                      f"method=preview ! nrtonemap ! fakesink")
            if rc >= 128:
                raise KeyboardInterrupt
            if rc != 0:
                raise RuntimeError("warm-up pipeline with an odd frame width failed")

    stages = [("nrvalidity", "validity.classify", validity.warmup),
            ("nrcrosstalk", "crosstalk lut + kernel", crosstalk.warmup),
            ("nrreconstruct", "pull-push preview", lambda: reconstruction.warmup("preview")),
            ("nrreconstruct", "fse, every preset", fse_presets),
            ("nrreconstruct", "nearest, linear", other_methods),
            ("nrtonemap", "log tone map", tonemap.warmup)]
    try:
        import gi
        gi.require_version("Gst", "1.0")
        stages.append(("pipelines", "every element on a tiny stream, every method", pipelines))
    except (ImportError, ValueError):  # no GStreamer: the core kernels are all there is
        pass
    return stages


def run_warmup(out=sys.stdout) -> tuple[int, float]:
    """Compile (or load from cache) every kernel; prints a line per stage; returns (compiled, seconds)."""
    from nrhdr_core.realtime import JitWatch
    stages = _stages()
    total_n, t_all = 0, time.perf_counter()
    for i, (element, what, fn) in enumerate(stages, 1):
        snap = JitWatch.snapshot()
        t0 = time.perf_counter()
        print(f"nrhdr warmup: [{i}/{len(stages)}] {element}: {what} ...", end="", file=out, flush=True)
        fn()
        n, _sec, _names = JitWatch.since(snap)
        total_n += n
        how = f"{n} function(s) compiled into the cache" if n else "cached"
        print(f" {time.perf_counter() - t0:.1f} s, {how}", file=out, flush=True)
    return total_n, time.perf_counter() - t_all


def cmd_warmup(a) -> int:
    n, sec = run_warmup()
    print(f"nrhdr warmup: done in {sec:.1f} s ({n} function(s) compiled; a second run compiles none)")
    if a.check and n:
        print("nrhdr warmup: --check: kernels were not in the cache", file=sys.stderr)
        return 1
    return 0


def add_warmup(sub) -> None:
    p = sub.add_parser("warmup", help="compile the numba kernels of the chain once (numba cache), so "
                                      "pipelines start at full speed")
    p.add_argument("--check", action="store_true",
                   help="exit 1 if any kernel had to be compiled (i.e. the cache was cold)")
    p.set_defaults(func=cmd_warmup)
