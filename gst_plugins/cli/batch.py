"""`nrhdr batch`: reprocess recorded raw clips or raw still sequences into an OpenEXR sequence (Y + state; a
colour profile: R, G, B + state), frame-parallel on Dask, or in chunks of consecutive frames with the temporal
reconstruction (nrhdr_core.batch; docs/BATCH.md). Exit status: 0 all frames written, 1 some frames failed (each
reported by number and file), 2 bad input or a refused output folder, 130 interrupted."""
from __future__ import annotations

import argparse
import sys

from .args import add_allow_outside, check_clip_cfa, number

EPILOG = """\
examples:
  nrhdr batch demo_out/clip -o demo_out/exr                      # one worker per core, fse fast
  nrhdr batch demo_out/clip -o best --preset best --png          # final quality + tone-mapped PNGs
  nrhdr batch rec.raw --profile camera.json -o out --workers 0   # plain loop in this process
  nrhdr batch stills --profile camera.json -o out                # a folder of 16-bit gray TIFF/PNG stills
  nrhdr batch demo_out/clip -o out --scheduler tcp://host:8786   # an existing Dask cluster
  nrhdr batch demo_out/clip -o out --temporal on --chunk 64 --overlap 8   # temporal, chunks of 64 frames
defaults are pipelines/raw_to_exr.sh's (METHOD=fse PRESET=fast MODE=threshold, nrcrosstalk mode=kernel),
so the files equal that pipeline's bit for bit."""


def add_batch(sub) -> None:
    from nrhdr_core import batch, chain
    p = sub.add_parser("batch", help="reprocess a raw clip into OpenEXR frames on a Dask cluster",
                       description=__doc__, epilog=EPILOG, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("input", help="clip folder (clip.json, clip.raw, camera.json), a GRAY16_LE raw file, or a "
                                 "raw still sequence: a folder of 16-bit gray .tif/.tiff/.png files or a "
                                 "pattern such as stills/frame_%%05d.tif (as nrimagesrc reads it)")
    p.add_argument("-o", "--output", required=True, help="output folder: frame_%%05d.exr (+ .png), batch.json")
    g = p.add_argument_group("input")
    g.add_argument("--profile", help="camera profile JSON (default: the clip's camera.json, or a still "
                                     "sequence folder's camera.json; required for a raw file)")
    g.add_argument("--width", type=number(1, 1 << 16, integer=True),
                   help="frame width of a raw file (default: the profile's mask)")
    g.add_argument("--height", type=number(1, 1 << 16, integer=True),
                   help="frame height of a raw file (default: the profile's mask)")
    g.add_argument("--frames", type=number(1, 10_000_000, integer=True),
                   help="number of frames (default: all the file holds)")
    g.add_argument("--start-index", type=number(0, 2147483647, integer=True), default=-1,
                   help="still pattern: index of the first file (default: the lowest present; nrimagesrc "
                        "start-index)")
    g = p.add_argument_group("chain (the elements' properties)")
    g.add_argument("--mode", choices=chain.VALIDITY_MODES, default="threshold", help="nrvalidity mode")
    g.add_argument("--dark-policy", choices=chain.DARK_POLICIES, default="weighted",
                   help="nrvalidity dark-policy (weighted: noisy dark attenuated pixels kept and fused; threshold: "
                        "the paper's hard l_min)")
    g.add_argument("--l-min", type=number(0, 1e9), default=None, help="nrvalidity l-min (default: the profile's)")
    g.add_argument("--crosstalk", choices=chain.CROSSTALK_MODES, default="kernel", help="nrcrosstalk mode")
    g.add_argument("--crosstalk-lut", choices=("compact", "full"), default="compact",
                   help="nrcrosstalk lut (mode=lut): compact = fast, full = the calibration's table (accurate)")
    g.add_argument("--crosstalk-profile", help="profile whose crosstalk calibration to apply (nrcrosstalk "
                                               "profile=; default: the camera profile's)")
    g.add_argument("--method", choices=chain.METHODS, default="fse", help="nrreconstruct method")
    g.add_argument("--preset", choices=chain.PRESETS, default="fast",
                   help="nrreconstruct preset (default fast, as raw_to_exr.sh; 'best' for final quality)")
    g.add_argument("--noise-fusion", choices=("auto", "accurate", "fast"), default="auto",
                   help="nrreconstruct noise-fusion (NOISY pixels: auto = fast for preview, accurate for the "
                        "others; or accurate, fast)")
    g.add_argument("--no-bounds", action="store_true", help="nrreconstruct use-bounds=false")
    g.add_argument("--temporal", choices=chain.TEMPORAL_MODES, default="off",
                   help="nrreconstruct temporal (on: the previous frames as a prior; frames are computed in "
                        "chunks of consecutive frames, see --chunk, --overlap)")
    g.add_argument("--temporal-budget", type=number(0, chain.MAX_TEMPORAL_BUDGET, integer=True), default=None,
                   help=f"nrreconstruct temporal-budget: blocks' worth of FSE work a frame that refines a still "
                        f"shot after its preview start (default {chain.TEMPORAL_BUDGET}; 0 = no bound; "
                        f"docs/TEMPORAL.md)")
    g.add_argument("--png", action="store_true",
                   help="also write tone-mapped GRAY8 PNGs (nrtonemap; monochrome clips)")
    g.add_argument("--operator", choices=chain.SDR_OPERATORS, default="local",
                   help="nrtonemap operator of the PNGs (docs/TONEMAP.md); local: each frame's own statistics "
                        "(the element smooths them over the stream)")
    g.add_argument("--exposure", type=number(-30, 30), default=0.0, help="nrtonemap exposure in stops")
    g.add_argument("--contrast", type=number(1, 1e12, lo_open=True), default=1000.0, help="nrtonemap contrast")
    g.add_argument("--white", type=number(0, 1e12, lo_open=True), default=None,
                   help="nrtonemap white (default: the profile's)")
    g = p.add_argument_group("temporal chunks (--temporal on)")
    g.add_argument("--chunk", type=number(1, 10_000_000, integer=True), default=None,
                   help=f"frames per chunk: a chunk is one task, computed and resumed whole (default "
                        f"{batch.DEFAULT_CHUNK})")
    g.add_argument("--overlap", type=number(0, 10_000_000, integer=True), default=None,
                   help=f"frames before a chunk that warm its temporal state up, computed and not written "
                        f"(default {batch.DEFAULT_OVERLAP}; docs/BATCH.md says how they change a chunk's first "
                        f"frames)")
    g = p.add_argument_group("execution")
    g.add_argument("--workers", type=number(0, 4096, integer=True), default=None,
                   help="local worker processes (default: one per core); 0 = plain loop in this process")
    g.add_argument("--threads-per-worker", type=number(1, 4096, integer=True), default=1,
                   help="numba threads per local worker (default 1; keep workers x threads = cores)")
    g.add_argument("--scheduler", help="address of an existing Dask scheduler (tcp://host:8786) instead of "
                                       "a local cluster")
    g.add_argument("--transfer", choices=("files", "data"), default="files",
                   help="files: workers read the raw file and write the outputs (shared file system, "
                        "default); data: this process sends raw frames and writes the files workers return")
    g.add_argument("--force", action="store_true",
                   help="recompute into a folder holding other settings' or another program's output")
    g.add_argument("--no-progress", action="store_true", help="no progress bar")
    add_allow_outside(p)
    p.set_defaults(func=cmd_batch)


def cmd_batch(a) -> int:
    from nrhdr_core import batch, outputs
    if a.scheduler and a.workers is not None:
        raise ValueError("--workers starts a local cluster; it cannot go with --scheduler")
    if a.temporal != "on" and (a.chunk is not None or a.overlap is not None):
        raise ValueError(f"{'--chunk' if a.chunk is not None else '--overlap'} is for the temporal "
                         f"reconstruction's chunks: add --temporal on (without it every frame is computed alone)")
    if a.temporal != "on" and a.temporal_budget is not None:
        raise ValueError("--temporal-budget bounds the temporal reconstruction's refinement: add --temporal on")
    from nrhdr_core import chain, profile
    settings = chain.ChainSettings(mode=a.mode, l_min=a.l_min, dark_policy=a.dark_policy, crosstalk=a.crosstalk,
                                   crosstalk_lut=a.crosstalk_lut, method=a.method,
                                   preset=a.preset, use_bounds=not a.no_bounds, noise_fusion=a.noise_fusion,
                                   temporal=a.temporal, operator=a.operator, white=a.white, exposure=a.exposure,
                                   contrast=a.contrast,
                                   temporal_budget=(chain.TEMPORAL_BUDGET if a.temporal_budget is None
                                                    else a.temporal_budget))
    src = batch.open_source(a.input, a.profile, a.width, a.height, a.frames, allow_outside=a.allow_outside_paths,
                            start_index=a.start_index)
    job = batch.Job(src, a.output, settings, png=a.png, crosstalk_profile=a.crosstalk_profile,
                    allow_outside=a.allow_outside_paths,
                    chunk=batch.DEFAULT_CHUNK if a.chunk is None else a.chunk,
                    overlap=batch.DEFAULT_OVERLAP if a.overlap is None else a.overlap)
    if a.profile:
        check_clip_cfa(a.input, job.profile)
    if job.profile.cfa != "none":    # a colour mosaic: refuse what the colour chain does not do before any frame
        chain.check_colour(settings, job.profile.cfa)
        if a.png:
            raise ValueError(f"--png writes GRAY8 PNGs of monochrome frames; {job.profile.path} is a colour "
                             f"profile (cfa {job.profile.cfa}): the EXR frames are RGB, tone map them with "
                             f"nrtonemap (docs/COLOUR.md)")
    if job.xt_profile is not None:   # another sensor's calibration would correct the wrong pixels
        profile.check_same_sensor(job.xt_profile, job.profile)
        if job.xt_profile.cfa != job.profile.cfa:
            raise ValueError(f"--crosstalk-profile {job.xt_profile.path}: cfa {job.xt_profile.cfa!r}, but the "
                             f"stream's profile {job.profile.path} has cfa {job.profile.cfa!r}: crosstalk "
                             f"calibrated for another colour filter array")
    # the stop signals raise outputs.Interrupted once (later ones are ignored, so the clean-up is not
    # broken off); the lock refuses a second run into the same folder
    with outputs.stop_on_signals(ends_process=True), outputs.lock(job.out_dir):
        return _run(a, batch, job, settings)


def _run(a, batch, job, settings) -> int:
    from nrhdr_core import outputs
    src = job.source
    todo, skipped = batch.prepare_output(job, force=a.force)
    progress = not a.no_progress
    chunks = (f" in {len(job.chunks(todo))} chunks of {job.chunk} frames (overlap {job.overlap})"
              if job.temporal else "")
    print(f"nrhdr batch: {src.frames} frames {src.width}x{src.height} from {src.raw}, {skipped} already done, "
          f"{len(todo)} to compute{chunks}; method={settings.method} preset={settings.preset} "
          f"temporal={settings.temporal} -> {job.out_dir}", file=sys.stderr)

    def on_failure(f, bar):
        bar.write(f"nrhdr batch: error: {f}", file=sys.stderr)

    res = None
    try:
        if not todo:
            res = batch.Result(skipped=skipped)
        elif a.workers == 0:
            res = batch.run_loop(job, todo, progress=progress, on_failure=on_failure)
        elif a.scheduler:
            from distributed import Client
            with Client(a.scheduler, timeout="30s") as client:
                for w in batch.oversubscription_warnings(client):
                    print(f"nrhdr batch: warning: oversubscribed: {w}", file=sys.stderr)
                res = batch.run_dask(job, todo, client, progress=progress, return_files=a.transfer == "data",
                                     on_failure=on_failure)
        else:
            n = a.workers or batch.usable_cores()
            if n * a.threads_per_worker > batch.usable_cores():
                print(f"nrhdr batch: warning: oversubscribed: {n} workers x {a.threads_per_worker} numba "
                      f"threads > {batch.usable_cores()} cores (docs/BATCH.md)", file=sys.stderr)
            with batch.local_client(a.workers, a.threads_per_worker) as client:
                res = batch.run_dask(job, todo, client, progress=progress, return_files=a.transfer == "data",
                                     on_failure=on_failure)
    except KeyboardInterrupt as e:
        if not a.scheduler:   # remote workers may still finish a frame; the next run cleans up
            batch.remove_stage(job)
        print(f"nrhdr batch: interrupted; the complete frames in {job.out_dir} are kept, rerun the same "
              f"command to resume", file=sys.stderr)
        return 128 + e.signum if isinstance(e, outputs.Interrupted) else 130
    batch.remove_stage(job)       # every task has ended
    res.skipped = skipped
    fps = f", {res.fps:.2f} frames/s" if res.done else ""
    print(f"nrhdr batch: wrote {len(res.done)} frames, skipped {skipped} done, {len(res.failures)} failed "
          f"in {res.seconds:.1f} s{fps}", file=sys.stderr)
    if res.failures:
        for f in sorted(res.failures, key=lambda f: f.index):
            print(f"nrhdr batch: failed: {f}", file=sys.stderr)
        return 1
    return 0


def add_recover(sub) -> None:
    p = sub.add_parser("recover", help="finish a raw recording left by a killed recorder (SIGKILL, power loss)",
                       description="Finish the recording that pipelines/live_record_and_preview.sh left in "
                                   "OUT_DIR when it was killed (.clip.raw.part): cut to whole frames, renamed "
                                   "clip.raw, clip.json written, so OUT_DIR is a clip folder again (nrhdr batch, "
                                   "pipelines/raw_to_exr.sh). Refused while the recorder still runs.")
    p.add_argument("folder", help="the recording's output folder (OUT_DIR)")
    p.add_argument("--lock-held", action="store_true", help=argparse.SUPPRESS)   # the recorder, holding the lock
    p.set_defaults(func=cmd_recover)


def cmd_recover(a) -> int:
    from nrhdr_core import outputs
    text = outputs.complete_recording(a.folder) if a.lock_held else outputs.recover(a.folder)
    print(text or f"nrhdr recover: {a.folder}: no unfinished recording (no {outputs.RECORDING_PART})")
    return 0
