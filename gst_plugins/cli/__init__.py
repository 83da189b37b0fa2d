"""The `nrhdr` command: simulate a camera, run and inspect the GStreamer elements, the demo, the paper's
SNR analysis and (from `nrhdr_core.calibration`) crosstalk calibration. `nrhdr --help` lists it all."""
from __future__ import annotations

import argparse
import importlib
import signal
import sys

# Every `nrhdr` subcommand, in `nrhdr --help` order, and the module of this package that implements it:
# module.add_<name>(sub) adds its parser (options, help text) and module.cmd_<name>(args) runs it.
COMMANDS = (
    ("simulate", "clip"),             # HDR scene -> raw clip folder (nrhdr_core.simulate)
    ("profile", "clip"),              # camera profile: mask PNG + JSON (nrhdr_core.profile)
    ("launch", "gst"),                # gst-launch-1.0 with the nrhdr elements found
    ("inspect", "gst"),               # gst-inspect-1.0 with the nrhdr elements found
    ("demo", "clip"),                 # simulate a clip and run the whole chain
    ("snr", "paper"),                 # the paper's SNR analysis, Figs. 3-5 (nrhdr_core.analysis)
    ("env", "gst"),                   # shell exports for plain gst-launch-1.0
    ("warmup", "warmup"),             # compile the numba kernels into the cache
    ("figures", "paper"),             # the paper's Figs. 2-10 (nrhdr_core.figures)
    ("batch", "batch"),               # raw clip -> OpenEXR frames on Dask (nrhdr_core.batch)
    ("recover", "batch"),             # a recording cut off by a crash -> a clip folder (nrhdr_core.outputs)
    ("calibrate", "calibrate"),       # crosstalk / ND calibration from flats (nrhdr_core.calibration)
    ("simulate-flats", "calibrate"),  # a simulated flat-field sweep for calibrate
    ("compare", "compare"),           # EXR frames against the simulator's truth, per region (nrhdr_core.metrics)
    ("hdr10", "hdr"),                 # raw clip -> HDR10 / HLG video or HDR PNG stills (nrhdr_core.hdr_output)
)


def _add_function(name: str, module: str):
    mod = importlib.import_module(f"{__name__}.{module}")
    return getattr(mod, "add_" + name.replace("-", "_"))


def build_parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(prog="nrhdr", description=__doc__)
    ap.add_argument("--version", action="version", version=f"nrhdr {__import__('nrhdr_core').__version__}")
    sub = ap.add_subparsers(dest="command", required=True)
    for name, module in COMMANDS:
        _add_function(name, module)(sub)
    return ap


def main(argv=None) -> int:
    """Run one `nrhdr` command; returns its exit status (2: bad arguments or input, named on stderr)."""
    ap = build_parser()
    try:
        a = ap.parse_args(argv)
    except SystemExit as e:                 # argparse's own exit: --help, --version, a refused argument
        return e.code if isinstance(e.code, int) else 2
    try:
        return int(a.func(a) or 0)
    except KeyboardInterrupt as e:           # Ctrl-C, or outputs.Interrupted (SIGTERM, SIGHUP) with its signum
        signum = int(getattr(e, "signum", signal.SIGINT))
        print(f"nrhdr {a.command}: stopped by {signal.Signals(signum).name}", file=sys.stderr)
        return 128 + signum
    except (ValueError, OSError) as e:
        print(f"nrhdr {a.command}: error: {e}", file=sys.stderr)
        return 2
