"""argparse value types for every `nrhdr` command: numbers are checked (finite, in range) before any work,
so `--exposure nan` or `--frames 1e9` is refused with a message naming the option."""
from __future__ import annotations

import argparse
import math

from nrhdr_core.profile import MAX_SIZE, ND_MAX


def _show(x) -> str:
    """A bound as the user would type it: 1024, not 1024.0."""
    return str(int(x)) if float(x).is_integer() else f"{x:g}"


def number(lo: float | None = None, hi: float | None = None, *, integer: bool = False,
           lo_open: bool = False, hi_open: bool = False):
    """A `type=` for argparse: a finite int/float within [lo, hi] (open ends where asked)."""
    def parse(text: str):
        try:
            v = int(text, 10) if integer else float(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"{text!r} is not {'a whole number' if integer else 'a number'}")
        if not integer and not math.isfinite(v):        # (a Python int is always finite, and may exceed a float)
            raise argparse.ArgumentTypeError(f"{text!r} is not a finite number")
        if lo is not None and (v < lo or (lo_open and v == lo)):
            raise argparse.ArgumentTypeError(f"{text} is out of range: must be {'>' if lo_open else '>='} {_show(lo)}")
        if hi is not None and (v > hi or (hi_open and v == hi)):
            raise argparse.ArgumentTypeError(f"{text} is out of range: must be {'<' if hi_open else '<='} {_show(hi)}")
        return v
    parse.__name__ = "integer" if integer else "number"    # argparse names the type in its message
    return parse


# the value ranges of the options several commands share
SEED = number(0, 2 ** 63 - 1, integer=True)
SIZE = number(1, MAX_SIZE, integer=True)       # sensor width / height
ND = number(1, ND_MAX)                         # ND factor (Eq. 1)
CODE_LEVEL = number(0, 65535)                  # a level in ADC codes (l_min)


def add_allow_outside(p) -> None:
    """`--allow-outside-paths`: trust the files named inside the JSON/CSV files this command reads (docs/
    RELIABILITY.md): they may then lie outside the folder holding the naming file."""
    p.add_argument("--allow-outside-paths", action="store_true",
                   help="accept files named by a profile, clip.json or exposures.csv outside that file's folder "
                        "(absolute paths, '..', links out of it); only for files you trust")



def recorded_cfa(path) -> str | None:
    """The CFA a JSON file written by nrhdr records (clip.json, a flat sweep's truth.json): its `cfa`, "none"
    where it has none (monochrome), None where the file is missing or unreadable (checked where it is read)."""
    import json
    from pathlib import Path
    p = Path(path)
    if not p.is_file():
        return None
    try:
        return json.loads(p.read_text()).get("cfa", "none") or "none"
    except (ValueError, AttributeError, OSError):
        return None


def sensor_kind(cfa: str) -> str:
    return f"a Bayer {cfa}" if cfa != "none" else "a monochrome"


def check_clip_cfa(source, prof) -> None:
    """ValueError naming both files when the input `source` records another CFA than the camera profile `prof`
    its frames are to be read with (a --profile given beside it): a clip folder's clip.json, else the
    camera.json of a still sequence's folder (a folder, or a file pattern's folder). A Bayer mosaic read as a
    monochrome frame, or the reverse, would be wrong pixel by pixel. A raw file records nothing."""
    from pathlib import Path
    p = Path(source)
    folder = p if p.is_dir() else p.parent if "%" in p.name else None
    if folder is None:
        return
    for name in ("clip.json", "camera.json"):
        recorded = recorded_cfa(folder / name)
        if recorded is not None:
            break
    have = getattr(prof, "cfa", "none")
    if recorded is not None and recorded != have:
        raise ValueError(f"--profile {prof.path or prof.name}: cfa {have!r}, but {folder / name} records "
                         f"{sensor_kind(recorded)} sensor (cfa {recorded!r}): use a profile of that sensor")
