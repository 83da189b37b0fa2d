#!/usr/bin/env python3
"""Per-frame cost of the HDR frame plumbing: one-block f32-u8-planar frames from the buffer pool
mapped as numpy views (what nrvalidity does now), against the anchor measured in the same run: the older
two-block frame allocated per frame and mapped block by block (map_range), and a copying `new_wrapped`.

    .venv/bin/python benchmarks/hdr_buffer.py [--width 1920 --height 1080 --repeat 200]

Downstream is modelled as holding the last two frames (a queue). Prints milliseconds per frame (median of
--repeat): allocation, mapping and one write of every pixel (as a
kernel does; fresh memory costs page faults), no kernel work.
"""
from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))


def timed_interleaved(fns, repeat):
    """Median ms per call of each function, calls interleaved in rotating order (shared-machine noise,
    CPU clock changes and cache state left by the previous call hit all variants alike)."""
    out = {f.__name__: [] for f in fns}
    for i in range(repeat):
        for f in fns[i % len(fns):] + fns[:i % len(fns)]:      # rotate: no variant always follows another
            t0 = time.perf_counter()
            f()
            out[f.__name__].append(time.perf_counter() - t0)
    return {k: 1e3 * statistics.median(v) for k, v in out.items()}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--width", type=int, default=1920)
    ap.add_argument("--height", type=int, default=1080)
    ap.add_argument("--repeat", type=int, default=200)
    a = ap.parse_args(argv)
    from gst_plugins.elements._common import Gst, HdrInfo, HdrPool, map_hdr, np
    w, h = a.width, a.height
    info = HdrInfo(w, h, 30, 1, None, None)
    pool = HdrPool(info)

    held = {"one_block_pool": [], "two_blocks_per_frame": []}

    def hold(name, buf):                 # downstream (a queue) still holds the last 2 frames, as in a pipeline
        q = held[name]
        q.append(buf)
        del q[:-2]

    def one_block_pool():
        buf = pool.acquire()
        hold("one_block_pool", buf)
        with map_hdr(buf, info, write=True) as (values, state):
            values.fill(1.0)             # a kernel writes every pixel: page faults of fresh memory count
            state.fill(1)

    def two_blocks_per_frame():          # two blocks per frame (anchor)
        alloc = Gst.Allocator.find(None)
        buf = Gst.Buffer.new()
        buf.append_memory(alloc.alloc(4 * w * h, None))
        buf.append_memory(alloc.alloc(w * h, None))
        ok0, m0 = buf.map_range(0, 1, Gst.MapFlags.READ | Gst.MapFlags.WRITE)
        ok1, m1 = buf.map_range(1, 1, Gst.MapFlags.READ | Gst.MapFlags.WRITE)
        np.ndarray((h, w), np.float32, buffer=m0.data).fill(1.0)
        np.ndarray((h, w), np.uint8, buffer=m1.data).fill(1)
        buf.unmap(m1)
        buf.unmap(m0)
        hold("two_blocks_per_frame", buf)

    frame = np.zeros(5 * w * h, np.uint8)

    def wrapped_copy():                   # Gst.Buffer.new_wrapped(arr.tobytes()): two copies of a frame
        Gst.Buffer.new_wrapped(frame.tobytes())

    fns = (one_block_pool, two_blocks_per_frame, wrapped_copy)
    for f in fns:
        f()
    r = timed_interleaved(fns, a.repeat)
    held.clear()
    pool.close()
    print(f"{w}x{h}, median of {a.repeat}, ms per frame (allocation + map + fill + unmap):")
    for k, v in r.items():
        print(f"  {k:22s} {v:8.3f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
