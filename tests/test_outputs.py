"""Safe outputs (nrhdr_core/outputs.py; docs/RELIABILITY.md "Stop, crash and disk full"): the write lock,
run-id temporaries, clean-up of a killed run's leftovers without touching other files, and the commands
that use them stopped with SIGINT / SIGTERM / SIGKILL (nrhdr simulate, calibrate, figures)."""
from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from nrhdr_core import outputs

ROOT = Path(__file__).resolve().parents[1]


def env():
    e = dict(os.environ)
    e["PYTHONPATH"] = os.pathsep.join([str(ROOT)] + [p for p in e.get("PYTHONPATH", "").split(os.pathsep) if p])
    return e


HOLD = """
import sys, time
from nrhdr_core import outputs
with outputs.lock(sys.argv[1]):
    print("held", flush=True)
    time.sleep(60)
"""


def _holder(target):
    p = subprocess.Popen([sys.executable, "-c", HOLD, str(target)], env=env(), stdout=subprocess.PIPE, text=True)
    assert p.stdout.readline().strip() == "held"
    return p


def test_lock_refuses_a_second_writer_and_dies_with_its_holder(tmp_path):
    target = tmp_path / "out"
    p = _holder(target)
    try:
        with pytest.raises(outputs.OutputLockedError, match=rf"{target} is being written by another command "
                                                             rf"\(pid {p.pid}: "):
            with outputs.lock(target):
                pass
        p.send_signal(signal.SIGKILL)          # a crash: the kernel releases the flock
        p.wait(10)
        assert (tmp_path / ".out.lock").exists()   # the file stays, the lock does not
        with outputs.lock(target):
            assert (tmp_path / ".out.lock").read_text().startswith(f"pid {os.getpid()}:")
        assert not (tmp_path / ".out.lock").exists()
    finally:
        if p.poll() is None:
            p.kill()
            p.wait()


def test_leftovers_of_other_runs_only_are_removed(tmp_path):
    out = tmp_path / "clip"
    (out / "truth").mkdir(parents=True)
    dead = [tmp_path / ".clip.nrtmp-12345-0123abcd.partial", out / ".frames.nrtmp-12345-89abcdef",
            out / "truth" / ".frame_00000.exr.nrtmp-777-deadbeef"]
    dead[0].mkdir()
    (dead[0] / "clip.raw").write_bytes(b"x" * 100)
    dead[1].mkdir()
    dead[2].write_bytes(b"partial")
    mine = outputs.temp_path(out / "frames")
    mine.mkdir()
    users = [tmp_path / ".clip.tmp", out / ".frame_00002.abc123.exr", out / "notes.nrtmp-1-2",
             tmp_path / ".clipboard.nrtmp-1-0123abcd", out / "truth" / "frame_00000.exr"]
    for f in users:
        f.write_bytes(b"the user's")
    with outputs.lock(out):
        removed = outputs.remove_leftovers(out)
    assert sorted(removed) == sorted(dead)
    assert not any(p.exists() for p in dead)
    assert mine.is_dir()                          # this run's own
    assert all(f.read_bytes() == b"the user's" for f in users)


def test_atomic_file_leaves_nothing_on_failure(tmp_path):
    f = tmp_path / "a.json"
    with pytest.raises(RuntimeError):
        with outputs.atomic_file(f) as tmp:
            tmp.write_text("half")
            raise RuntimeError("disk full")
    assert list(tmp_path.iterdir()) == []
    outputs.write_text(f, "whole")
    assert [p.name for p in tmp_path.iterdir()] == ["a.json"] and f.read_text() == "whole"


def test_finish_recording_keeps_whole_frames(tmp_path):
    from conftest import make_test_clip
    d, prof, raws = make_test_clip(tmp_path / "clip", frames=3)
    out = tmp_path / "rec"
    out.mkdir()
    part = out / outputs.RECORDING_PART
    part.write_bytes(raws[[0, 1, 2, 0]].astype("<u2").tobytes() + b"\x01" * 1000)   # 4 frames + a partial
    (out / outputs.RECORDING_META).write_text(json.dumps({"source_clip_json": str(d / "clip.json"),
                                                          "profile": str(d / "camera.json")}))
    from nrhdr_core import batch
    with pytest.raises(batch.BatchError, match="unfinished recording.*nrhdr recover"):
        batch.open_source(out)
    text = outputs.recover(out)
    assert "4 whole frames" in text and "1000 bytes of a partial last frame cut off" in text
    assert sorted(p.name for p in out.iterdir()) == ["camera.json", "camera_mask.png", "clip.json", "clip.raw"]
    got = np.fromfile(out / "clip.raw", "<u2").reshape(-1, prof.height, prof.width)
    assert np.array_equal(got, raws[[0, 1, 2, 0]])
    c = json.loads((out / "clip.json").read_text())
    assert c["frames"] == 4 and c["raw"] == "clip.raw" and c["profile"] == "camera.json" and "truth" not in c
    from nrhdr_core import profile
    assert np.array_equal(profile.load(out / "camera.json").mask, prof.mask)
    assert batch.open_source(out).frames == 4        # a clip folder nrhdr batch reads
    assert outputs.recover(out) is None              # nothing left to do


# ---- commands stopped ----------------------------------------------------------------------------------

def _start(args, **kw):
    return subprocess.Popen([sys.executable, "-m", "gst_plugins.cli", *map(str, args)], env=env(),
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, **kw)


def _wait_for(cond, p, timeout=120):
    t0 = time.monotonic()
    while not cond():
        assert p.poll() is None, p.communicate()[0]
        assert time.monotonic() - t0 < timeout, "timed out"
        time.sleep(0.05)


def _partials(parent, name):
    return [p for p in parent.iterdir() if p.name.startswith(f".{name}.nrtmp-")]


SIM = ["simulate", "--frames", "2000", "--width", "320", "--height", "240"]


@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM])
def test_simulate_stopped_leaves_nothing_and_an_old_clip_untouched(tmp_path, sig):
    out = tmp_path / "clip"
    out.mkdir()
    (out / "notes.txt").write_text("mine")
    p = _start([*SIM, "-o", out, "--force"])
    try:
        _wait_for(lambda: any((d / "truth").is_dir() and len(list((d / "truth").iterdir())) > 3
                              for d in _partials(tmp_path, "clip")), p)
        p.send_signal(sig)
        log = p.communicate(timeout=60)[0]
    finally:
        if p.poll() is None:
            p.kill()
    assert p.returncode == 128 + sig, log                              # 130 Ctrl-C, 143 SIGTERM
    assert "Traceback" not in log, log
    assert sorted(x.name for x in tmp_path.iterdir()) == ["clip"]       # no .partial, no lock file
    assert [x.name for x in out.iterdir()] == ["notes.txt"]


def test_simulate_killed_then_rerun_cleans_up_and_a_second_writer_is_refused(tmp_path):
    out = tmp_path / "clip"
    (tmp_path / ".clip.keep").write_text("mine")
    p = _start([*SIM, "-o", out])
    try:
        _wait_for(lambda: _partials(tmp_path, "clip"), p)
        q = _start([*SIM, "-o", out])       # the same folder while the first runs: refused, nothing touched
        log = q.communicate(timeout=120)[0]
        assert q.returncode == 2, log
        assert f"{out} is being written by another command (pid {p.pid}: " in log, log
        p.send_signal(signal.SIGKILL)       # a crash: its temporary folder and lock file stay
        p.wait(10)
    finally:
        if p.poll() is None:
            p.kill()
    left = _partials(tmp_path, "clip")
    assert left and (tmp_path / ".clip.lock").exists()
    r = _start(["simulate", "--frames", "2", "--width", "32", "--height", "24", "-o", out])
    log = r.communicate(timeout=300)[0]
    assert r.returncode == 0, log
    assert sorted(x.name for x in tmp_path.iterdir()) == [".clip.keep", "clip"]
    assert json.loads((out / "clip.json").read_text())["frames"] == 2


def test_calibrate_stopped_writes_no_part_of_a_profile(tmp_path, monkeypatch):
    """A stop after the profile was made but before the plots: none of the files appear (before, the mask
    was there without its profile and the rerun refused); the rerun then writes all of them."""
    from nrhdr_core import calibration, profile
    prof = profile.default(24, 32, seed=1)
    calibration.simulate_flats(tmp_path / "flats", prof, exposures=np.geomspace(1e-4, 0.2, 12),
                               frames_per_exposure=2, progress=False)
    out = tmp_path / "cam" / "camera.json"

    def stopped(*a, **k):
        raise outputs.Interrupted(signal.SIGTERM)
    monkeypatch.setattr(calibration, "write_plots", stopped)
    with pytest.raises(KeyboardInterrupt):
        calibration.run_calibrate(tmp_path / "flats", tmp_path / "flats" / "mask.png", out, progress=False)
    assert list((tmp_path / "cam").iterdir()) == []
    monkeypatch.undo()
    summary = calibration.run_calibrate(tmp_path / "flats", tmp_path / "flats" / "mask.png", out,
                                        progress=False)
    names = sorted(p.name for p in (tmp_path / "cam").iterdir())
    assert names == sorted(["camera.json", "camera_mask.png", "camera_crosstalk.npz", "camera_calib_curves.png",
                            "camera_calib_nd_eff.png", "camera_calib_valid_ratio.png"]), names
    assert profile.load(out).crosstalk is not None and summary["profile"] == str(out)


def test_figures_stopped_leaves_nothing(tmp_path, monkeypatch):
    from nrhdr_core import figures

    def stopped(*a, **k):
        raise outputs.Interrupted(signal.SIGINT)
    monkeypatch.setattr(figures, "fig06", stopped)
    with pytest.raises(KeyboardInterrupt):
        figures.run(tmp_path / "figs", tiny=True, quick=True, progress=False, only=("fig02", "fig06"))
    assert list(tmp_path.iterdir()) == []


def test_simulate_flats_and_demo_stopped_leave_nothing(tmp_path, monkeypatch):
    """A stop inside the writing of `nrhdr simulate-flats` and `nrhdr demo` (in the same process): their
    temporary folders and lock files are gone, an existing folder's files are untouched."""
    from gst_plugins import cli
    from gst_plugins.cli import clip
    from nrhdr_core import calibration, profile

    def stopped(*a, **k):
        (next(x for x in a if isinstance(x, Path)) / "half.tif").write_bytes(b"x")
        raise outputs.Interrupted(signal.SIGTERM)
    monkeypatch.setattr(calibration, "_write_flats", stopped)
    (tmp_path / "flats").mkdir()
    (tmp_path / "flats" / "notes.txt").write_text("mine")
    with pytest.raises(KeyboardInterrupt):
        calibration.simulate_flats(tmp_path / "flats", profile.default(8, 8), overwrite=True, progress=False)
    assert [p.name for p in tmp_path.iterdir()] == ["flats"]
    assert [p.name for p in (tmp_path / "flats").iterdir()] == ["notes.txt"]
    monkeypatch.setattr(clip, "_run_demo", stopped)
    assert cli.main(["demo", "-o", str(tmp_path / "demo")]) == 128 + signal.SIGTERM
    assert [p.name for p in tmp_path.iterdir()] == ["flats"]
