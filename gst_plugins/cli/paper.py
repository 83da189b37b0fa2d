"""`nrhdr snr`: the paper's SNR and valid-pixel analysis (nrhdr_core.analysis); `nrhdr figures`: the paper's
Figs. 2-10 regenerated with the numbers beside the paper's (nrhdr_core.figures)."""
from __future__ import annotations

import sys

from .args import CODE_LEVEL, ND, SEED


def cmd_snr(a) -> int:
    from nrhdr_core import analysis
    paths = analysis.run_snr_analysis(a.output, nd=a.nd, l_min=a.l_min, seed=a.seed, overwrite=a.force)
    for p in paths:
        print(f"wrote {p}")
    return 0


def add_snr(sub) -> None:
    p = sub.add_parser("snr", help="the paper's SNR and valid-pixel analysis (Fig. 3, 4, 5) as plots")
    p.add_argument("-o", "--output", default="snr_out")
    p.add_argument("--nd", type=ND, default=6.35)
    p.add_argument("--l-min", type=CODE_LEVEL, default=100.0)
    p.add_argument("--seed", type=SEED, default=0)
    p.add_argument("--force", action="store_true", help="replace the three files of an earlier run")
    p.set_defaults(func=cmd_snr)


def cmd_figures(a) -> int:
    from nrhdr_core import figures
    try:
        doc = figures.run(a.output, quick=a.quick, force=a.force, seed=a.seed, data_dir=a.data,
                          progress=not a.quiet)
    except ValueError as e:
        print(f"nrhdr figures: error: {e}", file=sys.stderr)
        return 2
    print(f"wrote {len(doc['files'])} figures, figures.json and index.md to {a.output}/ "
          f"({doc['total_seconds']} s)")
    for r in doc["numbers"]:
        if r["paper"] is not None:
            print(f"  {r['figure']}: {r['quantity']}: paper {r['paper']}, ours {r['ours']} {r['unit']}")
    return 0


def add_figures(sub) -> None:
    p = sub.add_parser("figures", help="the paper's Figs. 2-10 as PNG + figures.json + index.md (paper vs ours)",
                       description="Regenerate the paper's figures from simulation: Fig. 2 (mask spectra, "
                                   "aliasing), 3-5 (ideal camera SNR, known pixels, FSE), 6b (crosstalk), "
                                   "7-8 (calibration), 9 (SNR after LUT compensation), 10 (HDR scene). "
                                   "Uses ../shared/data/hdr/*.exr for Fig. 10 when present.")
    p.add_argument("-o", "--output", required=True, help="new (or empty) folder to write")
    p.add_argument("--quick", action="store_true", help="smaller sizes (under 2 minutes on 2 cores)")
    p.add_argument("--force", action="store_true",
                   help="write into an existing non-empty folder (replaces only the files written here)")
    p.add_argument("--seed", type=SEED, default=0)
    p.add_argument("--data", help="shared data folder with hdr/*.exr (default: $NRHDR_SHARED_DATA or "
                                  "../shared/data)")
    p.add_argument("-q", "--quiet", action="store_true")
    p.set_defaults(func=cmd_figures)
