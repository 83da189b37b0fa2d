"""`nrhdr simulate`, `nrhdr profile`, `nrhdr demo`: simulated clips and camera profiles, and the demo
that runs the whole chain on one (nrhdr_core.simulate, nrhdr_core.profile)."""
from __future__ import annotations

import argparse
import shlex
import sys
import time
from pathlib import Path

from .args import CODE_LEVEL, ND, SEED, SIZE, add_allow_outside, number


def rgb_numbers(lo: float, hi: float):
    """A `type=` for argparse: three comma-separated numbers R,G,B, each checked by `args.number(lo, hi)`."""
    one = number(lo, hi)

    def parse(text: str):
        parts = text.split(",")
        if len(parts) != 3:
            raise argparse.ArgumentTypeError(f"{text!r} is not three numbers R,G,B (e.g. 0.6,1,0.8)")
        return tuple(float(one(t.strip())) for t in parts)
    parse.__name__ = "R,G,B"
    return parse


def _scene(arg: str | None, colour: bool = False):
    """Load the scene named on the command line (linear RGB (3, H, W) for a colour sensor, else its
    luminance), or synthesise the default one (in colour for a colour sensor: simulate.synthetic_rgb_scene)."""
    from nrhdr_core import io, scene, simulate
    if arg in (None, "", "synthetic"):
        return (simulate.synthetic_rgb_scene() if colour else scene.synthetic_hdr_scene()), "synthetic"
    if colour:
        return io.read_rgb(arg, nonfinite="error"), Path(arg).name
    return io.read_luminance(arg, nonfinite="error"), Path(arg).name


def _pattern(a) -> str:
    """--pattern (default nonregular), refused where --nd-layout regular (which has no pattern) contradicts it."""
    if getattr(a, "nd_layout", None) == "regular" and a.pattern not in (None, "regular", "none"):
        raise ValueError(f"--pattern {a.pattern} contradicts --nd-layout regular (the Assorted-Pixels block "
                         f"checkerboard: it has no pattern of its own); use --nd-layout balanced or independent")
    return a.pattern or "nonregular"


def _profile_from_args(a, **fields):
    from nrhdr_core import profile
    if getattr(a, "profile", None):
        return profile.load(a.profile, allow_outside=a.allow_outside_paths)
    pattern = _pattern(a)
    cfa = getattr(a, "cfa", None) or "none"
    layout = getattr(a, "nd_layout", None)
    if cfa != "none":
        for opt, v in (("--width", a.width), ("--height", a.height)):
            if v % 2:
                raise ValueError(f"{opt} {v}: a Bayer sensor (--cfa {cfa}) has an even width and height (whole "
                                 f"2 x 2 blocks)")
        fields["cfa"] = cfa
    elif layout not in (None, "independent"):
        raise ValueError(f"--nd-layout {layout} places the ND filter over a colour filter array: give --cfa")
    if pattern == "none":    # the unmodified camera: no ND pixel, the same sensor and noise
        import numpy as np
        return profile.make(np.zeros((a.height, a.width), bool), nd=a.nd, l_min=a.l_min, **fields)
    if cfa != "none":
        fields["nd_layout"] = layout
    return profile.default(a.height, a.width, seed=a.mask_seed, pattern=pattern, nd=a.nd, l_min=a.l_min,
                           **fields)


def _option_error(e: ValueError) -> ValueError:
    """A ValueError of nrhdr_core whose message starts with an argument's name, naming the option instead:
    'cut_frame must ...' -> '--cut-frame must ...'."""
    text = str(e)
    name = text.split(" ")[0].rstrip(":")
    return ValueError("--" + name.replace("_", "-") + text[len(name):])


def cmd_simulate(a) -> int:
    from nrhdr_core import cfa as cfas
    from nrhdr_core import simulate
    motion = simulate.Motion(pan=a.pan, tilt=a.tilt, zoom=a.zoom, fov=a.fov)
    try:                                   # before anything is read or written; messages start with the name
        simulate.check_args(a.frames, a.fps, a.exposure, motion, a.sequence, cut_frame=a.cut_frame,
                            cfa=a.cfa, nd_layout=a.nd_layout, sensitivity=a.sensitivity)
    except ValueError as e:
        raise _option_error(e) from None
    if a.cut_scene is not None and a.cut_frame is None:
        raise ValueError("--cut-scene needs --cut-frame (the frame at which the second shot starts)")
    prof = _profile_from_args(a)
    try:
        simulate.clip_profile(prof, a.cfa, a.nd_layout)
    except ValueError as e:
        raise ValueError(f"{_option_error(e)} (--profile {a.profile})") from None
    colour = cfas.is_colour(prof.cfa)
    if a.sensitivity is not None and not colour:
        raise ValueError("--sensitivity weighs the colour channels of a Bayer sensor: give --cfa (or a colour "
                         "--profile)")
    sens = a.sensitivity or (1.0, 1.0, 1.0)
    model = None
    if a.sensor_model and a.sensor_model != "none":
        from nrhdr_core import crosstalk
        model = crosstalk.sensor_model_preset(a.sensor_model, prof.height, prof.width,
                                                 seed=a.sensor_seed)
    scene, name = _scene(a.scene, colour)
    simulate.check_scene(scene, prof, a.exposure, a.scene or "synthetic", sens)
    cut_scene, cut_name = _scene(a.cut_scene, colour) if a.cut_scene is not None else (None, None)
    if cut_scene is not None:
        simulate.check_scene(cut_scene, prof, a.exposure, a.cut_scene, sens)
    objects = simulate.random_objects(a.objects, prof.height, prof.width, a.frames, a.object_speed,
                                      a.object_size, a.object_kind, a.seed)
    extra = {"nd_layout": a.nd_layout, "sensitivity": a.sensitivity} if colour else {}
    info = simulate.simulate_clip(scene, a.output, prof, frames=a.frames, fps=a.fps,
                                  exposure_stops=a.exposure, motion=motion, seed=a.seed,
                                  sensor_model=model, sequence=a.sequence, scene_name=name,
                                  overwrite=a.force, objects=objects, cut_frame=a.cut_frame,
                                  cut_scene=cut_scene, cut_scene_name=cut_name, **extra)
    out = Path(a.output)
    mosaic = f" (Bayer {info['cfa']} mosaic, ND layout {info['nd_layout']})" if info.get("cfa") else ""
    print(f"wrote {info['frames']} frames {info['width']}x{info['height']} GRAY16_LE{mosaic} to "
          f"{out / 'clip.raw'}")
    print(f"profile {out / 'camera.json'}, ground truth {out / 'truth'}/")
    clip = shlex.quote(str(out))
    if colour:
        print(f"run it: pipelines/colour_to_exr.sh {clip} (linear camera-RGB OpenEXR frames), "
              f"pipelines/raw_to_display.sh {clip} (on the screen)   or\n  {launch_line(info, out)}")
    else:
        print(f"run it: pipelines/raw_to_display.sh {clip}   or\n  {launch_line(info, out)}")
    return 0


def launch_line(clip: dict, out: Path, sink: str = "autovideosink") -> str:
    """The `nrhdr launch` command that plays clip folder `out`, quoted for a POSIX shell: it pastes into
    bash as printed (`plane-strides=<N>` and paths with spaces stay one argument each). The same line plays a
    colour clip: nrvalidity takes the CFA from the profile, nrreconstruct demosaics, nrtonemap gives RGB."""
    words = ["nrhdr", "launch", "filesrc", f"location={out / 'clip.raw'}", "!", *rawvideoparse(clip).split(),
             "!", "nrvalidity", f"profile={out / 'camera.json'}", "!", "nrreconstruct", "!", "nrtonemap", "!",
             "videoconvert", "!", sink]
    return " ".join(w if w == "!" else shlex.quote(w) for w in words)     # a lone ! is not history expansion


def cmd_profile(a) -> int:
    from nrhdr_core import profile
    fmt = {"bit_depth": a.bit_depth, "black_level": a.black_level, "alignment": a.alignment,
           "packing": a.packing, "out_of_range": a.out_of_range}
    if a.white_level is not None:
        fmt["white_level"] = a.white_level
    elif a.bit_depth != 12:
        fmt["white_level"] = (1 << a.bit_depth) - 1
    if a.gain is not None:
        fmt["gain"] = a.gain
    if a.white_balance is not None:
        if a.cfa in (None, "none"):
            raise ValueError("--white-balance holds the gains of a Bayer sensor's colour channels: give --cfa")
        fmt["white_balance"] = a.white_balance
    p = _profile_from_args(a, **fmt)
    profile.save(p, a.output, overwrite=a.force)
    colour = ""
    if a.cfa not in (None, "none"):
        from nrhdr_core import mask
        colour = f", CFA {p.cfa}, ND layout {mask.nd_layout_of(p.mask, p.cfa)}"
    print(f"wrote {a.output} ({p.width}x{p.height}, {_pattern(a)} mask, ND {p.nd}, "
          f"{p.mask.mean() * 100:.1f} % attenuated{colour})")
    return 0


def rawvideoparse(clip: dict) -> str:
    """rawvideoparse for a clip's GRAY16_LE file: rows are unpadded (GStreamer's default stride would
    round odd widths up to 4 bytes)."""
    return (f"rawvideoparse format=gray16-le width={clip['width']} height={clip['height']} "
            f"framerate={clip['fps']}/1 plane-strides=<{2 * clip['width']}>")


def demo_pipeline(clip: dict, out: Path, method: str, preset: str) -> str:
    d = Path(clip["dir"])
    prof = d / clip["profile"]
    return (f"filesrc location={d / clip['raw']} ! {rawvideoparse(clip)} ! nrvalidity profile={prof} ! "
            f"nrcrosstalk profile={prof} ! nrreconstruct method={method} preset={preset} post-stats=true ! tee name=t "
            f"t. ! queue ! nrexrsink write-state=true location={out / 'exr' / 'frame_%05d.exr'} "
            f"t. ! queue ! nrtonemap ! pngenc ! multifilesink location={out / 'png' / 'frame_%05d.png'}")


# What `nrhdr demo` writes into its output folder (outputs.staged_folder: --force replaces only these).
DEMO_OUTPUTS = (r"clip/.*", r"exr/frame_\d+\.exr", r"png/frame_\d+\.png")


class _DemoFailed(Exception):
    pass


def _check_demo(a) -> None:
    """ValueError naming the option: a colour demo (--cfa) needs an even size and a colour method."""
    from nrhdr_core import cfa as cfas
    if not cfas.is_colour(a.cfa):
        return
    for opt, v in (("--width", a.width), ("--height", a.height)):
        if v % 2:
            raise ValueError(f"{opt} {v}: a Bayer sensor (--cfa {a.cfa}) has an even width and height (whole "
                             f"2 x 2 blocks)")
    if a.method not in COLOUR_METHODS:
        raise ValueError(f"--method {a.method} works on monochrome clips only; a colour demo (--cfa {a.cfa}) "
                         f"takes --method {' or '.join(COLOUR_METHODS)}")


COLOUR_METHODS = ("fse", "preview")    # nrreconstruct's methods for a mosaic stream that the demo offers


def cmd_demo(a) -> int:
    from nrhdr_core import io, outputs
    _check_demo(a)
    final = Path(a.output).resolve()
    try:   # locked, written aside and renamed in; a stop or failure leaves nothing
        with outputs.staged_folder(final, force=a.force, owned=io.owned_by_patterns(*DEMO_OUTPUTS)) as tmp:
            rc, lines = _run_demo(a, Path(tmp))
            if rc != 0:
                raise _DemoFailed
    except _DemoFailed:
        print(f"nrhdr demo: nothing written to {final}", file=sys.stderr)
        return rc
    for line in lines:
        print(line.replace(str(tmp), str(final)))      # the staging folder is `final` now
    return 0


def _run_demo(a, out: Path):
    """The demo in folder `out` (a staging folder); returns (rc, summary lines)."""
    import numpy as np
    from nrhdr_core import cfa as cfas
    from nrhdr_core import io, metrics, scene, simulate
    from .. import runtime
    for sub in ("exr", "png"):
        (out / sub).mkdir(parents=True, exist_ok=True)
    colour = cfas.is_colour(a.cfa)
    what = f" in colour (Bayer {a.cfa})" if colour else ""
    print(f"nrhdr demo: simulating {a.frames} frames {a.width}x{a.height} of the synthesised HDR scene{what}")
    from nrhdr_core import profile
    if colour:
        prof = profile.default(a.height, a.width, seed=1, cfa=a.cfa)
        sc = simulate.synthetic_rgb_scene()
    else:
        prof = profile.default(a.height, a.width, seed=1)
        sc = scene.synthetic_hdr_scene()
    clip = simulate.simulate_clip(sc, out / "clip", prof, frames=a.frames, fps=30, seed=1)
    clip = simulate.load_clip(out / "clip")
    desc = demo_pipeline(clip, out, a.method, a.preset)
    # the staging folder `out` is gone when the demo ends: its paths are printed only at the end, in `lines`
    print(f"nrhdr demo: running the chain (method={a.method} preset={a.preset})")
    stats = []

    def on_message(msg):
        s = msg.get_structure()
        if s is not None and s.get_name() == "nrhdr-frame-stats":
            stats.append(s.get_value("missing"))

    t0 = time.perf_counter()
    rc = runtime.run_pipeline(desc, on_message=on_message)
    dt = time.perf_counter() - t0
    if rc != 0:
        print("nrhdr demo: stopped by a signal" if rc >= 128 else "nrhdr demo: the pipeline failed",
              file=sys.stderr)
        return rc, []
    exrs = sorted((out / "exr").glob("frame_*.exr"))
    pngs = sorted((out / "png").glob("frame_*.png"))
    # quality against the simulator's ground truth (log domain: HDR-robust), on a few frames
    lp = []
    for f in exrs[:: max(1, len(exrs) // 6)]:
        v, _ = io.read_exr(f)
        truth, _ = io.read_exr(out / "clip" / "truth" / f.name)
        lp.append(metrics.log_psnr(np.minimum(truth, prof.white), v))
    miss = 100.0 * float(np.mean(stats)) if stats else float("nan")
    shell = " ".join(w if w == "!" else shlex.quote(w) for w in desc.split())   # pastes into bash as printed
    kinds = ("RGB PNG, white balance from the profile", "channels R, G, B (camera RGB) + state") if colour else \
        ("PNG", "channels Y + state")
    lines = [f"pipeline: nrhdr launch {shell}",
             f"tone-mapped frames: {out / 'png'}/ ({len(pngs)} {kinds[0]})",
             f"linear HDR frames:  {out / 'exr'}/ ({len(exrs)} OpenEXR, {kinds[1]})",
             f"summary: {len(pngs)} frames in {dt:.1f} s = {len(pngs) / dt:.1f} frames/s (JIT warm-up "
             f"included), {miss:.1f} % of pixels reconstructed, log-domain PSNR vs ground truth "
             f"{np.mean(lp):.1f} dB{' (camera RGB, all three channels)' if colour else ''}"]
    if not (len(pngs) == a.frames == len(exrs)):
        print(f"nrhdr demo: expected {a.frames} frames, the chain wrote {len(pngs)} PNG and {len(exrs)} EXR",
              file=sys.stderr)
        return 1, []
    return 0, lines


def _add_sensor_args(p, profile_opt=True):
    from nrhdr_core.cfa import CFAS, DEFAULT_ND_LAYOUT, ND_LAYOUTS
    g = p.add_argument_group("sensor (ignored with --profile)")
    if profile_opt:
        p.add_argument("--profile", help="existing camera profile JSON to use")
    g.add_argument("--width", type=SIZE, default=640)
    g.add_argument("--height", type=SIZE, default=480)
    g.add_argument("--pattern", choices=("nonregular", "regular", "cell2", "cell2diag", "bluenoise", "voidcluster",
                                         "none"),
                   default=None, help="ND mask: the paper's non-regular (iid) pattern (the default), the regular "
                   "2x2 (Nayar) one, a reduced-randomness design (docs/PAPER.md), or none (an unmodified "
                   "camera with the same sensor, to compare against: nrhdr compare)")
    g.add_argument("--mask-seed", type=SEED, default=0, help="seed of the non-regular mask")
    g.add_argument("--cfa", choices=CFAS, default=None,
                   help="colour filter array: none (monochrome, the default) or a Bayer phase, the colours of "
                        "the top-left 2x2 block (docs/COLOUR.md); width and height must be even; with "
                        "--profile it must be the profile's")
    g.add_argument("--nd-layout", choices=ND_LAYOUTS, default=None,
                   help=f"ND mask over the CFA: independent (--pattern as is), balanced (--pattern on each "
                        f"2x2 colour sub-lattice: half of every colour plane attenuated) or regular (Assorted "
                        f"Pixels: 2x2 blocks clear / ND in a checkerboard); default {DEFAULT_ND_LAYOUT} "
                        f"(docs/SIMULATOR.md)")
    g.add_argument("--nd", type=ND, default=6.35, help="ND factor (Eq. 1), 1..1024")
    g.add_argument("--l-min", type=CODE_LEVEL, default=100.0, help="threshold for attenuated pixels (2.3)")



def add_simulate(sub) -> None:
    p = sub.add_parser("simulate", help="turn an HDR scene into raw sensor video (clip folder)")
    p.add_argument("scene", nargs="?", default="synthetic",
                   help="OpenEXR / Radiance .hdr / PNG scene, or 'synthetic' (default)")
    p.add_argument("-o", "--output", required=True, help="clip folder to write")
    p.add_argument("--frames", type=number(1, 10 ** 6, integer=True), default=60)
    p.add_argument("--fps", type=number(1, 10000, integer=True), default=30)
    p.add_argument("--exposure", type=number(-30, 30), default=0.0,
                   help="stops relative to auto exposure (scene median at 18 %% of the regular range), -30..30")
    p.add_argument("--seed", type=SEED, default=0, help="noise seed")
    p.add_argument("--pan", type=number(-1, 1), default=0.15, help="camera pan, fraction of the scene width")
    p.add_argument("--tilt", type=number(-1, 1), default=0.05, help="camera tilt, fraction of the scene height")
    p.add_argument("--zoom", type=number(0, 100, lo_open=True), default=1.25,
                   help="zoom factor over the clip (1 = none)")
    p.add_argument("--fov", type=number(0, 1, lo_open=True), default=0.8, help="first view's share of the scene")
    g = p.add_argument_group("moving objects and scene cut (docs/SIMULATOR.md)")
    g.add_argument("--objects", type=number(0, 1000, integer=True), default=0,
                   help="objects moving on straight lines over the view, drawn from --seed (default 0: none)")
    g.add_argument("--object-kind", choices=("mixed", "disc", "patch"), default="mixed",
                   help="disc: uniform, alternately bright (24 x the scene median) and dark (median / 32); "
                        "patch: a square of the scene's texture; mixed: patch, bright disc, dark disc in turn")
    g.add_argument("--object-speed", type=number(0, 10000), default=4.0,
                   help="pixels per frame (direction drawn from --seed)")
    g.add_argument("--object-size", type=number(1, 4096), default=48.0,
                   help="diameter of a disc / side of a patch, pixels")
    g.add_argument("--cut-frame", type=number(1, 10 ** 6, integer=True), default=None,
                   help="first frame of a second shot (a scene cut), 1..frames-1")
    g.add_argument("--cut-scene", default=None,
                   help="scene of the second shot (file or 'synthetic'); default: the scene turned by 180 "
                        "degrees")
    p.add_argument("--sensor-model", default="none",
                   help="crosstalk/PRNU/DSNU preset: none or prototype (paper section 3)")
    p.add_argument("--sensor-seed", type=SEED, default=0,
                   help="seed of the sensor model's pixel-to-pixel variation (same as simulate-flats')")
    p.add_argument("--sequence", choices=("png", "tiff"), help="also write 16-bit raw frames")
    p.add_argument("--sensitivity", type=rgb_numbers(1e-3, 1e3), default=None,
                   help="R,G,B: relative sensitivity of a Bayer sensor's colour channels (default 1,1,1); the "
                        "profile written gets the white balance 1/sensitivity, normalised to green")
    p.add_argument("--force", action="store_true",
                   help="replace the clip files in an existing folder (other files there are kept)")
    _add_sensor_args(p)
    add_allow_outside(p)
    p.set_defaults(func=cmd_simulate)


def add_profile(sub) -> None:
    from nrhdr_core.profile import ALIGNMENTS, OUT_OF_RANGE, PACKINGS
    p = sub.add_parser("profile", help="write a camera profile (mask PNG + JSON)")
    p.add_argument("-o", "--output", required=True)
    p.add_argument("--force", action="store_true", help="replace an existing profile (JSON and mask PNG)")
    _add_sensor_args(p, profile_opt=False)
    g = p.add_argument_group("sensor data format (docs/PROFILE.md; defaults: the paper's 12-bit prototype)")
    g.add_argument("--bit-depth", type=number(1, 16, integer=True), default=12, help="ADC bits per code, 1..16")
    g.add_argument("--white-level", type=number(1, 65535, integer=True), default=None,
                   help="code a saturated pixel reads (default: the largest code of the bit depth, 4095 at 12 "
                        "bits); codes >= white level - 1 are clipped")
    g.add_argument("--black-level", type=number(0, 65535), default=0.0, help="code of zero light")
    g.add_argument("--gain", type=number(1e-4, 1e4), default=None, help="DN per electron (noise model)")
    g.add_argument("--alignment", choices=ALIGNMENTS, default="lsb",
                   help="where the code sits in its 16-bit word: lsb (code = word) or msb (code = word >> "
                        "(16 - bit depth))")
    g.add_argument("--packing", choices=tuple(PACKINGS), default="none",
                   help="packed pixel formats arriving as GRAY16_LE bytes (Aravis labels Mono12Packed so), "
                        "unpacked by nrvalidity")
    g.add_argument("--white-balance", type=rgb_numbers(1e-3, 1e3), default=None,
                   help="R,G,B gains that make a grey object grey (a --cfa sensor; default 1,1,1)")
    g.add_argument("--out-of-range", choices=OUT_OF_RANGE, default="clip",
                   help="a code above the bit depth's range: a clipped pixel, or an element error (a stream "
                        "of another bit depth than the profile's)")
    p.set_defaults(func=cmd_profile)


def add_demo(sub) -> None:
    from nrhdr_core.cfa import CFAS
    p = sub.add_parser("demo", help="simulate a clip of a synthesised scene and run the whole chain")
    p.add_argument("-o", "--output", default="demo_out")
    p.add_argument("--cfa", choices=CFAS, default="none",
                   help="none: the monochrome camera (default); a Bayer phase: a colour camera (ND layout "
                        "balanced) filming the synthesised scene in colour, through the colour chain (RGB PNG, "
                        "RGB OpenEXR; --method fse or preview)")
    p.add_argument("--frames", type=number(1, 10 ** 6, integer=True), default=60)
    p.add_argument("--width", type=number(2, 65536, integer=True), default=640)
    p.add_argument("--height", type=number(2, 65536, integer=True), default=480)
    p.add_argument("--method", default="fse", choices=("fse", "linear", "nearest", "preview"))
    p.add_argument("--preset", default="fast", choices=("preview", "fast", "balanced", "best"))
    p.add_argument("--force", action="store_true",
                   help="replace the demo's files (clip/, exr/frame_*, png/frame_*) in an existing folder; "
                        "other files there are kept")
    p.set_defaults(func=cmd_demo)
