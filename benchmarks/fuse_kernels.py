"""`fuse_noisy`'s kernel (the NOISY-pixel fusion of the reconstruction) at a git revision against the
working tree's, in one run: `_fuse_kernel` on the same 1920 x 1080 inputs (random masks: 50 % known, 0 %
and 30 % NOISY), interleaved call by call; both must give the same bits.

    PYTHONPATH=. .venv/bin/python benchmarks/fuse_kernels.py --before 7436889

The revision's kernel is the source of `_fuse_add_row`, `_fuse_slide` and `_fuse_kernel` in
``git show REV:nrhdr_core/reconstruction.py``, compiled here (numba, not cached). Median of ``--repeat``
calls each after two untimed ones; anchor: one float32 frame copy, same run."""
from __future__ import annotations

import argparse
import statistics
import subprocess
import sys
import time
from pathlib import Path

import numba
import numpy as np
from numba import njit, prange

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from nrhdr_core import reconstruction as R  # noqa: E402


def load_base(rev):
    src = subprocess.run(["git", "-C", str(ROOT), "show", f"{rev}:nrhdr_core/reconstruction.py"],
                         capture_output=True, text=True, check=True).stdout
    a = src.index('@njit(cache=True, nogil=True, inline="always")\ndef _fuse_add_row(')
    b = src.index("\n\n\n", src.index("def _fuse_kernel("))
    ns = dict(njit=njit, prange=prange, np=np)
    exec(src[a:b].replace("cache=True", "cache=False"), ns)   # noqa: S102 (our own source at REV)
    return ns["_fuse_kernel"]


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--before", default="HEAD~1", help="git revision to compare the working tree's kernel with")
    ap.add_argument("--repeat", type=int, default=12)
    a = ap.parse_args(argv)
    base = load_base(a.before)
    rng = np.random.default_rng(1)
    h, w = 1080, 1920
    v = (rng.random((h, w)) * 3000).astype(np.float32)
    known = rng.random((h, w)) < 0.5
    nt = numba.get_num_threads()
    args = (np.float32(0.55), np.float32(0.55 ** 2 * 4 + 1 / 12), np.float32(6.35), np.float32(1.0), 2)
    ta = []
    for _ in range(a.repeat + 2):
        t = time.perf_counter()
        v.copy()
        ta.append(time.perf_counter() - t)
    print(f"# fuse_noisy kernel, {w}x{h}, base = {a.before}, tree = working tree; numba threads {nt}")
    print(f"anchor: float32 frame copy {statistics.median(ta[2:]) * 1e3:.2f} ms\n")
    print("| NOISY share | setting | base ms | tree ms | tree / base | same bits |")
    print("|---|---|---|---|---|---|")
    for frac in (0.0, 0.3):
        noisy = ~known & (rng.random((h, w)) < frac * 2)
        for joint in (False, True):
            tb, tf = [], []
            for _ in range(a.repeat + 2):
                g = v.copy()
                t = time.perf_counter()
                base(g, v, known, noisy, *args, joint, 64, nt)
                tb.append(time.perf_counter() - t)
                g2 = v.copy()
                t = time.perf_counter()
                R._fuse_kernel(g2, v, known, noisy, *args, joint, 64, nt)
                tf.append(time.perf_counter() - t)
            b, f = statistics.median(tb[2:]), statistics.median(tf[2:])
            print(f"| {noisy.mean():.2f} | {'accurate' if joint else 'fast'} | {b * 1e3:.2f} | {f * 1e3:.2f} | "
                  f"{f / b:.3f} | {'yes' if np.array_equal(g, g2) else 'NO'} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
