"""`nrhdr hdr10`: a raw clip -> HDR10 (PQ) or HLG video for HDR televisions and players, or HDR stills
(docs/HDR-OUTPUT.md). Two passes: the chain (nrhdr_core.chain, as the elements compute it) turns every frame
into BT.2100 10-bit codes (`tonemap.hdr_encode`: diffuse white at the reference white, the BT.2390 EETF to the
mastering peak) and measures MaxCLL / MaxFALL; then x265enc encodes them (HEVC Main 10, BT.2020 / PQ or HLG /
BT.2020 non-constant luminance / limited range, ST 2086 and CTA-861.3 SEI) into MP4 or Matroska. A folder
instead of OUT.mp4 / OUT.mkv gets 16-bit PNG frames with a cICP chunk.

A colour clip (the profile's cfa is a Bayer phase) is reconstructed in colour (`chain.process_frame`:
`demosaic.reconstruct_cfa`), white balanced (--white-balance), converted from BT.709 camera RGB to BT.2020
primaries, encoded per channel (`tonemap.hdr_encode_rgb`) and written as BT.2020 non-constant-luminance Y'CbCr
4:2:0 (`hdr_output.ycbcr_frame`); MaxCLL / MaxFALL from max(R, G, B) per pixel; stills are RGB PNG.

--report decodes the video with ffmpeg and scores it (nrhdr_core.hdr_output.quality_report): grey clips in
display light, colour clips per BT.2020 channel, in luminance and in CIEDE2000 (white: the reference white)."""
from __future__ import annotations

import argparse
import contextlib
import os
import sys
import time
from pathlib import Path

from .args import add_allow_outside, check_clip_cfa, number

EPILOG = """\
examples:
  nrhdr hdr10 demo_out/clip demo.mp4                        # HDR10: PQ, 203 cd/m2 white, 1000 cd/m2 peak
  nrhdr hdr10 demo_out/clip demo.mkv --transfer hlg         # HLG (ARIB STD-B67) in Matroska
  nrhdr hdr10 demo_out/clip stills                          # 16-bit PNG frames with cICP (PQ)
  nrhdr hdr10 demo_out/clip demo.mp4 --crf 12 --speed-preset slow   # transparent, slower
defaults of the chain are pipelines/raw_to_hdr10.sh's (METHOD=fse PRESET=fast MODE=threshold, nrcrosstalk
mode=kernel)."""


def add_hdr10(sub) -> None:
    from nrhdr_core import chain, hdr_output, tonemap
    p = sub.add_parser("hdr10", help="raw clip -> HDR10 / HLG video (HEVC Main 10, MP4 or MKV, with "
                                     "mastering display and content light level) or HDR PNG stills",
                       description=__doc__, epilog=EPILOG, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("input", help="clip folder (clip.json, clip.raw, camera.json) or a GRAY16_LE raw file")
    p.add_argument("output", help="OUT.mp4 or OUT.mkv (video), anything else: a folder of frame_%%05d.png")
    g = p.add_argument_group("input")
    g.add_argument("--profile", help="camera profile JSON (default: the clip's camera.json; required for a "
                                     "raw file)")
    g.add_argument("--frames", type=number(1, 10_000_000, integer=True),
                   help="number of frames (default: all the file holds)")
    g.add_argument("--fps", type=number(1, 1000, integer=True), default=None,
                   help="frame rate (default: the clip's, else 30)")
    g = p.add_argument_group("chain (the elements' properties)")
    g.add_argument("--mode", choices=chain.VALIDITY_MODES, default="threshold", help="nrvalidity mode")
    g.add_argument("--crosstalk", choices=chain.CROSSTALK_MODES, default="kernel", help="nrcrosstalk mode")
    g.add_argument("--method", choices=chain.METHODS, default="fse", help="nrreconstruct method")
    g.add_argument("--preset", choices=chain.PRESETS, default="fast", help="nrreconstruct preset")
    g = p.add_argument_group("display light (nrtonemap transfer=pq|hlg)")
    g.add_argument("--transfer", choices=tonemap.TRANSFERS, default="pq",
                   help="pq: HDR10 (SMPTE ST 2084); hlg: ARIB STD-B67 (no static metadata)")
    g.add_argument("--reference-white", type=number(1, 10000), default=tonemap.REFERENCE_WHITE_NITS,
                   help="cd/m2 of the scene's diffuse white (the regular pixels' white; ITU-R BT.2408: 203)")
    g.add_argument("--exposure", type=number(-20, 20), default=0.0, help="exposure in stops (x 2^exposure)")
    g.add_argument("--white-balance", choices=tonemap.WHITE_BALANCE, default="profile",
                   help="colour clips: the profile's white_balance gains, grey world (the frame's mean colour "
                        "made grey, smoothed over the clip) or none (camera RGB)")
    g.add_argument("--peak", type=number(0, 10000), default=hdr_output.DEFAULT_PEAK,
                   help="mastering display peak in cd/m2: highlights above it are rolled off by the BT.2390 "
                        "EETF (0: no roll-off, PQ clips at 10000)")
    g.add_argument("--min-luminance", type=number(0, 100), default=hdr_output.DEFAULT_MIN_LUMINANCE,
                   help="mastering display black in cd/m2")
    g.add_argument("--primaries", choices=tuple(hdr_output.PRIMARIES), default="bt2020",
                   help="mastering display primaries")
    g.add_argument("--max-cll", type=number(0, 65535, integer=True), default=None,
                   help="MaxCLL in cd/m2 (default: measured over the frames)")
    g.add_argument("--max-fall", type=number(0, 65535, integer=True), default=None,
                   help="MaxFALL in cd/m2 (default: measured over the frames)")
    g = p.add_argument_group("encoder (x265enc)")
    g.add_argument("--crf", type=number(0, 51), default=hdr_output.DEFAULT_CRF,
                   help="x265 constant quality (lower = better and bigger; chosen by measurement, "
                        "docs/BENCHMARKS.md)")
    g.add_argument("--speed-preset", choices=hdr_output.SPEED_PRESETS, default=hdr_output.DEFAULT_SPEED_PRESET,
                   help="x265 speed preset (speed against compression at the same quality)")
    g.add_argument("--x265-options", default="",
                   help="more x265 options, key=value:key=value (e.g. lossless=1)")
    g = p.add_argument_group("output")
    g.add_argument("--force", action="store_true", help="replace an existing OUT (or its PNG frames)")
    g.add_argument("--no-progress", action="store_true", help="no progress bar")
    g.add_argument("--report", action="store_true",
                   help="decode the video with ffmpeg and print its quality against the chain's display light "
                        "and the simulator's truth (PU21-PSNR, log2 PSNR, 10-bit code error; colour: per R, G, B "
                        "and luminance, and CIEDE2000; docs/HDR-OUTPUT.md)")
    add_allow_outside(p)
    p.set_defaults(func=cmd_hdr10)


def _progress(total, enabled, desc):
    from tqdm import tqdm
    return tqdm(total=total, desc=desc, unit="frame", disable=not enabled, dynamic_ncols=True, smoothing=0.1,
                file=sys.stderr)


def _need_elements(Gst, names) -> None:
    missing = [n for n in names if Gst.ElementFactory.find(n) is None]
    if missing:
        raise ValueError(f"GStreamer elements {', '.join(missing)} missing: install gstreamer1.0-plugins-bad "
                         f"(x265enc, h265parse) and gstreamer1.0-plugins-good (mp4mux, matroskamux, capssetter)")


def first_pass(src, prof, settings, a, codes_path, progress, pngs=None, reference=None, gains_used=None):
    """Every frame through the chain and hdr_encode (colour clips: hdr_encode_rgb); codes
    appended to `codes_path` (uint16 << 6; colour: R'G'B' planes), or PNG stills written into `pngs`; returns
    the measured LightLevels. `reference`: a list that gets each frame's display light before quantisation
    (hdr_output.display_reference / display_reference_rgb, float32); `gains_used`: a list that gets each
    colour frame's white-balance gains."""
    import numpy as np
    from nrhdr_core import batch, cfa, chain, hdr_output, io, tonemap
    diffuse, white = float(prof.regular_white), float(prof.white)
    source_peak = tonemap.peak_luminance(white, diffuse, a.transfer, a.reference_white, a.exposure)
    levels = hdr_output.LightLevels(a.transfer)
    colour = cfa.is_colour(getattr(prof, "cfa", "none"))
    out = np.empty(((3,) if colour else ()) + (src.height, src.width), np.uint16)
    wb = getattr(a, "white_balance", "profile")
    grey = tonemap.GreyWorld(0.1, white) if wb == "grey-world" else None
    with _progress(src.frames, progress, "hdr10 pass 1 (chain)") as bar, \
            (open(codes_path, "wb") if codes_path is not None else contextlib.nullcontext()) as f:
        for i in range(src.frames):
            raw = batch.read_frame(src.raw, src.width, src.height, i)
            values, _state = chain.process_frame(raw.copy(), prof, settings)
            if colour:
                gains = (grey.update(values) if grey is not None else
                         tuple(prof.white_balance) if wb == "profile" else (1.0, 1.0, 1.0))
                tonemap.hdr_encode_rgb(values, diffuse, a.transfer, gains, "bt2020", a.reference_white, a.exposure,
                                       out=out, peak=a.peak, source_peak=source_peak)
                if reference is not None:
                    reference.append(hdr_output.display_reference_rgb(
                        values, diffuse, a.transfer, gains, "bt2020", a.reference_white, a.exposure, a.peak,
                        source_peak).astype(np.float32))
                if gains_used is not None:
                    gains_used.append(gains)
            else:
                tonemap.hdr_encode(values, diffuse, a.transfer, reference_white=a.reference_white,
                                   exposure_stops=a.exposure, out=out, peak=a.peak, source_peak=source_peak)
                if reference is not None:
                    reference.append(hdr_output.display_reference(
                        values, diffuse, a.transfer, a.reference_white, a.exposure, a.peak,
                        source_peak).astype(np.float32))
            levels.update(out)
            if pngs is not None:
                sig = hdr_output.full_range16(out)
                io.write_hdr_png(Path(pngs) / f"frame_{i:05d}.png", np.moveaxis(sig, 0, -1) if colour else sig,
                                 a.transfer)
            else:
                f.write(out.tobytes())
            bar.update(1)
    return levels


def encoder_description(a, container: str, levels: tuple[int, int] | None, width: int, height: int,
                        fps: int) -> tuple[str, str]:
    """(appsrc caps, the encoder-to-muxer part of the pipeline) for `a`'s settings."""
    from nrhdr_core import hdr_output
    md = None
    if levels is not None:
        md = hdr_output.MasteringDisplay(a.primaries, a.peak if a.peak > 0 else 10000.0, a.min_luminance)
    caps = hdr_output.encoder_caps(a.transfer, md, levels) + f",width={width},height={height},framerate={fps}/1"
    enc = f"x265enc name=enc speed-preset={a.speed_preset} ! h265parse"
    if container == "mkv":
        if md is not None:   # the muxer stores the luminance / 5: hand it 5x, the SEI keeps the true values
            enc += f' ! capssetter caps="{hdr_output.matroska_caps(md)}"'
        enc += " ! matroskamux"
    else:
        enc += " ! mp4mux"
    return caps, enc


def second_pass(codes_path, src, caps, enc, options, target, progress, colour: bool = False):
    """Encode the codes file into `target` through appsrc ! <enc> ! filesink (x265enc `options`); raises on a
    pipeline error.
    A stop signal (outputs.Interrupted) ends the stream with EOS (the file is closed) and is returned."""
    import numpy as np
    import gi
    gi.require_version("Gst", "1.0")
    gi.require_version("GstVideo", "1.0")
    from gi.repository import Gst, GstVideo
    from nrhdr_core import hdr_output
    Gst.init(None)
    _need_elements(Gst, ["x265enc", "h265parse", "capssetter", "mp4mux", "matroskamux", "appsrc"])
    pipeline = Gst.parse_launch(f"appsrc name=src format=time block=true ! {enc} ! filesink name=sink")
    pipeline.get_by_name("sink").set_property("location", str(target))
    pipeline.get_by_name("enc").set_property("option-string", options)
    appsrc = pipeline.get_by_name("src")
    gcaps = Gst.Caps.from_string(caps)
    appsrc.set_property("caps", gcaps)
    vi = GstVideo.VideoInfo.new_from_caps(gcaps)
    appsrc.set_property("max-bytes", 4 * vi.size)      # block after 4 queued frames
    fps = vi.fps_n / vi.fps_d
    bus = pipeline.get_bus()
    frame = np.empty(vi.size, np.uint8)
    codes = np.memmap(codes_path, np.uint16, "r",
                      shape=(src.frames,) + ((3,) if colour else ()) + (src.height, src.width))
    if pipeline.set_state(Gst.State.PLAYING) == Gst.StateChangeReturn.FAILURE:
        raise ValueError(f"{target}: the encoder pipeline does not start ({enc})")

    def check():
        while True:
            m = bus.pop_filtered(Gst.MessageType.ERROR | Gst.MessageType.EOS)
            if m is None:
                return False
            if m.type == Gst.MessageType.ERROR:
                err, dbg = m.parse_error()
                raise ValueError(f"{target}: {m.src.get_name()}: {err.message}")
            return True

    stopped = None
    try:
        with _progress(src.frames, progress, "hdr10 pass 2 (x265)") as bar:
            try:
                for i in range(src.frames):
                    if colour:
                        hdr_output.ycbcr_frame(codes[i], frame, vi.offset, vi.stride)
                    else:
                        hdr_output.i420_10_frame(codes[i], frame, vi.offset, vi.stride)
                    buf = Gst.Buffer.new_wrapped(frame.tobytes())
                    buf.pts = int(round(i * Gst.SECOND / fps))
                    buf.duration = int(round(Gst.SECOND / fps))
                    if appsrc.emit("push-buffer", buf) != Gst.FlowReturn.OK:
                        check()
                        raise ValueError(f"{target}: the encoder refused frame {i}")
                    check()
                    bar.update(1)
            except KeyboardInterrupt as e:      # a stop: end the stream, so the file is closed and plays
                stopped = e
            appsrc.emit("end-of-stream")
            while True:
                m = bus.timed_pop_filtered(Gst.SECOND, Gst.MessageType.ERROR | Gst.MessageType.EOS)
                if m is None:
                    continue
                if m.type == Gst.MessageType.ERROR:
                    err, _ = m.parse_error()
                    raise ValueError(f"{target}: {m.src.get_name()}: {err.message}")
                break
    finally:
        pipeline.set_state(Gst.State.NULL)
        del codes
    return stopped


def cmd_hdr10(a) -> int:
    import numpy as np
    from nrhdr_core import batch, cfa, chain, hdr_output, io, outputs, profile, simulate
    from nrhdr_core.tonemap import HLG_NOMINAL_PEAK
    out = Path(a.output)
    container = hdr_output.container_of(out)
    if a.transfer == "hlg" and a.peak > HLG_NOMINAL_PEAK:
        raise ValueError(f"--peak {a.peak:g}: HLG's reference display peaks at {HLG_NOMINAL_PEAK:g} cd/m2")
    if a.max_cll is not None and a.max_fall is not None:
        hdr_output.content_light_caps_field(a.max_cll, a.max_fall)      # MaxFALL <= MaxCLL, before any work
    src = batch.open_source(a.input, a.profile, frames=a.frames, allow_outside=a.allow_outside_paths)
    prof = profile.load(src.profile, allow_outside=a.allow_outside_paths)
    if (prof.width, prof.height) != (src.width, src.height):
        raise ValueError(f"{src.profile}: a {prof.width}x{prof.height} profile for {src.width}x{src.height} frames")
    if a.profile:
        check_clip_cfa(a.input, prof)
    colour = cfa.is_colour(getattr(prof, "cfa", "none"))
    if a.report:
        if container is None:
            raise ValueError(f"--report scores a video decoded by ffmpeg; {out} names a folder of PNG stills "
                             f"(give OUT.mp4 or OUT.mkv)")
        need_ffmpeg()
    fps = a.fps
    if fps is None:
        fps = 30
        if Path(a.input).is_dir():
            fps = int(simulate.load_clip(Path(a.input), allow_outside=a.allow_outside_paths).get("fps", 30))
    settings = chain.ChainSettings(mode=a.mode, crosstalk=a.crosstalk, method=a.method, preset=a.preset)
    if colour:
        chain.check_colour(settings, prof.cfa)
    if container is not None:
        hdr_output.check_encode_size(src.width, src.height, f"{out}")
    progress = not a.no_progress
    with outputs.stop_on_signals(ends_process=True):
        if container is None:       # HDR stills
            owned = io.owned_by_patterns(r"frame_\d{5}\.png")
            with outputs.staged_folder(out, force=a.force, owned=owned) as stage:
                levels = first_pass(src, prof, settings, a, None, progress, pngs=stage)
            print(f"nrhdr hdr10: {src.frames} frames -> {out}/frame_NNNNN.png (16-bit{' RGB' if colour else ''}, "
                  f"cICP BT.2020/{a.transfer.upper()}, full range); MaxCLL {levels.max_cll}, MaxFALL "
                  f"{levels.max_fall_int} cd/m2")
            return 0
        with outputs.lock(out):
            outputs.remove_leftovers(out)
            if os.path.lexists(out) and not a.force:
                io.refuse_existing([out])
            codes = outputs.temp_path(out, ".codes")
            part = Path(f"{out}.part")             # the video being encoded (the lock is ours)
            try:
                reference, gains = ([], []) if a.report else (None, None)
                levels = first_pass(src, prof, settings, a, codes, progress, reference=reference, gains_used=gains)
                if a.report:
                    quantised = np.fromfile(codes, np.uint16).reshape(
                        (src.frames,) + ((3,) if colour else ()) + (src.height, src.width)) >> 6
                cll = levels.values()
                if a.max_cll is not None or a.max_fall is not None:
                    cll = (a.max_cll if a.max_cll is not None else cll[0],
                           a.max_fall if a.max_fall is not None else cll[1])
                meta = cll if a.transfer == "pq" else None
                caps, enc = encoder_description(a, container, meta, src.width, src.height, fps)
                t0, c0 = time.perf_counter(), time.process_time()
                options = f"crf={a.crf:g}" + (f":{a.x265_options}" if a.x265_options else "")
                stopped = second_pass(codes, src, caps, enc, options, part, progress, colour)
                enc_s, enc_cpu = time.perf_counter() - t0, time.process_time() - c0
                os.replace(part, out)           # complete, or closed by EOS after a stop: it plays
                if stopped is not None:
                    raise stopped
            finally:
                Path(codes).unlink(missing_ok=True)
                part.unlink(missing_ok=True)
    size = out.stat().st_size
    secs = src.frames / fps
    kbps = size * 8 / secs / 1000
    bpp = size * 8 / (src.frames * src.width * src.height)
    meta_text = (f"MaxCLL {cll[0]}, MaxFALL {cll[1]} cd/m2, mastering {a.peak:g}/{a.min_luminance:g} cd/m2"
                 if a.transfer == "pq" else "HLG: no static metadata")
    print(f"nrhdr hdr10: {src.frames} frames {src.width}x{src.height} -> {out} (HEVC Main 10, "
          f"{a.transfer.upper()}, crf {a.crf:g}, {a.speed_preset}): {kbps:.0f} kbit/s, {bpp:.4f} bit/pixel; "
          f"{meta_text}; encoded at {src.frames / enc_s:.2f} frames/s ({enc_cpu / src.frames:.3f} CPU s per frame)")
    if a.report:
        print_report(quality(a, src, prof, out, reference, gains, quantised, colour), a.reference_white)
    return 0


def need_ffmpeg() -> None:
    """--report decodes the video with ffmpeg: refused before any work when it is not installed."""
    import shutil
    if shutil.which("ffmpeg") is None:
        raise ValueError("--report decodes the video with ffmpeg, which is not installed (Debian: ffmpeg)")


def decode_planes(path, width: int, height: int):
    """(Y', Cb, Cr) code planes of a 10-bit 4:2:0 video decoded by ffmpeg (yuv420p10le: the codes as coded):
    (N, H, W) and (N, ceil(H/2), ceil(W/2)) twice."""
    import subprocess
    import numpy as np
    need_ffmpeg()
    raw = subprocess.run(["ffmpeg", "-v", "error", "-i", str(path), "-f", "rawvideo", "-pix_fmt", "yuv420p10le",
                          "-"], capture_output=True, check=True).stdout
    cw, ch = (width + 1) // 2, (height + 1) // 2
    n = width * height
    frames = np.frombuffer(raw, "<u2").reshape(-1, n + 2 * cw * ch)
    return (frames[:, :n].reshape(-1, height, width), frames[:, n:n + cw * ch].reshape(-1, ch, cw),
            frames[:, n + cw * ch:].reshape(-1, ch, cw))


def quality(a, src, prof, out, reference, gains, quantised, colour: bool) -> list:
    """The --report figures (hdr_output.quality_report) as sections [(title, [(row, report)])]: the 10-bit codes
    (colour: also the 4:2:0 Y'CbCr the encoder was given, as a player converts it back) and ffmpeg's decode of
    `out` against the chain's display light before quantisation (`reference`); with the simulator's truth, the
    chain and the decode against the truth through the same mapping (colour: each frame's `gains`)."""
    import numpy as np
    from nrhdr_core import hdr_output
    ref = np.stack(reference)
    y, cb, cr = decode_planes(out, src.width, src.height)
    if len(y) != len(ref):
        raise ValueError(f"{out}: the decoded video has {len(y)} frames, the clip {len(ref)}")

    def light(codes):
        return hdr_output.code_light(codes, a.transfer)

    if colour:      # code values (float32), each row's light computed when it is scored
        sent = np.stack([hdr_output.rgb_from_ycbcr420(*hdr_output.ycbcr420_planes(q, shift=0)).astype(np.float32)
                         for q in quantised])
        decoded = np.stack([hdr_output.rgb_from_ycbcr420(*p).astype(np.float32) for p in zip(y, cb, cr)])
        rows = [("10-bit R'G'B'", quantised), ("4:2:0 Y'CbCr", sent), ("decoded", decoded)]
    else:
        rows = [("10-bit codes", quantised), ("decoded", y)]

    def score(r, t):
        return hdr_output.quality_report(r, t, a.transfer, a.reference_white)

    sections = [("against the chain's display light before quantisation",
                 [(n, score(ref, light(c))) for n, c in rows])]
    truth = truth_reference(a, src, prof, gains if colour else None)
    if truth is not None:
        sections.append(("against the simulator's truth through the same mapping",
                         [("the chain", score(truth, ref)), ("decoded", score(truth, light(rows[-1][1])))]))
    return sections


def print_report(sections, reference_white: float) -> None:
    """The --report lines: per row and channel (R, G, B, luminance Y; grey clips: Y) PU21-PSNR / log2 PSNR of
    the display light and the error of the 10-bit code values; colour: CIEDE2000."""
    print("nrhdr hdr10 --report: PU21-PSNR / log2 PSNR (dB) of the display light (cd/m2; colour: BT.2020 R, G, "
          "B and luminance Y); error of the 10-bit code values mean / mean |e| / max |e|")
    for title, rows in sections:
        print(f"{title}:")
        for name, rep in rows:
            for ch in ("R", "G", "B", "Y"):
                if ch in rep:
                    s = rep[ch]
                    print(f"  {name:<14} {ch}  {s['pu21_psnr']:6.2f} / {s['log2_psnr']:6.2f} dB   code error "
                          f"{s['code_error_mean']:+.3f} / {s['code_error_abs_mean']:.3f} / "
                          f"{s['code_error_abs_max']:.3f}")
            de = rep.get("ciede2000")
            if de is not None:
                text = ("no pixel" if de["mean"] is None else
                        f"mean {de['mean']:.3f}, 95th percentile {de['p95']:.3f} over {100 * de['share']:.1f} % of "
                        f"the pixels")
                print(f"  {name:<14} CIEDE2000 {text} (luminance at most the reference white "
                      f"{reference_white:g} cd/m2, its CIELAB white)")


def truth_reference(a, src, prof, gains=None):
    """The display light of the simulator's truth frames (clip.json `truth`) through the same mapping
    (colour: `gains`, each frame's white balance), or None when the input has none."""
    import json
    import numpy as np
    from nrhdr_core import hdr_output, io, tonemap
    cj = Path(a.input) / "clip.json"
    if not cj.is_file():
        return None
    pattern = json.loads(cj.read_text()).get("truth")
    if not pattern:
        return None
    diffuse, white = float(prof.regular_white), float(prof.white)
    source_peak = tonemap.peak_luminance(white, diffuse, a.transfer, a.reference_white, a.exposure)
    out = []
    for i in range(src.frames):
        f = Path(a.input) / (pattern % i)
        if not f.is_file():
            return None
        v, _ = io.read_exr(f, shape=(src.height, src.width))
        if (v.ndim == 3) != (gains is not None):
            raise ValueError(f"{f}: a {'colour' if v.ndim == 3 else 'grey'} truth frame for a "
                             f"{'colour' if gains is not None else 'monochrome'} profile ({src.profile})")
        if gains is not None:
            out.append(hdr_output.display_reference_rgb(v, diffuse, a.transfer, gains[i], "bt2020",
                                                        a.reference_white, a.exposure, a.peak, source_peak))
        else:
            out.append(hdr_output.display_reference(v, diffuse, a.transfer, a.reference_white, a.exposure, a.peak,
                                                    source_peak))
    return np.asarray(out, np.float32) if out else None
