"""`nrhdr warmup`: compile every numba kernel of the chain once, into numba's on-disk cache (next to the
sources, `nrhdr_core/__pycache__`), so that no pipeline compiles on its first frames. Every stage line is one
call of `nrhdr_core.chain.warmup`, the one warm-up entry point, with every setting the element offers and the
array types of its mapped buffers (`elements=True`); no element runs here, so none reports a compilation.
With `--cfa` (a Bayer phase) the colour chain's kernels too: the stages on a mosaic of that phase
(`chain.warmup(cfa=)`: demosaic.reconstruct_cfa) and nrtonemap's colour outputs (`tonemap.warmup_rgb`,
`hdr_output.warmup_rgb`). Run by scripts/setup.sh after install; elements that still compile report it (Gst
INFO log + bus INFO message)."""
from __future__ import annotations

import dataclasses
import itertools
import sys
import time


def _stages(cfa: str = "none"):
    """(element, what, callable) for every stage of the chain, in pipeline order; with a Bayer `cfa` the
    colour chain's stages follow (a mosaic of that phase in, camera RGB out)."""
    from nrhdr_core import cfa as cfas
    from nrhdr_core import chain, hdr_output, tonemap
    S = chain.ChainSettings

    def warm(stages, settings, **kw):
        return lambda: chain.warmup(settings, stages=stages, elements=True, **kw)

    def recon(methods, presets):
        # every noise fusion and bounds setting, with and without NOISY pixels (the two dark policies)
        return [S(method=m, preset=p, use_bounds=b, noise_fusion=f, dark_policy=d)
                for m, p, b, f, d in itertools.product(methods, presets, (True, False), chain.NOISE_FUSIONS,
                                                       chain.DARK_POLICIES)]

    validity = [S(mode=m, dark_policy=d) for m, d in itertools.product(chain.VALIDITY_MODES, chain.DARK_POLICIES)]
    crosstalk = [S(crosstalk=x, crosstalk_lut=lut) for x, lut in itertools.product(chain.CROSSTALK_MODES,
                                                                                   chain.LUT_FORMS)]
    stages = [
        ("nrvalidity", "every mode and dark policy", warm(("validity",), validity)),
        ("nrcrosstalk", "every mode and LUT form", warm(("crosstalk",), crosstalk)),
        ("nrreconstruct", "pull-push preview", warm(("reconstruction",), recon(("preview",), ("fast",)))),
        ("nrreconstruct", "fse, every preset", warm(("reconstruction",), recon(("fse",), chain.PRESETS))),
        ("nrreconstruct", "nearest, linear", warm(("reconstruction",), recon(("nearest", "linear"), ("fast",)))),
        ("nrreconstruct", "temporal on, every method, bounded and unbounded budget",
         warm(("reconstruction",), [dataclasses.replace(s, temporal="on", temporal_budget=b)
                                    for s in recon(chain.METHODS, ("fast",))
                                    for b in (chain.TEMPORAL_BUDGET, 0)])),
        ("nrtonemap", "log tone map", warm(("tonemap",), S(), transfers=("log",))),
        ("nrtonemap", "HDR output " + ", ".join(t for t in chain.TRANSFERS if t != "log"),
         warm(("tonemap",), S(), transfers=tuple(t for t in chain.TRANSFERS if t != "log"))),
    ]
    if cfas.is_colour(cfa):
        mosaic = f"Bayer {cfa}"
        stages += [
            ("nrvalidity", f"{mosaic}, every mode and dark policy", warm(("validity",), validity, cfa=cfa)),
            ("nrcrosstalk", f"{mosaic}, every mode and LUT form", warm(("crosstalk",), crosstalk, cfa=cfa)),
            ("nrreconstruct", f"{mosaic}, " + ", ".join(chain.COLOUR_METHODS) + ", every preset",
             warm(("reconstruction",), recon(chain.COLOUR_METHODS, chain.PRESETS), cfa=cfa)),
            ("nrtonemap", "RGB tone map, " + ", ".join(tonemap.SDR_OPERATORS),
             lambda: tonemap.warmup_rgb(elements=True)),
            ("nrtonemap", "RGB HDR output " + ", ".join(hdr_output.TRANSFERS),
             lambda: hdr_output.warmup_rgb(elements=True)),
        ]
    return stages


def run_warmup(out=None, cfa: str = "none") -> tuple[int, float]:
    """Compile (or load from cache) every kernel, the colour chain's too for a Bayer `cfa`; prints a line per
    stage to `out` (default: stdout); returns (compiled, seconds)."""
    from nrhdr_core.realtime import JitWatch
    out = sys.stdout if out is None else out
    stages = _stages(cfa)
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
    n, sec = run_warmup(cfa=a.cfa)
    from nrhdr_core import realtime
    t0 = time.perf_counter()
    realtime.load_scene("synthetic", 1080)          # the 1080p camera stand-in's scene, into its file cache
    print(f"nrhdr warmup: nrcamsrc scene=synthetic at 1080p ... {time.perf_counter() - t0:.1f} s (scene cache)")
    print(f"nrhdr warmup: done in {sec:.1f} s ({n} function(s) compiled; a second run compiles none)")
    if a.check and n:
        print("nrhdr warmup: --check: kernels were not in the cache", file=sys.stderr)
        return 1
    return 0


def add_warmup(sub) -> None:
    p = sub.add_parser("warmup", help="compile the numba kernels of the chain once (numba cache), so "
                                      "pipelines start at full speed")
    from nrhdr_core.cfa import CFAS
    p.add_argument("--check", action="store_true",
                   help="exit 1 if any kernel had to be compiled (i.e. the cache was cold)")
    p.add_argument("--cfa", choices=CFAS, default="none",
                   help="also the colour chain's kernels, on a Bayer mosaic of this phase (docs/COLOUR.md); "
                        "default none: the monochrome chain's only")
    p.set_defaults(func=cmd_warmup)
