#!/usr/bin/env python3
"""Pull linear HDR frames out of a pipeline as numpy arrays (appsink), values and per-pixel state.

    filesrc ! rawvideoparse ! nrvalidity ! nrcrosstalk ! nrreconstruct ! appsink caps=other/x-nrhdr

Each sample is one `other/x-nrhdr` frame (docs/ELEMENTS.md): one block of 4*W*H bytes float32 linear
values then W*H state bytes. `map_sample(sample)` gives numpy views of both planes without a copy, valid
inside the `with` block (copy what you keep). Without a clip folder, a small clip is simulated first.

Usage:
    .venv/bin/python examples/appsink_numpy.py [CLIP_DIR] [--method nearest] [--save frames.npz]

Prints per frame: measured / reconstructed / clipped / too-dark pixel counts and the value range; with
--save, writes all frames (values, state) to an .npz file.
"""
from __future__ import annotations

import argparse
import os
import sys
import tempfile
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))    # run from a checkout
os.environ.setdefault("GST_REGISTRY_FORK", "no")

import gi  # noqa: E402

gi.require_version("Gst", "1.0")
gi.require_version("GstApp", "1.0")
from gi.repository import Gst, GstApp  # noqa: E402,F401

import numpy as np  # noqa: E402

import gst_plugins  # noqa: E402

from nrhdr_core.states import ATTENUATED, CLIPPED, DARK, REASON_MASK, RECONSTRUCTED, VALID  # noqa: E402,F401


def pull_frames(clip: Path, method: str):
    """Yield (pts, values copy, state copy) for every frame of the clip folder."""
    from gst_plugins.elements._common import map_sample
    from nrhdr_core import simulate
    c = simulate.load_clip(clip)           # checked: sizes, and the files it names inside the clip folder
    w, h = c["width"], c["height"]
    pipeline = Gst.parse_launch(
        f"filesrc location=\"{c['raw_path']}\" ! rawvideoparse format=gray16-le width={w} height={h} "
        f"framerate={c['fps']}/1 plane-strides=<{2 * w}> ! nrvalidity profile=\"{c['profile_path']}\" "
        f"! nrcrosstalk ! nrreconstruct method={method} "
        f"! appsink name=sink sync=false caps=other/x-nrhdr")
    sink = pipeline.get_by_name("sink")
    bus = pipeline.get_bus()
    pipeline.set_state(Gst.State.PLAYING)
    try:
        while True:
            smp = sink.try_pull_sample(5 * Gst.SECOND)
            msg = bus.pop_filtered(Gst.MessageType.ERROR)
            if msg is not None:
                err, _ = msg.parse_error()
                raise RuntimeError(f"{msg.src.get_name()}: {err.message}")
            if smp is None:
                if sink.is_eos():
                    return
                raise RuntimeError("no frame within 5 s")
            with map_sample(smp) as (values, state):          # zero-copy views into the frame
                yield smp.get_buffer().pts, values.copy(), state.copy()
    finally:
        pipeline.set_state(Gst.State.NULL)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("clip", nargs="?", help="clip folder from `nrhdr simulate` (default: simulate a small one)")
    ap.add_argument("--method", default="nearest", choices=("fse", "linear", "nearest", "preview"))
    ap.add_argument("--save", help="write all frames to this .npz (values, state, pts)")
    a = ap.parse_args(argv)
    gst_plugins.register_all()
    tmp = None
    clip = Path(a.clip) if a.clip else None
    if clip is None:
        from nrhdr_core import profile, scene, simulate
        tmp = tempfile.TemporaryDirectory(prefix="appsink_numpy-")
        clip = Path(tmp.name) / "clip"
        simulate.simulate_clip(scene.synthetic_hdr_scene(), clip, profile.default(48, 64, seed=1), frames=5,
                               fps=5, seed=1)
    frames = []
    try:
        for i, (pts, values, state) in enumerate(pull_frames(clip, a.method)):
            reason = state & REASON_MASK
            filled = (state & RECONSTRUCTED) != 0
            print(f"frame {i} pts {pts / Gst.SECOND:.3f} s: {values.shape[1]}x{values.shape[0]} float32, "
                  f"measured {np.count_nonzero(reason == VALID)}, reconstructed {np.count_nonzero(filled)} "
                  f"(clipped {np.count_nonzero(reason == CLIPPED)}, too dark {np.count_nonzero(reason == DARK)}), "
                  f"behind ND {np.count_nonzero(state & ATTENUATED)}, values {values.min():.4g}..{values.max():.4g}")
            frames.append((pts, values, state))
    except RuntimeError as e:
        print(f"appsink_numpy: ERROR {e}", file=sys.stderr)
        return 1
    finally:
        if tmp is not None and not a.save:
            tmp.cleanup()
    if a.save and frames:
        np.savez_compressed(a.save, pts=np.array([f[0] for f in frames]), values=np.stack([f[1] for f in frames]),
                            state=np.stack([f[2] for f in frames]))
        print(f"appsink_numpy: wrote {a.save}")
    print(f"appsink_numpy: {len(frames)} frames")
    return 0 if frames else 1


if __name__ == "__main__":
    sys.exit(main())
