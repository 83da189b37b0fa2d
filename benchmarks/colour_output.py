"""Colour output against grey: ms per 1920 x 1080 frame of each SDR operator, HDR transfer and the Y'CbCr
packing, grey and colour side by side, measured in the same run (docs/COLOUR.md "Colour output").

    PYTHONPATH=. .venv/bin/python benchmarks/colour_output.py              # best of 9 (~1 min)
    PYTHONPATH=. .venv/bin/python benchmarks/colour_output.py --repeat 21
    PYTHONPATH=. .venv/bin/python benchmarks/colour_output.py --only "tone map"   # the SDR rows only

Frame: a luminance ramp over the whole range, g = geomspace(1, 2e4) in raster order (white 2e4, diffuse
white 4094: the default sensor profile's), colour = (1.1 g, g, 0.8 g) planar float32 (3, H, W); white
balance (1.2, 1, 0.9). Grey: `log_tonemap`, `LocalTonemap` (state kept over the calls), `hdr_encode` into
uint16, `hdr_output.i420_10_frame`; colour: `tonemap_rgb` log / `LocalTonemap.rgb` into (H, W, 3) uint8 (the
calls nrtonemap makes for a colour frame; "(rows)" into rows padded as a mapped video frame's may be),
`hdr_encode_rgb` (BT.2020 primaries), `hdr_output.ycbcr_frame` 4:2:0. Roll-off: peak 1000 cd/m^2 from the
white's `peak_luminance`. Every function is called once first (compilation, scratch planes); grey and colour
calls alternate and each figure is the best of `--repeat` calls, so that the ratio compares the same
moments of a shared machine. The anchor `copy` (one float32 1080p np.copyto) is measured in the same run.
"""
from __future__ import annotations

import argparse
import os
import sys
import timeit

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
from nrhdr_core import hdr_output as ho  # noqa: E402
from nrhdr_core import tonemap as t  # noqa: E402

H, W = 1080, 1920
WHITE, DIFFUSE = 2e4, 4094.0
WB = (1.2, 1.0, 0.9)


def cases():
    g = np.geomspace(1.0, WHITE, H * W).astype(np.float32).reshape(H, W)
    rgb = np.stack([1.1 * g, g, 0.8 * g])
    u8, rgb8 = np.empty((H, W), np.uint8), np.empty((H, W, 3), np.uint8)
    padded = np.empty((H, W * 3 + 64), np.uint8)[:, :W * 3].reshape(H, W, 3)
    c1, c3 = np.empty((H, W), np.uint16), np.empty((3, H, W), np.uint16)
    frame = np.empty(W * H * 3, np.uint8)
    offsets, strides = (0, 2 * W * H, 2 * W * H * 5 // 4), (2 * W, W, W)
    dst = np.empty_like(g)
    lg, lc = t.LocalTonemap(), t.LocalTonemap()
    yield "copy (anchor)", lambda: np.copyto(dst, g), None
    yield ("tone map log", lambda: t.log_tonemap(g, WHITE, out=u8),
           lambda: t.tonemap_rgb(rgb, WHITE, "log", WB, out=rgb8))
    yield ("tone map local", lambda: lg(g, WHITE, out=u8),
           lambda: lc.rgb(rgb, WHITE, white_balance=WB, out=rgb8))
    yield ("tone map local (rows)", lambda: lg(g, WHITE, out=u8),
           lambda: lc.rgb(rgb, WHITE, white_balance=WB, out=padded))
    for transfer in t.TRANSFERS:
        for peak in (0.0, 1000.0):
            src = t.peak_luminance(WHITE, DIFFUSE, transfer) if peak else 0.0
            name = f"{transfer}" + (" roll-off" if peak else "")
            yield (name, lambda tr=transfer, p=peak, s=src: t.hdr_encode(g, DIFFUSE, tr, out=c1, peak=p, source_peak=s),
                   lambda tr=transfer, p=peak, s=src: t.hdr_encode_rgb(rgb, DIFFUSE, tr, WB, out=c3, peak=p,
                                                                       source_peak=s))
    yield ("Y'CbCr 4:2:0", lambda: ho.i420_10_frame(c1, frame, offsets, strides),
           lambda: ho.ycbcr_frame(c3, frame, offsets, strides))


def best_ms(fn, repeat: int) -> float:
    fn()
    return min(timeit.repeat(fn, number=1, repeat=repeat)) * 1e3


def best_pair_ms(grey, colour, repeat: int) -> tuple[float, float]:
    """Best of `repeat` calls of each, the calls alternating (after one untimed call each)."""
    grey(), colour()
    g = c = float("inf")
    for _ in range(repeat):
        g = min(g, timeit.timeit(grey, number=1))
        c = min(c, timeit.timeit(colour, number=1))
    return g * 1e3, c * 1e3


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--repeat", type=int, default=9)
    ap.add_argument("--only", default="", help="time only the rows whose name contains this (and the anchor)")
    a = ap.parse_args(argv)
    print(f"{W}x{H}, best of {a.repeat}, ms per frame")
    print(f"{'':22s} {'grey':>8s} {'colour':>8s} {'ratio':>6s}")
    for name, grey, colour in cases():
        if colour is None:
            print(f"{name:22s} {best_ms(grey, a.repeat):8.1f}")
            continue
        if a.only not in name:
            continue
        g, c = best_pair_ms(grey, colour, a.repeat)
        print(f"{name:22s} {g:8.1f} {c:8.1f} {c / g:6.2f}", flush=True)


if __name__ == "__main__":
    main()
