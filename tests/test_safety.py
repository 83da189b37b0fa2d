"""Issue 9: nothing lost, nothing silent. Signals reach gst-launch children as EOS, commands never overwrite
what they did not write, calibrations are bound to their sensor, odd inputs give clear errors."""
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

from gst_plugins import cli
from nrhdr_core import io, profile

ROOT = Path(__file__).resolve().parents[1]
PIPELINES = ROOT / "pipelines"


# ---- 1. signals: `nrhdr launch` turns SIGINT/SIGTERM into EOS, no orphan ----------------------------------

def _children(pid: int) -> list[int]:
    out = []
    for task in Path(f"/proc/{pid}/task").glob("*"):
        try:
            out += [int(c) for c in (task / "children").read_text().split()]
        except OSError:
            pass
    return out


def _alive(pid: int) -> bool:
    try:
        st = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
    except OSError:
        return False
    return st != "Z"


def _wait_for(cond, timeout=60.0, step=0.1):
    t0 = time.monotonic()
    while time.monotonic() - t0 < timeout:
        if cond():
            return True
        time.sleep(step)
    return False


def _live_recording(env, prof_path, out_dir, nrhdr_cmd):
    """`nrhdr launch` of a live source (videotestsrc is-live=true) recorded by nrexrsink."""
    desc = ["videotestsrc", "is-live=true", "pattern=snow", "!",
            "video/x-raw,format=GRAY16_LE,width=64,height=48,framerate=30/1", "!",
            "nrvalidity", f"profile={prof_path}", "!", "nrreconstruct", "method=preview", "!",
            "nrexrsink", f"location={out_dir}/f_%05d.exr", "write-state=true"]
    return subprocess.Popen(nrhdr_cmd + ["launch"] + desc, env=env, stdout=subprocess.PIPE,
                            stderr=subprocess.STDOUT, text=True)


def _nrhdr_cmd():
    return [sys.executable, "-m", "gst_plugins.cli"]


def _check_recording(out_dir, prof):
    files = sorted(Path(out_dir).glob("f_*.exr"))
    assert files, "nothing recorded"
    assert [f.name for f in files] == [f"f_{i:05d}.exr" for i in range(len(files))]  # no gap
    assert not [p for p in Path(out_dir).iterdir() if p.name.startswith(".")], "temporary files left"
    for f in files:  # every file complete and readable
        v, st = io.read_exr(f)
        assert v.shape == (prof.height, prof.width) and st is not None
    return len(files)


@pytest.mark.gst
@pytest.mark.parametrize("sig,status", [(signal.SIGTERM, 143), (signal.SIGINT, 130)])
def test_launch_turns_signal_into_eos_live_source(gst_subprocess_env, tiny_clip, tmp_path, sig, status):
    d, prof, _ = tiny_clip
    env = dict(gst_subprocess_env, PYTHONPATH=f"{ROOT}{os.pathsep}{gst_subprocess_env.get('PYTHONPATH', '')}")
    p = _live_recording(env, d / "camera.json", tmp_path, _nrhdr_cmd())
    try:
        assert _wait_for(lambda: len(list(tmp_path.glob("f_*.exr"))) >= 5 or p.poll() is not None), \
            "the live recording did not start"
        assert p.poll() is None, p.communicate()[0]
        kids = _children(p.pid)
        assert kids, "no gst-launch child"
        p.send_signal(sig)          # to the wrapper's PID only (not the process group)
        out, _ = p.communicate(timeout=60)
    finally:
        if p.poll() is None:
            p.kill()
    assert p.returncode == status, out
    assert "EOS" in out, out              # gst-launch -e finished with EOS, not killed
    assert not any(_alive(k) for k in kids), "gst-launch child left running"
    n = _check_recording(tmp_path, prof)
    time.sleep(0.5)
    assert len(list(tmp_path.glob("f_*.exr"))) == n  # nothing is still recording


@pytest.mark.gst
def test_launch_child_stops_when_wrapper_is_killed_hard(gst_subprocess_env, tiny_clip, tmp_path):
    d, prof, _ = tiny_clip
    env = dict(gst_subprocess_env, PYTHONPATH=f"{ROOT}{os.pathsep}{gst_subprocess_env.get('PYTHONPATH', '')}")
    p = _live_recording(env, d / "camera.json", tmp_path, _nrhdr_cmd())
    try:
        assert _wait_for(lambda: len(list(tmp_path.glob("f_*.exr"))) >= 5 or p.poll() is not None)
        kids = _children(p.pid)
        assert kids and p.poll() is None
        p.kill()                    # SIGKILL: the wrapper cannot forward anything
        p.communicate(timeout=30)
        assert _wait_for(lambda: not any(_alive(k) for k in kids), timeout=30), "orphaned gst-launch"
    finally:
        if p.poll() is None:
            p.kill()
    _check_recording(tmp_path, prof)


@pytest.mark.gst
def test_shipped_pipeline_stops_on_sigterm(gst_subprocess_env, tmp_path):
    """pipelines/*.sh exec `nrhdr launch`, so a SIGTERM to the script's PID stops the whole pipeline."""
    from conftest import make_test_clip
    d, _, _ = make_test_clip(tmp_path / "clip", frames=300, fps=30)     # 10 s played in real time
    for sh in PIPELINES.glob("*.sh"):
        if sh.name != "common.sh":
            assert 'exec "$NRHDR" launch' in sh.read_text(), f"{sh.name} must exec nrhdr launch"
    env = dict(gst_subprocess_env, SYNC="true")
    p = subprocess.Popen(["bash", str(PIPELINES / "raw_to_display_headless.sh"), str(d)], env=env,
                         stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    try:
        assert _wait_for(lambda: bool(_children(p.pid)) or p.poll() is not None)
        kids = _children(p.pid)
        assert _wait_for(lambda: p.poll() is not None or any(
            "gst-launch" in Path(f"/proc/{k}/cmdline").read_text(errors="replace") for k in _children(p.pid)
            if Path(f"/proc/{k}/cmdline").exists()), timeout=30)
        kids = _children(p.pid)
        assert p.poll() is None
        time.sleep(1.0)
        p.send_signal(signal.SIGTERM)
        out, _ = p.communicate(timeout=60)
    finally:
        if p.poll() is None:
            p.kill()
    assert p.returncode == 143, out
    assert not any(_alive(k) for k in kids)
