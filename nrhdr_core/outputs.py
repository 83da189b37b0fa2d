"""Writing outputs safely: one writer per output (a lock), temporary names that carry the run id, commit by
rename, and clean-up of temporaries, both this run's (on a stop) and those of a killed run (by the next run).
docs/RELIABILITY.md, "Stop, crash and disk full".

- `lock(target)`: `fcntl.flock` on `.<name>.lock` beside `target`; a second writer is refused with
  `OutputLockedError` naming the holder. The kernel releases the lock when its holder dies (even by SIGKILL).
- Temporary names: `.<name>.nrtmp-<pid>-<random>[suffix]` (`temp_path`). Only names with the `.nrtmp-` tag
  are ever removed, and only by a process holding the target's lock (`remove_leftovers`), so a concurrent
  run's temporaries and a user's own files are never touched.
- `atomic_file(path)`, `write_bytes`, `write_text`: a file appears complete under its name or not at all.
- `staged_folder(final)`: a whole folder written aside and renamed in; `staged_files(target, dest)`: a group
  of files written aside and moved into `dest` together (signals held back while they move).
- `stop_on_signals()`: SIGINT, SIGTERM and SIGHUP raise `Interrupted` (a KeyboardInterrupt) once, so the
  clean-up of a stopped command runs; later copies are ignored until the block ends.
"""
from __future__ import annotations

import contextlib
import os
import re
import secrets
import shutil
import signal
import sys
import threading
from pathlib import Path

from .io import OutputExistsError

TEMP_TAG = ".nrtmp-"
STOP_SIGNALS = (signal.SIGINT, signal.SIGTERM, signal.SIGHUP)

_run = {"pid": None, "id": None}


class OutputLockedError(OSError):
    """Another command is writing the same output (its lock is held)."""


class Interrupted(KeyboardInterrupt):
    """A stop signal (SIGINT, SIGTERM, SIGHUP) during `stop_on_signals`; `signum` says which."""

    def __init__(self, signum: int):
        super().__init__(signal.Signals(signum).name)
        self.signum = int(signum)


def run_id() -> str:
    """`<pid>-<8 hex>`: unique per process (recomputed after a fork)."""
    if _run["pid"] != os.getpid():
        _run.update(pid=os.getpid(), id=f"{os.getpid()}-{secrets.token_hex(4)}")
    return _run["id"]


def temp_path(target, suffix: str = "") -> Path:
    """The temporary name of `target` for this run: `.<name>.nrtmp-<run id><suffix>` beside it."""
    target = Path(target)
    return target.parent / f".{target.name}{TEMP_TAG}{run_id()}{suffix}"


_TEMP_RX = re.compile(r"\..*\.nrtmp-(\d+)-[0-9a-f]{8}.*")


def is_temp(name: str) -> bool:
    """True for a name made by `temp_path` (any run)."""
    return _TEMP_RX.fullmatch(name) is not None


def _lock_path(target: Path) -> Path:
    return target.parent / f".{target.name}.lock"


@contextlib.contextmanager
def lock(target, hint: str = "wait for it to finish, or choose another output"):
    """Hold the write lock of `target` (a file or folder, which need not exist) for the block. Raises
    OutputLockedError naming the holder (pid and command line) when another process holds it."""
    import fcntl
    target = Path(os.path.abspath(target))
    target.parent.mkdir(parents=True, exist_ok=True)
    lp = _lock_path(target)
    while True:
        fd = os.open(lp, os.O_RDWR | os.O_CREAT, 0o644)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            try:
                holder = os.pread(fd, 4096, 0).decode(errors="replace").strip() or "unknown process"
            finally:
                os.close(fd)
            raise OutputLockedError(f"{target} is being written by another command ({holder}); nothing was "
                                    f"written: {hint}") from None
        try:   # the holder before us may have removed the file after we opened it: lock the current one
            same = os.stat(lp).st_ino == os.fstat(fd).st_ino
        except FileNotFoundError:
            same = False
        if same:
            break
        os.close(fd)
    try:
        os.ftruncate(fd, 0)
        os.pwrite(fd, f"pid {os.getpid()}: {' '.join(sys.argv)}\n".encode(), 0)
        yield target
    finally:
        with contextlib.suppress(OSError):
            os.unlink(lp)           # while still holding it: a waiter re-checks the inode
        os.close(fd)


def remove_leftovers(target) -> list[Path]:
    """Remove the temporaries of other (dead) runs for `target`: `.<name>.nrtmp-*` beside it and, when it is a
    folder, every `.nrtmp-` name in it and its direct subfolders. Call it only while holding `lock(target)`
    (then no live writer owns them). Returns what was removed."""
    target = Path(os.path.abspath(target))
    mine = run_id()
    found = []
    if target.parent.is_dir():
        found += [p for p in target.parent.iterdir() if p.name.startswith(f".{target.name}{TEMP_TAG}")]
    if target.is_dir() and not target.is_symlink():
        for d in [target] + [p for p in target.iterdir() if p.is_dir() and not p.is_symlink()]:
            found += [p for p in d.iterdir() if is_temp(p.name)]
    removed = []
    for p in found:
        if not is_temp(p.name) or f"{TEMP_TAG}{mine}" in p.name:
            continue
        if p.is_dir() and not p.is_symlink():
            shutil.rmtree(p, ignore_errors=True)
        else:
            p.unlink(missing_ok=True)
        removed.append(p)
    return removed


def _umask() -> int:
    m = os.umask(0)
    os.umask(m)
    return m


@contextlib.contextmanager
def held_signals():
    """Hold back the stop signals (delivered when the block ends): a group of renames is not split."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    old = signal.pthread_sigmask(signal.SIG_BLOCK, STOP_SIGNALS)
    try:
        yield
    finally:
        signal.pthread_sigmask(signal.SIG_SETMASK, old)


@contextlib.contextmanager
def atomic_file(path):
    """Yields the temporary path to write `path` to; renamed to `path` when the block succeeds, removed
    when it fails. The file gets the usual mode (0666 & ~umask)."""
    path = Path(path)
    tmp = temp_path(path)
    try:
        yield tmp
        if tmp.exists():
            os.chmod(tmp, 0o666 & ~_umask())
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)


def write_bytes(path, data: bytes) -> Path:
    with atomic_file(path) as tmp:
        tmp.write_bytes(data)
    return Path(path)


def write_text(path, text: str) -> Path:
    with atomic_file(path) as tmp:
        tmp.write_text(text)
    return Path(path)


_stop = {"depth": 0, "fired": []}


def _ignore(signum, frame):
    """A later copy of a stop (`stop_on_signals`)."""


@contextlib.contextmanager
def stop_on_signals(ends_process: bool = False):
    """SIGINT, SIGTERM and SIGHUP raise `Interrupted` in the main thread (the first one; later ones are
    ignored until the outermost such block ends, so clean-up is not broken off; with `ends_process`, after a
    stop they stay ignored after the block too: a command that exits then). Python handlers rather than
    SIG_IGN: a signal pending when SIG_IGN is set prints "Signal N ignored due to race condition". Does
    nothing outside the main thread. Yields the list of signals received."""
    if threading.current_thread() is not threading.main_thread():
        yield []
        return

    def stop(signum, frame):
        if _stop["fired"]:
            return
        _stop["fired"].append(signum)
        raise Interrupted(signum)

    old = {s: signal.signal(s, stop) for s in STOP_SIGNALS}
    _stop["depth"] += 1
    try:
        yield _stop["fired"]
    finally:
        _stop["depth"] -= 1
        keep = ends_process and _stop["fired"]
        for s, h in old.items():
            signal.signal(s, _ignore if keep else h)
        if _stop["depth"] == 0:
            _stop["fired"] = []


def refuse_nonempty(folder, hint: str = "--force") -> None:
    folder = Path(folder)
    if os.path.lexists(folder) and not folder.is_dir():
        raise OutputExistsError(f"{folder} exists and is not a folder; nothing was written")
    if folder.is_dir() and any(not _is_ours(p.name) for p in folder.iterdir()):
        raise OutputExistsError(f"{folder} already exists and is not empty; nothing was written: use {hint} "
                                f"to replace what this command writes there, or choose another folder")


def _is_ours(name: str) -> bool:
    return is_temp(name) or name.endswith(".lock") and name.startswith(".")


def _files_under(d: Path) -> list[str]:
    return sorted(p.relative_to(d).as_posix() for p in d.rglob("*") if p.is_file() or p.is_symlink())


@contextlib.contextmanager
def staged_folder(final, force: bool = False, owned=None, hint: str = "--force"):
    """Write a whole output folder: yields a temporary sibling folder (run id in its name) to write into; on
    success it becomes `final` (rename), on any exception (a stop signal included: `stop_on_signals`) it is
    removed and `final` is left untouched. Holds `lock(final)` and first removes a killed run's leftovers.

    An existing non-empty `final` is refused (OutputExistsError) unless `force`. With `force`, the files of
    `final` that the command writes (`owned(rel_path)`, default: every file) are replaced as a whole: the old
    folder is renamed aside, the new one renamed in, and every file the command does not own (e.g. the
    user's notes) is moved back into it; nothing but old outputs of the same command is deleted."""
    final = Path(os.path.abspath(final))
    owned = owned or (lambda rel: True)
    with stop_on_signals(), lock(final):
        remove_leftovers(final)
        if not force:
            refuse_nonempty(final, hint)
        elif os.path.lexists(final) and not final.is_dir():
            raise OutputExistsError(f"{final} exists and is not a folder; nothing was written")
        tmp = temp_path(final, ".partial")
        tmp.mkdir()
        try:
            yield tmp
            os.chmod(tmp, 0o777 & ~_umask())
            with held_signals():
                _commit_folder(tmp, final, owned)
        finally:
            if tmp.exists():
                shutil.rmtree(tmp, ignore_errors=True)


def _commit_folder(tmp: Path, final: Path, owned) -> None:
    if final.is_dir() and not any(not _is_ours(p.name) for p in final.iterdir()):
        shutil.rmtree(final)
    if not final.exists():
        os.rename(tmp, final)
        return
    old = temp_path(final, ".old")
    os.rename(final, old)           # the old folder, whole, aside
    try:
        os.rename(tmp, final)       # the new folder, whole, in
    except OSError:
        os.rename(old, final)       # put the old one back: nothing changed
        raise
    for rel in _files_under(old):   # give back what this command did not write
        if owned(rel):
            continue
        dst = final / rel
        if os.path.lexists(dst):
            dst = dst.with_name(dst.name + ".kept")
        dst.parent.mkdir(parents=True, exist_ok=True)
        os.replace(old / rel, dst)
    for d in sorted((p for p in old.rglob("*") if p.is_dir() and not p.is_symlink()), reverse=True):
        rel = d.relative_to(old).as_posix()
        if not (final / rel).exists():
            (final / rel).mkdir(parents=True, exist_ok=True)   # keep the user's (empty) folders
    shutil.rmtree(old)              # holds only this command's old outputs now


@contextlib.contextmanager
def staged_files(target, dest=None):
    """Write a group of files that belong together (a profile and its mask, a set of figures): yields a
    temporary folder beside `target` (run id in its name); on success every file in it is moved into `dest`
    (default: `target`, made if needed) with the stop signals held back, so they appear together; on any
    exception the folder is removed and nothing is moved. Holds `lock(target)` and first removes a killed
    run's leftovers. Checking for existing files is the caller's (before the work)."""
    target = Path(os.path.abspath(target))
    dest = Path(os.path.abspath(dest)) if dest is not None else target
    with stop_on_signals(), lock(target):
        remove_leftovers(target)
        tmp = temp_path(target, ".partial")
        tmp.mkdir()
        try:
            yield tmp
            with held_signals():
                dest.mkdir(parents=True, exist_ok=True)
                for p in sorted(tmp.iterdir()):
                    if p.is_file() and not p.name.startswith("."):
                        os.chmod(p, 0o666 & ~_umask())
                        os.replace(p, dest / p.name)
        finally:
            shutil.rmtree(tmp, ignore_errors=True)


# ---- raw recordings ------------------------------------------------------------------------------------

def finish_recording(part, clip_json_src, out_dir, profile, raw_name: str = "clip.raw") -> tuple[int, int]:
    """Turn a raw GRAY16_LE recording `part` (written by a filesink) into the clip folder `out_dir`: the file
    is cut to whole frames and renamed to `out_dir/raw_name`, the camera profile is copied in
    (`camera.json` + its mask and calibration), and `clip.json` (the source clip's description with the
    recorded frame count; no ground truth) is written last, atomically. The folder is self-contained, like
    one of `nrhdr simulate`. Returns (frames kept, bytes cut off the end)."""
    import json
    from . import profile as profiles
    part, out_dir = Path(part), Path(out_dir)
    c = json.loads(Path(clip_json_src).read_text())
    fb = 2 * int(c["width"]) * int(c["height"])
    size = part.stat().st_size
    frames, cut = divmod(size, fb)
    cam = profiles.load(profile)
    with held_signals():
        if cut:
            os.truncate(part, size - cut)
        os.replace(part, out_dir / raw_name)
        profiles.save(cam, out_dir / "camera.json")
        for k in ("truth", "sequence"):
            c.pop(k, None)
        c.update(frames=frames, raw=raw_name, profile="camera.json",
                 recorded_from=os.path.abspath(Path(clip_json_src).parent),
                 recorded_profile=os.path.abspath(profile))
        write_text(out_dir / "clip.json", json.dumps(c, indent=2) + "\n")
    return frames, cut


RECORDING_PART = ".clip.raw.part"        # pipelines/live_record_and_preview.sh: the raw file while recording
RECORDING_META = ".clip.json.part"       # {source_clip_json, profile}: written before the first frame


def complete_recording(out_dir) -> str | None:
    """The recorder's own finish (it holds the lock of `out_dir/clip.raw`): `.clip.raw.part` cut to whole
    frames and renamed `clip.raw`, `clip.json` written from `.clip.json.part`. Returns what was done, or None
    when there is no unfinished recording."""
    from . import io
    out_dir = Path(out_dir)
    part, meta = out_dir / RECORDING_PART, out_dir / RECORDING_META
    if not part.is_file():
        return None
    if not meta.is_file():
        raise FileNotFoundError(f"{meta} not found: cannot tell the frame size of {part}")
    m = io.read_json(meta, "recording description")
    c = io.read_json(Path(m["source_clip_json"]), "clip description (clip.json)")
    if part.stat().st_size < 2 * int(c["width"]) * int(c["height"]):
        part.unlink()
        meta.unlink(missing_ok=True)
        return f"no whole frame was recorded: nothing written to {out_dir}"
    frames, cut = finish_recording(part, m["source_clip_json"], out_dir, m["profile"])
    meta.unlink(missing_ok=True)
    return (f"recorded {frames} whole frames to {out_dir / 'clip.raw'} (clip folder)"
            + (f"; {cut} bytes of a partial last frame cut off" if cut else ""))


def recover(out_dir) -> str | None:
    """Finish a recording that a killed recorder (SIGKILL, power loss) left in `out_dir`: `.clip.raw.part`
    cut to whole frames and renamed `clip.raw` (replacing an older one), `clip.json` written from
    `.clip.json.part`. Returns what was done, or None when there was nothing to recover. Refuses
    (OutputLockedError) while the recorder still runs (it holds the lock of `out_dir/clip.raw`)."""
    out_dir = Path(out_dir)
    with lock(out_dir / "clip.raw", hint="the recording is still running; it finishes the file itself"):
        return complete_recording(out_dir)
