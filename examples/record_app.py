#!/usr/bin/env python3
"""A small recording app that embeds the nrhdr elements in-process.

Records a raw clip to a linear OpenEXR sequence (values + per-pixel state, full dynamic range) and
tone-mapped PNG previews, from one pipeline with a tee:

    filesrc ! rawvideoparse ! nrvalidity ! nrcrosstalk ! nrreconstruct ! tee
        tee. ! queue ! nrexrsink                       (OUT/exr/frame_%05d.exr)
        tee. ! queue ! nrtonemap ! pngenc ! multifilesink (OUT/png/frame_%05d.png)

Usage:
    .venv/bin/python examples/record_app.py CLIP_DIR OUT_DIR [--method fse] [--preset fast]
    .venv/bin/python examples/record_app.py --raw clip.raw --width 640 --height 480 --fps 30 \
        --profile camera.json OUT_DIR

Exit status: 0 when every frame was recorded, 1 on a pipeline error (printed with the element's name),
2 on bad arguments, 130 when interrupted twice. Ctrl-C once finishes the recording cleanly (EOS).
"""
from __future__ import annotations

import argparse
import os
import signal
import sys
import time
from pathlib import Path

# Run from a checkout without installing: make `gst_plugins` and `nrhdr_core` importable.
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

# An app started from a virtualenv must keep the registry scan in-process (the external scanner runs the
# system Python). Registering in-process (below) does not need the scan at all.
os.environ.setdefault("GST_REGISTRY_FORK", "no")

import gi  # noqa: E402

gi.require_version("Gst", "1.0")
from gi.repository import GLib, Gst  # noqa: E402

import gst_plugins  # noqa: E402


def parse_args(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("clip", nargs="?", help="clip folder from 'nrhdr simulate' (clip.json, clip.raw, camera.json)")
    ap.add_argument("output", help="output folder: exr/ and png/ are created in it")
    ap.add_argument("--raw", help="raw GRAY16_LE file (instead of a clip folder)")
    ap.add_argument("--profile", help="camera profile JSON (default: the clip's camera.json)")
    ap.add_argument("--width", type=int, help="frame width (default: from clip.json)")
    ap.add_argument("--height", type=int, help="frame height (default: from clip.json)")
    ap.add_argument("--fps", type=int, help="frame rate (default: from clip.json)")
    ap.add_argument("--method", default="fse", choices=("fse", "linear", "nearest", "preview"))
    ap.add_argument("--preset", default="fast", choices=("preview", "fast", "balanced", "best"))
    ap.add_argument("--exposure", type=float, default=0.0, help="preview exposure in stops")
    return ap.parse_args(argv)


def clip_settings(a) -> dict:
    info = {}
    if a.clip:
        from nrhdr_core import simulate
        try:
            info = simulate.load_clip(a.clip)   # checked: sizes, and the files it names inside the clip folder
        except simulate.ClipError as e:
            raise SystemExit(f"record_app: {e}")
        info["raw"], info["profile"] = info["raw_path"], info["profile_path"]
    for k in ("raw", "profile", "width", "height", "fps"):
        v = getattr(a, k)
        if v is not None:
            info[k] = v
    missing = [k for k in ("raw", "profile", "width", "height", "fps") if k not in info]
    if missing:
        raise SystemExit(f"record_app: give a clip folder or --{' --'.join(missing)}")
    return info


def build_pipeline(c: dict, out: Path, a) -> Gst.Pipeline:
    """The pipeline is described as text (gst-launch syntax) with escaped paths, then parsed."""
    def q(s):  # quote a path for parse_launch
        return '"' + str(s).replace("\\", "\\\\").replace('"', '\\"') + '"'

    w, h = int(c["width"]), int(c["height"])
    desc = (
        f"filesrc location={q(c['raw'])} ! rawvideoparse format=gray16-le width={w} height={h} "
        f"framerate={int(c['fps'])}/1 plane-strides=<{2 * w}> "
        f"! nrvalidity name=validity profile={q(c['profile'])} ! nrcrosstalk "
        f"! nrreconstruct name=reconstruct method={a.method} preset={a.preset} post-stats=true ! tee name=t "
        f"t. ! queue ! nrexrsink name=exr location={q(out / 'exr' / 'frame_%05d.exr')} write-state=true "
        f"t. ! queue ! nrtonemap exposure={a.exposure} ! video/x-raw,format=GRAY8 ! pngenc "
        f"! multifilesink location={q(out / 'png' / 'frame_%05d.png')}"
    )
    return Gst.parse_launch(desc)


def main(argv=None) -> int:
    a = parse_args(argv)
    c = clip_settings(a)
    out = Path(a.output)
    for sub in ("exr", "png"):
        (out / sub).mkdir(parents=True, exist_ok=True)

    gst_plugins.register_all()           # one call: every nrhdr element, in this process
    try:
        pipeline = build_pipeline(c, out, a)
    except GLib.Error as e:
        print(f"record_app: bad pipeline: {e.message}", file=sys.stderr)
        return 2

    loop = GLib.MainLoop()
    state = {"rc": 0, "frames": 0, "missing": 0.0, "seconds": 0.0, "interrupts": 0}

    def on_message(_bus, msg):
        t = msg.type
        if t == Gst.MessageType.ELEMENT:
            s = msg.get_structure()
            if s is not None and s.get_name() == "nrhdr-frame-stats":
                state["frames"] += 1
                state["missing"] += s.get_value("missing")
                state["seconds"] += s.get_value("seconds")
        elif t == Gst.MessageType.ERROR:
            err, dbg = msg.parse_error()
            print(f"record_app: ERROR from {msg.src.get_name()}: {err.message}", file=sys.stderr)
            if dbg:
                print(f"  debug: {dbg}", file=sys.stderr)
            state["rc"] = 1
            loop.quit()
        elif t == Gst.MessageType.WARNING:
            w, _ = msg.parse_warning()
            print(f"record_app: warning from {msg.src.get_name()}: {w.message}", file=sys.stderr)
        elif t == Gst.MessageType.EOS:
            loop.quit()

    def on_sigint():
        state["interrupts"] += 1
        if state["interrupts"] == 1:
            print("record_app: stopping, finishing the files (Ctrl-C again to abort)", file=sys.stderr)
            pipeline.send_event(Gst.Event.new_eos())
            return GLib.SOURCE_CONTINUE
        state["rc"] = 130
        loop.quit()
        return GLib.SOURCE_REMOVE

    bus = pipeline.get_bus()
    bus.add_signal_watch()
    bus.connect("message", on_message)
    GLib.unix_signal_add(GLib.PRIORITY_DEFAULT, signal.SIGINT, on_sigint)

    t0 = time.perf_counter()
    if pipeline.set_state(Gst.State.PLAYING) == Gst.StateChangeReturn.FAILURE:
        # the element at fault has posted an error: let the bus handler print it
        ctx = loop.get_context()
        while ctx.pending():
            ctx.iteration(False)
        if state["rc"] == 0:
            print("record_app: the pipeline could not start", file=sys.stderr)
        state["rc"] = 1
    else:
        loop.run()
    pipeline.set_state(Gst.State.NULL)
    bus.remove_signal_watch()
    dt = time.perf_counter() - t0

    if state["rc"] == 0:
        n = state["frames"]
        miss = 100.0 * state["missing"] / n if n else 0.0
        print(f"record_app: {n} frames in {dt:.1f} s: {out / 'exr'}/ (OpenEXR, Y + state), "
              f"{out / 'png'}/ (PNG previews); {miss:.1f} % of pixels reconstructed "
              f"({a.method}, {state['seconds'] / max(n, 1) * 1000:.1f} ms/frame)")
    return state["rc"]


if __name__ == "__main__":
    sys.exit(main())
