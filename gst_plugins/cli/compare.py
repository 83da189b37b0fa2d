"""`nrhdr compare`: HDR frames written by the chain (nrexrsink / `nrhdr batch`) against the simulator's
ground truth, per region (dark / mid / bright), in log2 PSNR, PU21-PSNR and pixels off by more than 1 and
3 stops (nrhdr_core.metrics.clip_report); for a colour profile (a Bayer cfa) on the BT.709 luminance of the
camera-RGB frames (metrics.rgb_clip_report). Put an unmodified camera beside it: simulate the
same scene with `--pattern none` (no ND pixel, the same noise model) and run it through the same chain."""
from __future__ import annotations

import json
import sys
from pathlib import Path

from .args import add_allow_outside, number


def add_compare(sub) -> None:
    p = sub.add_parser("compare", help="score EXR frames against the simulator's truth, per region (dark/mid/"
                                       "bright), e.g. the ND camera's chain beside an unmodified camera")
    p.add_argument("results", nargs="+", metavar="EXR_DIR",
                   help="folders of frame_NNNNN.exr written by the chain (nrexrsink, nrhdr batch)")
    p.add_argument("--truth", required=True, metavar="DIR",
                   help="the clip's truth/ folder (nrhdr simulate): frames of the same names")
    p.add_argument("--profile", required=True,
                   help="the ND camera's profile JSON: its l_min x ND and regular clip split the regions, "
                        "its white caps both; with a Bayer cfa the frames are camera RGB, scored on their "
                        "luminance")
    p.add_argument("--frames", type=number(0, 10 ** 9, integer=True), default=0,
                   help="score only every k-th frame so that about this many are read (0: all)")
    p.add_argument("--json", action="store_true", help="print the figures as JSON")
    add_allow_outside(p)
    p.set_defaults(func=cmd_compare)


def _frames(folder: Path) -> list[Path]:
    if not folder.is_dir():
        raise ValueError(f"{folder}: not a folder")
    files = sorted(folder.glob("frame_*.exr"))
    if not files:
        raise ValueError(f"{folder}: no frame_*.exr in it")
    return files


def _kind(colour: bool) -> str:
    return "colour (R, G, B)" if colour else "grey (Y)"


def _pairs(files, truth_dir: Path, prof, colour: bool = False):
    """(truth, test) frames of the same name; grey (H, W) or, for a colour profile, camera RGB (3, H, W): a
    frame of the other kind is refused naming it and the profile."""
    from nrhdr_core import io
    for f in files:
        t_path = truth_dir / f.name
        if not t_path.is_file():
            raise ValueError(f"{f}: no truth frame {t_path}")
        truth, _ = io.read_exr(t_path)
        if (truth.ndim == 3) != colour:
            raise ValueError(f"{t_path}: a {_kind(truth.ndim == 3)} truth frame, but --profile {prof.path} is "
                             f"{'a colour profile (cfa ' + prof.cfa + ')' if colour else 'monochrome'}")
        try:
            test, _ = io.read_exr(f, shape=truth.shape[-2:])       # the size is checked before decoding
        except io.ImageSizeError as e:
            raise ValueError(f"{e}: the size of its truth {t_path}") from None
        if test.ndim != truth.ndim:
            raise ValueError(f"{f}: a {_kind(test.ndim == 3)} frame, its truth {t_path} is {_kind(truth.ndim == 3)}")
        yield truth, test


def cmd_compare(a) -> int:
    from nrhdr_core import cfa, metrics, profile
    prof = profile.load(a.profile, allow_outside=a.allow_outside_paths)
    colour = cfa.is_colour(prof.cfa)
    score = metrics.rgb_clip_report if colour else metrics.clip_report
    truth_dir = Path(a.truth)
    if not truth_dir.is_dir():
        raise ValueError(f"--truth {truth_dir}: not a folder")
    dark, bright, white = prof.l_min * prof.nd, prof.regular_white, prof.white
    report = {}
    for r in a.results:
        files = _frames(Path(r))
        if a.frames:
            files = files[:: max(1, len(files) // a.frames)]
        report[r] = score(_pairs(files, truth_dir, prof, colour), dark, bright, white)
    if a.json:
        json.dump({"regions": {"dark_below": dark, "bright_from": bright, "white": white},
                   "values": "luminance" if colour else "grey", "results": report}, sys.stdout, indent=1)
        print()
        return 0
    what = "the BT.709 luminance of camera RGB (colour profile, cfa " + prof.cfa + ")" if colour else "grey values"
    print(f"scored: {what}; regions by the truth: dark < l_min x ND = {dark:g}, bright >= the regular clip "
          f"{bright:g}; both capped at white {white:g}; log2 PSNR peak log2(white)\n")
    print("| frames | negative / non-finite | log2 PSNR all / dark / mid / bright (dB) | PU21-PSNR dark / mid / "
          "bright (dB) | pixels > 1 stop / > 3 stops off | EXR folder |")
    print("|---|---|---|---|---|---|")
    fmt = lambda x: "-" if x is None else f"{x:.2f}"  # noqa: E731
    for r, s in report.items():
        lp = " / ".join(fmt(s[k]["log2_psnr"]) for k in metrics.REGIONS)
        pu = " / ".join(fmt(s[k]["pu21_psnr"]) for k in ("dark", "mid", "bright"))
        print(f"| {s['frames']} | {s['negative']} / {s['nonfinite']} | {lp} | {pu} | "
              f"{s['all']['off_1stop']} / {s['all']['off_3stops']} | {r} |")
    return 0
