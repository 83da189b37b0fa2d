"""Batch reprocessing of recorded raw clips and raw still sequences, parallel on Dask (dask.distributed);
docs/BATCH.md.

Every frame goes through `chain.process_frame` (the elements' own core calls, so the output equals the
GStreamer chain's bit for bit) and is written with `io.write_exr(path, values, state)` (nrexrsink's writer)
into the run's stage folder `OUT/.frames.nrtmp-<run id>` and renamed into OUT, so a file with its final name
is complete. The unit of work (a Dask task) and of resume is a `Chunk`: one frame, or with the temporal
reconstruction (settings.temporal "on") `Job.chunk` consecutive frames through one
`temporal.TemporalReconstructor`, warmed up on the `Job.overlap` frames before the chunk (processed, not
written). The output folder is locked for the run (`outputs.lock`: a second run into it is refused) and
gets a manifest (`batch.json`) with the input's identity and the settings: a rerun with the same settings
skips the frames whose files exist and removes the stage folders of killed runs (only `.nrtmp-` names), a
rerun with other settings or into a folder written by something else refuses unless forced. A frame that
fails (e.g. the truncated last frame of a raw file) is reported by number and file; the others are still
written.

Oversubscription rule: workers x numba threads per worker = cores (default: one single-threaded worker
process per core, numba pinned to 1 thread through NUMBA_NUM_THREADS before the worker starts).
"""
from __future__ import annotations

import contextlib
import dataclasses
import hashlib
import json
import os
import shutil
import tempfile
import time
from pathlib import Path

import numpy as np

from . import chain, io, outputs

MANIFEST = "batch.json"
MANIFEST_FORMAT = "nrhdr-batch"
DEFAULT_CHUNK = 32                  # --temporal on: frames per chunk (one task; docs/BATCH.md)
DEFAULT_OVERLAP = 8                 # ... and warm-up frames before each chunk
EXR_NAME = "frame_{:05d}.exr"       # nrexrsink location=OUT/frame_%05d.exr
PNG_NAME = "frame_{:05d}.png"       # pipelines/raw_to_png.sh names


class BatchError(ValueError):
    """Bad input or an output folder the batch must not touch; the message names the file or folder."""


def usable_cores() -> int:
    """Cores this process may run on (the affinity mask, not the machine's count)."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except (AttributeError, OSError):
        return max(1, os.cpu_count() or 1)


# ---- input ------------------------------------------------------------------------------------------

@dataclasses.dataclass(frozen=True)
class Source:
    """A GRAY16_LE raw file: `frames` frames of width x height (frames past the file's end, or a partial
    last frame, fail when read); or, with `stills`, a raw still sequence (`raw`: its folder or pattern),
    the first `frames` of its files."""
    raw: Path
    width: int
    height: int
    frames: int
    profile: Path
    stills: io.StillSequence | None = None

    @property
    def frame_bytes(self) -> int:
        return 2 * self.width * self.height

    def read(self, index: int) -> np.ndarray:
        """Frame `index` as uint16 (H, W): nrimagesrc's frame of a still sequence, rawvideoparse's of a
        raw file; errors name the file."""
        if self.stills is not None:
            return self.stills.read(index)
        return read_frame(self.raw, self.width, self.height, index)

    def frame_file(self, index: int) -> str:
        """The file frame `index` comes from (for error reports)."""
        if self.stills is not None and 0 <= index < len(self.stills):
            return self.stills.files[index]
        return str(self.raw)


def open_source(path, profile=None, width=None, height=None, frames=None, allow_outside: bool = False,
                start_index: int = -1) -> Source:
    """A clip folder (clip.json + clip.raw + camera.json, from `nrhdr simulate`), a raw file with a
    profile, or a raw still sequence (`open_stills`). Geometry: the clip's, else width/height given, else
    the profile's mask. Frame count: every frame the file holds (a partial last one included, so it is
    reported), at least the clip's count. The files clip.json names must lie in the clip folder unless
    `allow_outside` (simulate.load_clip): a clip folder received from someone else cannot make batch read a
    file from elsewhere."""
    p = Path(path)
    clip_frames = 0
    if "%" in p.name and not p.exists() or p.is_dir() and not (p / "clip.json").is_file():
        if (p / outputs.RECORDING_PART).is_file():
            raise BatchError(f"{p}: an unfinished recording ({outputs.RECORDING_PART}, its recorder was "
                             f"killed): make it a clip folder with 'nrhdr recover {p}' first")
        return open_stills(p, profile, width, height, frames, allow_outside, start_index)
    if start_index >= 0:
        raise BatchError(f"--start-index is for a still sequence's file pattern, not {p}")
    if p.is_dir():
        cj = p / "clip.json"
        from . import simulate
        try:
            c = simulate.load_clip(p, allow_outside=allow_outside)
        except simulate.ClipError as e:
            raise BatchError(str(e)) from None
        w, h, clip_frames = c["width"], c["height"], c["frames"]
        raw = Path(c["raw_path"])
        prof = Path(profile) if profile else Path(c["profile_path"])
        if width is not None and int(width) != w or height is not None and int(height) != h:
            raise BatchError(f"{cj} says {w}x{h}; --width/--height {width}x{height} disagree")
    elif p.is_file():
        if not profile:
            raise BatchError(f"{p}: a raw file needs --profile (the camera profile JSON)")
        raw, prof = p, Path(profile)
        w = h = None
        if width is not None or height is not None:
            if width is None or height is None:
                raise BatchError("give both --width and --height (or neither: the profile's mask size)")
            w, h = int(width), int(height)
    else:
        raise BatchError(f"{p}: no such clip folder or raw file")
    if not prof.is_file():
        raise BatchError(f"camera profile {prof} not found")
    if w is None:
        from . import profile as profile_mod
        pm = profile_mod.load(prof, allow_outside=allow_outside)
        w, h = pm.width, pm.height
    if w < 1 or h < 1:
        raise BatchError(f"frame size must be positive, got {w}x{h}")
    if not raw.is_file():
        raise BatchError(f"raw video {raw} not found")
    size = raw.stat().st_size
    fb = 2 * w * h
    in_file = -(-size // fb)  # whole frames + a partial one
    n = int(frames) if frames is not None else max(in_file, clip_frames)
    if n < 1:
        raise BatchError(f"{raw}: no frames ({size} bytes, {w}x{h} GRAY16_LE frames are {fb} bytes)")
    return Source(raw=raw.resolve(), width=w, height=h, frames=n, profile=prof.resolve())


def open_stills(location, profile=None, width=None, height=None, frames=None, allow_outside: bool = False,
                start_index: int = -1) -> Source:
    """A raw still sequence (a folder of 16-bit gray TIFF / PNG files or a printf pattern, read as nrimagesrc
    reads it: `io.still_sequence`, every header checked here) with its camera profile: `profile`, else the
    folder's camera.json. `frames`: the first that many files; width/height, when given, must be the
    files'."""
    loc = Path(location)
    if loc.is_dir() and not any(os.path.splitext(n)[1].lower() in io.STILL_EXTENSIONS for n in os.listdir(loc)):
        raise BatchError(f"{loc}: not a clip folder (no clip.json) nor a still sequence (no "
                         f"{', '.join(io.STILL_EXTENSIONS)} files); give a clip folder from 'nrhdr simulate', a "
                         f"raw file with --profile, or a folder of 16-bit gray stills")
    try:
        seq = io.still_sequence(loc, start_index, allow_outside=allow_outside)
    except io.ImageFileError as e:
        raise BatchError(str(e)) from None
    folder = loc if loc.is_dir() else loc.parent
    prof = Path(profile) if profile else folder / "camera.json"
    if not prof.is_file():
        raise BatchError(f"{loc}: a still sequence needs its camera profile: --profile FILE (or a camera.json "
                         f"in the folder)" if not profile else f"camera profile {prof} not found")
    if (width is not None and int(width) != seq.width) or (height is not None and int(height) != seq.height):
        raise BatchError(f"{loc}: the stills are {seq.width}x{seq.height}; --width/--height {width}x{height} "
                         f"disagree")
    n = len(seq)
    if frames is not None:
        if int(frames) > n:
            raise BatchError(f"{loc}: --frames {frames} but the sequence has {n} files")
        n = int(frames)
    return Source(raw=Path(os.path.abspath(loc)), width=seq.width, height=seq.height, frames=n,
                  profile=prof.resolve(), stills=seq)


def read_frame(raw, width: int, height: int, index: int) -> np.ndarray:
    """Frame `index` of a GRAY16_LE file as uint16 (H, W); a missing or partial frame is an error naming
    the file and the frame."""
    from .io import ImageFileError
    fb = 2 * width * height
    with open(raw, "rb") as f:
        size = os.fstat(f.fileno()).st_size
        f.seek(index * fb)
        data = f.read(fb)
    if len(data) != fb:
        whole, rest = divmod(size, fb)
        what = (f"truncated: {len(data)} of {fb} bytes" if data else "missing: the file ends before it")
        raise ImageFileError(f"{raw}: frame {index} is {what} (the file is {size} bytes = {whole} whole "
                             f"{width}x{height} GRAY16_LE frames + {rest} bytes)")
    return np.frombuffer(data, dtype="<u2").reshape(height, width).astype(np.uint16, copy=False)


# ---- job, manifest, output folder ----------------------------------------------------------------------

def _file_id(path: Path) -> dict:
    st = path.stat()
    return {"path": str(path), "size": st.st_size, "mtime_ns": st.st_mtime_ns}


def _sha256(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


@dataclasses.dataclass(frozen=True)
class Chunk:
    """The unit of work and of resume: frames start..stop-1 are computed in order through one chain and
    written; frames warm..start-1 go through the same chain first, not written (they warm the temporal
    state up). Without the temporal reconstruction a chunk is one frame (warm = start)."""
    start: int
    stop: int
    warm: int


@dataclasses.dataclass
class Job:
    """What to compute: source frames, settings, output folder; profiles loaded once here. `chunk`,
    `overlap`: the temporal reconstruction's chunks (frames per chunk, warm-up frames before it); only
    with settings.temporal "on"."""
    source: Source
    out_dir: Path
    settings: chain.ChainSettings = chain.ChainSettings()
    png: bool = False
    crosstalk_profile: Path | None = None
    allow_outside: bool = False      # profiles naming files outside their folder (profile.load)
    chunk: int = DEFAULT_CHUNK
    overlap: int = DEFAULT_OVERLAP

    def __post_init__(self):
        from . import profile as profile_mod
        for name, lo in (("chunk", 1), ("overlap", 0)):
            v = getattr(self, name)
            if not (isinstance(v, (int, np.integer)) and not isinstance(v, bool) and v >= lo):
                raise BatchError(f"batch {name} must be an integer >= {lo}, got {v!r}")
        self.out_dir = Path(self.out_dir)
        self.profile = profile_mod.load(self.source.profile, allow_outside=self.allow_outside)
        if (self.profile.width, self.profile.height) != (self.source.width, self.source.height):
            raise BatchError(f"profile {self.source.profile} has a {self.profile.width}x{self.profile.height} "
                             f"mask but the frames are {self.source.width}x{self.source.height}")
        self.xt_profile = None
        if self.crosstalk_profile is not None:
            self.crosstalk_profile = Path(self.crosstalk_profile).resolve()
            self.xt_profile = profile_mod.load(self.crosstalk_profile, allow_outside=self.allow_outside)
            if (self.xt_profile.width, self.xt_profile.height) != (self.profile.width, self.profile.height):
                raise BatchError(f"crosstalk profile {self.crosstalk_profile} has a {self.xt_profile.width}x"
                                 f"{self.xt_profile.height} mask but the frames are {self.profile.width}x"
                                 f"{self.profile.height}")

    @property
    def temporal(self) -> bool:
        """The temporal reconstruction (nrreconstruct temporal=on): frames in chunks."""
        return self.settings.temporal == "on"

    def chunks(self, todo) -> list[Chunk]:
        """The chunks that compute the frames `todo`: one per frame; with `temporal`, the chunks of
        `chunk` frames counted from frame 0 that hold them (every frame of such a chunk is computed and
        written), each warmed up on the `overlap` frames before it (fewer at the clip's start)."""
        if not self.temporal:
            return [Chunk(i, i + 1, i) for i in todo]
        n, c = self.source.frames, int(self.chunk)
        starts = sorted({i - i % c for i in todo})
        return [Chunk(s, min(s + c, n), max(0, s - int(self.overlap))) for s in starts]

    def outputs(self, index: int) -> list[Path]:
        names = [EXR_NAME.format(index)] + ([PNG_NAME.format(index)] if self.png else [])
        return [self.out_dir / n for n in names]

    @property
    def stage(self) -> Path:
        """This run's stage folder in the output folder: files are written here, then renamed into it."""
        return outputs.temp_path(self.out_dir / "frames")

    def manifest(self) -> dict:
        """Everything the output depends on: a rerun resumes only when this is equal. A still sequence is
        identified by its location and the SHA-256 of its files' names, sizes and mtimes."""
        s = self.source
        if s.stills is None:
            ident = _file_id(s.raw)
        else:
            h = hashlib.sha256()
            for f in s.stills.files[:s.frames]:
                st = os.stat(f)
                h.update(f"{f}\0{st.st_size}\0{st.st_mtime_ns}\n".encode())
            ident = {"path": str(s.raw), "stills": s.stills.files[0], "files_sha256": h.hexdigest()}

        def prof(path):
            if path is None:
                return None
            return {"path": str(path), "sha256": _sha256(path)}

        out = {"format": MANIFEST_FORMAT, "version": 1, "writer": "nrhdr batch",
               "input": dict(ident, width=s.width, height=s.height, frames=s.frames),
               "profile": prof(s.profile), "crosstalk_profile": prof(self.crosstalk_profile),
               "settings": self._settings(), "png": self.png,
               "files": {"exr": "frame_%05d.exr", "png": "frame_%05d.png" if self.png else None}}
        if self.temporal:     # a chunk's first frames depend on where it starts and on its warm-up
            out["chunks"] = {"chunk": int(self.chunk), "overlap": int(self.overlap)}
        return out

    def _settings(self) -> dict:
        """The settings the output depends on: temporal_budget only with the temporal reconstruction."""
        d = self.settings.as_dict()
        if not self.temporal:
            d.pop("temporal_budget")
        return d


def _diff(a, b, prefix=""):
    out = []
    for k in sorted(set(a) | set(b)):
        va, vb = a.get(k), b.get(k)
        if isinstance(va, dict) and isinstance(vb, dict):
            out += _diff(va, vb, f"{prefix}{k}.")
        elif va != vb:
            out.append(f"{prefix}{k}: {va!r} -> {vb!r}")
    return out


def remove_stage(job: Job) -> None:
    """Remove this run's stage folder (after the run, or when it is stopped)."""
    shutil.rmtree(job.stage, ignore_errors=True)


# Settings a manifest may lack, with the behaviour such a manifest records: every frame reconstructed alone,
# PNGs by the log curve.
IMPLIED_SETTINGS = {"temporal": "off", "operator": "log"}


def prepare_output(job: Job, force: bool = False) -> tuple[list[int], int]:
    """Check the output folder, write the manifest; returns (frames to compute, frames skipped). Call it
    holding `outputs.lock(job.out_dir)`.

    Empty/new folder: all frames. Our manifest with equal settings: the frames whose files are missing (with
    `job.temporal`: every frame of a chunk that misses one, as a chunk is computed whole). Other settings,
    or a non-empty folder without our manifest: BatchError unless `force` (then this job's frame files
    there are deleted first, so an interrupted forced run resumes correctly). Killed runs'
    stage folders are removed (`outputs.remove_leftovers`); other files are never touched."""
    out = job.out_dir
    if out.exists() and not out.is_dir():
        raise BatchError(f"output {out} exists and is not a folder")
    want = job.manifest()
    mpath = out / MANIFEST
    resume = False
    if mpath.is_file():
        try:
            have = io.read_json(mpath, "batch manifest")
            ours = have.get("format") == MANIFEST_FORMAT
        except io.FileContentError:
            have, ours = None, False
        if ours and isinstance(have.get("settings"), dict):
            have = dict(have, settings={**IMPLIED_SETTINGS, **have["settings"]})
        if ours and have == want:
            resume = True
        elif not force:
            if ours:
                diff = "; ".join(_diff(have, want)[:6])
                raise BatchError(f"{out} holds a batch run with other input or settings ({diff}): use --force "
                                 f"to recompute it, or another output folder")
            raise BatchError(f"{mpath} is not an nrhdr batch manifest: use --force to overwrite {out}")
    elif out.is_dir() and any(not outputs.is_temp(f.name) for f in out.iterdir()) and not force:
        raise BatchError(f"{out} is not empty and was not written by nrhdr batch (no {MANIFEST}): use --force "
                         f"to write into it anyway, or another output folder")
    out.mkdir(parents=True, exist_ok=True)
    outputs.remove_leftovers(out)
    job.stage.mkdir(exist_ok=True)
    frames = range(job.source.frames)
    if not resume:
        for i in frames:   # forced: this job's old frame files go before the new manifest is written
            for f in job.outputs(i):
                f.unlink(missing_ok=True)
        outputs.write_text(mpath, json.dumps(want, indent=2) + "\n")
        return list(frames), 0
    todo = [i for i in frames if not all(f.is_file() for f in job.outputs(i))]
    todo = [i for c in job.chunks(todo) for i in range(c.start, c.stop)]
    return todo, job.source.frames - len(todo)


# ---- the chunk task (runs on the workers) --------------------------------------------------------------

def write_frame_files(files, values, state, tone, stage=None) -> None:
    """nrexrsink's write (EXR: Y + state) and, with `tone`, the GRAY8 PNG; with `stage`, written there and
    then renamed to `files` (the PNG first: a frame counts as done when its EXR exists)."""
    from . import io
    files = [Path(f) for f in files]
    tmp = [Path(stage) / f.name for f in files] if stage is not None else files
    io.write_exr(tmp[0], values, state)
    if tone is not None:
        io.write_image(tmp[1], tone, np.uint8)
    if stage is not None:
        for t, f in reversed(list(zip(tmp, files))):
            os.replace(t, f)


def chunk_frames(read, chunk: Chunk, profile, xt_profile, settings: chain.ChainSettings):
    """The frames of `chunk` through `chain.process_frame` in order, with settings.temporal "on" through
    one `chain.temporal_for(settings)` (frames chunk.warm..start-1 warm it up and are not yielded), as
    nrreconstruct temporal=on runs a stream that starts at frame chunk.warm. `read(i)`: raw frame i.
    Yields (i, (values, state) or the exception that frame raised) for chunk.start..stop-1. A frame that
    fails resets the temporal state: the next frame is reconstructed alone, as after a scene cut."""
    tr = chain.temporal_for(settings) if settings.temporal == "on" else None
    for i in range(chunk.warm, chunk.stop):
        try:
            out = chain.process_frame(read(i), profile, settings, xt_profile, temporal=tr)
        except Exception as e:  # noqa: BLE001 - reported by frame, the others go on
            if tr is not None:
                tr.reset()
            out = e
        if i >= chunk.start:
            yield i, out


def chunk_task(chunk: Chunk, src: Source, profile, xt_profile, settings: chain.ChainSettings, files,
               raws=None, return_files: bool = False, stage=None):
    """Compute the frames of `chunk` (`chunk_frames`) and write frame i's files `files[i - chunk.start]`
    through the stage folder `stage` (a shared file system), or, with `return_files`, in a private temp
    folder and return their bytes for the client to write. `raws`: the raw frames chunk.warm..stop-1 sent
    by the client (an error text for a frame it could not read); None: read here from `src`. Returns
    [(index, (wall seconds, CPU seconds of this process), {name: bytes} or None, error text or None)] for
    chunk.start..stop-1; the warm-up frames' time counts in the first frame's."""
    def read(i):
        if raws is None:
            return src.read(i)
        r = raws[i - chunk.warm]
        if isinstance(r, str):
            raise BatchError(r)
        return r

    out = []
    tmp = Path(tempfile.mkdtemp(prefix="nrhdr-batch-")) if return_files else None
    try:
        t0, c0 = time.perf_counter(), time.process_time()
        for i, frame in chunk_frames(read, chunk, profile, xt_profile, settings):
            names, data, err = files[i - chunk.start], None, None
            try:
                if isinstance(frame, BaseException):
                    raise frame
                values, state = frame
                tone = chain.tonemap_frame(values, profile, settings) if len(names) > 1 else None
                if return_files:
                    local = [tmp / Path(o).name for o in names]
                    write_frame_files(local, values, state, tone)
                    data = {f.name: f.read_bytes() for f in local}
                else:
                    write_frame_files(names, values, state, tone, stage)
            except Exception as e:  # noqa: BLE001 - reported by frame, the others go on
                err = _error_text(e)
            t1, c1 = time.perf_counter(), time.process_time()
            out.append((i, (t1 - t0, c1 - c0), data, err))
            t0, c0 = t1, c1
    finally:
        if tmp is not None:
            shutil.rmtree(tmp, ignore_errors=True)
    return out


# ---- drivers -----------------------------------------------------------------------------------------

@dataclasses.dataclass
class Failure:
    index: int
    file: str
    error: str

    def __str__(self):
        return f"frame {self.index} of {self.file}: {self.error}"


@dataclasses.dataclass
class Result:
    done: list[int] = dataclasses.field(default_factory=list)
    skipped: int = 0
    failures: list[Failure] = dataclasses.field(default_factory=list)
    seconds: float = 0.0          # wall time of the frame loop (after warm-up)
    frame_seconds: float = 0.0    # sum of the per-frame compute (wall) times on the workers (warm-up frames in)
    frame_cpu_seconds: float = 0.0  # sum of the workers' CPU time per frame (all their threads)

    @property
    def fps(self) -> float:
        return len(self.done) / self.seconds if self.seconds > 0 else 0.0


def _progress(total, enabled, desc="batch"):
    from tqdm import tqdm
    return tqdm(total=total, desc=desc, unit="frame", disable=not enabled, dynamic_ncols=True,
                smoothing=0.1)


def _error_text(e: BaseException) -> str:
    """Our own errors (ValueError/OSError: bad data, unreadable files) speak for themselves; others keep
    their type."""
    return str(e) if isinstance(e, (ValueError, OSError)) and str(e) else f"{type(e).__name__}: {e}"


class _Recorder:
    """Adds a chunk's per-frame results (`chunk_task`) to a Result, reports failures as they come."""

    def __init__(self, job: Job, res: Result, bar, on_failure):
        self.job, self.res, self.bar, self.on_failure = job, res, bar, on_failure

    def fail(self, i: int, text: str) -> None:
        f = Failure(i, self.job.source.frame_file(i), text)
        self.res.failures.append(f)
        if self.on_failure:
            self.on_failure(f, self.bar)

    def frame(self, i: int, times, err) -> None:
        if err is None:
            self.res.done.append(i)
        else:
            self.fail(i, err)
        self.res.frame_seconds += times[0]
        self.res.frame_cpu_seconds += times[1]
        self.bar.update(1)


def run_loop(job: Job, todo, progress: bool = False, on_failure=None) -> Result:
    """The same tasks in a plain loop in this process (no Dask): `--workers 0` and the scaling anchor."""
    res = Result()
    warm_cache(job.settings, job.png)
    chain.warmup(job.settings, tone=job.png)
    t0 = time.perf_counter()
    with _progress(len(todo), progress) as bar:
        rec = _Recorder(job, res, bar, on_failure)
        for c in job.chunks(todo):
            files = [[str(p) for p in job.outputs(i)] for i in range(c.start, c.stop)]
            for i, times, _, err in chunk_task(c, job.source, job.profile, job.xt_profile, job.settings, files,
                                               stage=str(job.stage)):
                rec.frame(i, times, err)
    res.seconds = time.perf_counter() - t0
    return res


def warm_cache(settings: chain.ChainSettings, tone: bool = False) -> None:
    """Fill numba's on-disk cache for `settings` in a short-lived subprocess, so that this process and the
    workers then *load* the kernels rather than JIT-compile them. Why: the fastmath FSE kernels give results
    that differ in the last bits between a fresh JIT compile and the cached machine code (observed with
    numba 0.68), so two processes agree bit for bit (batch workers among themselves and with a
    GStreamer run) only when both loaded the cache. A failure here only costs speed."""
    import subprocess
    import sys
    code = ("import json, sys; from nrhdr_core import chain; "
            "chain.warmup(chain.ChainSettings(**json.loads(sys.argv[1])), tone=sys.argv[2] == '1')")
    env = dict(os.environ, PYTHONPATH=os.pathsep.join(p for p in sys.path if p))
    subprocess.run([sys.executable, "-c", code, json.dumps(settings.as_dict()), "1" if tone else "0"],
                   env=env, check=False, stdout=subprocess.DEVNULL)


def _worker_warmup(settings: chain.ChainSettings, tone: bool) -> None:
    warm_cache(settings, tone)
    chain.warmup(settings, tone)


def warm_workers(client, settings: chain.ChainSettings, tone: bool) -> None:
    """On every worker: fill numba's cache in a subprocess (`warm_cache`), then load the kernels, before
    the clock starts."""
    client.run(_worker_warmup, settings, tone)


def worker_threads(client) -> dict:
    """{worker address: (dask threads, numba threads, cores)} for the oversubscription check."""
    def probe():
        import numba
        return numba.config.NUMBA_NUM_THREADS, usable_cores()
    info = client.scheduler_info(n_workers=-1)["workers"] if _takes_n_workers(client) else \
        client.scheduler_info()["workers"]
    probed = client.run(probe)
    return {a: (w.get("nthreads", 1), *probed.get(a, (None, None))) for a, w in info.items()}


def _takes_n_workers(client) -> bool:
    import inspect
    try:
        return "n_workers" in inspect.signature(client.scheduler_info).parameters
    except (TypeError, ValueError):
        return False


def oversubscription_warnings(client) -> list[str]:
    """Hosts where dask threads x numba threads exceed the cores (the rule of docs/BATCH.md)."""
    hosts: dict[str, list] = {}
    for addr, (nthreads, numba_threads, cores) in worker_threads(client).items():
        host = addr.rsplit(":", 1)[0]
        hosts.setdefault(host, []).append((nthreads, numba_threads or 1, cores or 1))
    out = []
    for host, ws in hosts.items():
        used = sum(n * t for n, t, _ in ws)
        cores = ws[0][2]
        if used > cores:
            out.append(f"{host}: {len(ws)} workers x threads x numba threads = {used} > {cores} cores "
                       f"(start workers with NUMBA_NUM_THREADS=1 and --nthreads 1, one per core)")
    return out


def run_dask(job: Job, todo, client, progress: bool = False, return_files: bool = False,
             window: int | None = None, on_failure=None, warm: bool = True) -> Result:
    """Chunk-parallel (frame-parallel without the temporal reconstruction) on a dask.distributed client:
    one task per `Job.chunks` entry. At most `window` tasks are in flight (default: 2 x worker threads + 1
    single frames, or one chunk per worker thread), so memory stays bounded and Ctrl-C has little to
    cancel. With `return_files` the client reads the raw frames and writes the files the workers return
    (no shared file system); else workers read the raw file and write the outputs themselves.
    KeyboardInterrupt cancels the tasks in flight and propagates."""
    from distributed import as_completed
    res = Result()
    nthreads = sum(client.nthreads().values()) or 1
    window = window or (nthreads if job.temporal else 2 * nthreads + 1)
    prof_f = client.scatter(job.profile, broadcast=True, hash=False)
    xt_f = client.scatter(job.xt_profile, broadcast=True, hash=False) if job.xt_profile is not None else None
    src_f = client.scatter(job.source, broadcast=True, hash=False)   # a still sequence's file list: sent once
    if warm:
        warm_workers(client, job.settings, job.png)
    pending = iter(job.chunks(todo))
    inflight: dict = {}
    ac = as_completed()
    src = job.source

    def raws_of(c: Chunk):
        out = []
        for i in range(c.warm, c.stop):
            try:
                out.append(src.read(i))
            except Exception as e:  # noqa: BLE001 - the task reports it as that frame's failure
                out.append(_error_text(e))
        return out

    def submit_next() -> bool:
        for c in pending:
            files = [[str(p) for p in job.outputs(i)] for i in range(c.start, c.stop)]
            fut = client.submit(chunk_task, c, src_f, prof_f, xt_f, job.settings, files,
                                raws_of(c) if return_files else None, return_files, str(job.stage),
                                key=f"nrhdr-chunk-{c.start}-{os.getpid()}-{time.monotonic_ns()}", pure=False,
                                retries=0)
            inflight[fut] = c
            ac.add(fut)
            return True
        return False

    t0 = time.perf_counter()
    try:
        with _progress(len(todo), progress) as bar:
            rec = _Recorder(job, res, bar, on_failure)
            for _ in range(window):
                if not submit_next():
                    break
            for fut in ac:
                c = inflight.pop(fut)
                if fut.status == "finished":
                    for i, times, files, err in fut.result():
                        if err is None and files:
                            try:
                                for name, data in sorted(files.items(), key=lambda kv: kv[0].endswith(".exr")):
                                    outputs.write_bytes(job.out_dir / name, data)
                            except Exception as e:  # noqa: BLE001 - e.g. a write on the client failed
                                err = _error_text(e)
                        rec.frame(i, times, err)
                else:
                    try:
                        err = fut.exception()
                        text = _error_text(err) if err is not None else f"task {fut.status}"
                    except Exception as e:  # noqa: BLE001 - cancelled/lost
                        text = _error_text(e)
                    for i in range(c.start, c.stop):
                        rec.frame(i, (0.0, 0.0), text)
                fut.release()
                submit_next()
    except BaseException:
        if inflight:
            client.cancel(list(inflight), force=True)
        raise
    finally:
        res.seconds = time.perf_counter() - t0
    return res


@contextlib.contextmanager
def _sigint_ignored():
    """Ignore SIGINT while the worker processes start: they inherit the ignored disposition (it survives
    fork and exec), so a terminal's Ctrl-C, sent to the whole process group, reaches only this process,
    which cancels the frames and closes the cluster (workers would otherwise die printing tracebacks).
    A Ctrl-C during the few seconds of cluster start-up is lost."""
    import signal
    import threading
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    old = signal.signal(signal.SIGINT, signal.SIG_IGN)
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, old)


@contextlib.contextmanager
def local_client(workers: int | None = None, numba_threads: int = 1, quiet: bool = True):
    """A LocalCluster of `workers` processes (default: one per core) with one dask thread each and numba
    limited to `numba_threads` threads (NUMBA_NUM_THREADS set before each worker process starts).
    Closing it (also on Ctrl-C) stops every worker process."""
    import logging

    import dask
    from distributed import Client, LocalCluster
    workers = workers or usable_cores()
    ours = {"NUMBA_NUM_THREADS": str(int(numba_threads)), "OMP_NUM_THREADS": "1"}
    env = dict(dask.config.get("distributed.nanny.pre-spawn-environ", {}) or {})
    env.update(ours)
    cluster = client = None
    saved = dict(os.environ)
    # worker-saturation inf: the scheduler hands every submitted frame (at most the window) to a worker at
    # once instead of holding it until a thread is free, so a worker never waits a round trip per frame
    with dask.config.set({"distributed.nanny.pre-spawn-environ": env,
                          "distributed.scheduler.worker-saturation": float("inf")}):
        try:
            # the nanny prefers os.environ over its config and copies its values into os.environ: set
            # ours there too, and restore this process's environment once the workers have started
            os.environ.update(ours)
            try:
                with _sigint_ignored():   # workers inherit it: Ctrl-C is for this process
                    cluster = LocalCluster(n_workers=int(workers), threads_per_worker=1, processes=True,
                                           host="127.0.0.1", dashboard_address=None,
                                           scheduler_kwargs={"dashboard_address": "127.0.0.1:0"},
                                           silence_logs=logging.CRITICAL if quiet else logging.WARNING)
            finally:
                os.environ.clear()
                os.environ.update(saved)
            client = Client(cluster)
            yield client
        finally:
            if client is not None:
                with contextlib.suppress(Exception):
                    client.close(timeout=10)
            if cluster is not None:
                with contextlib.suppress(Exception):
                    cluster.close(timeout=20)
