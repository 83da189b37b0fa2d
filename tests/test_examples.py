"""The embedding examples run as subprocesses: a stub camera SDK feeding a live appsrc
with settings changed while playing, and an appsink pulling HDR frames as numpy arrays."""
from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

pytestmark = pytest.mark.gst
ROOT = Path(__file__).resolve().parents[1]


def run_example(name, args, env, timeout=240):
    """Run an example with G_DEBUG=fatal-criticals: any GStreamer-CRITICAL (e.g. "The created element should
    be floating") aborts it and fails the test."""
    env = dict(env, G_DEBUG="fatal-criticals")
    p = subprocess.run([sys.executable, str(ROOT / "examples" / name), *map(str, args)], env=env, cwd=ROOT,
                       capture_output=True, text=True, timeout=timeout)
    out = p.stdout + p.stderr
    assert "CRITICAL" not in out, out
    return p.returncode, out


def test_camera_appsrc_live_with_settings_changed_while_playing(gst_subprocess_env):
    rc, out = run_example("camera_appsrc.py", ["--frames", 18, "--fps", 18, "--width", 64, "--height", 48],
                          gst_subprocess_env)
    assert rc == 0, out
    assert "captured 18 frames, out 18; timestamps increasing: True" in out
    m = re.search(r"method preview for frames 0\.\.(\d+), nearest from frame (\d+)", out)
    assert m and 0 < int(m.group(2)) < 18, out
    m = re.search(r"mean display level ([\d.]+) before the exposure change, ([\d.]+) after", out)
    assert m and float(m.group(2)) > float(m.group(1)) + 5, out     # +2 stops brightens the display


def test_appsink_numpy_values_and_state(gst_subprocess_env, tiny_clip, tmp_path):
    d, prof, raws = tiny_clip
    npz = tmp_path / "frames.npz"
    rc, out = run_example("appsink_numpy.py", [d, "--save", npz], gst_subprocess_env)
    assert rc == 0, out
    assert f"appsink_numpy: {len(raws)} frames" in out
    f = np.load(npz)
    assert f["values"].shape == (len(raws), prof.height, prof.width) and f["values"].dtype == np.float32
    assert list(f["pts"]) == [i * 200_000_000 for i in range(len(raws))]
    scale = np.where(prof.mask, prof.nd, 1.0)
    for raw, v, st in zip(raws, f["values"], f["state"]):
        known = (st & 0x0F) == 0
        # measured pixels: paper Eq. 3, (code - black) * (ND behind a filter else 1)
        np.testing.assert_allclose(v[known], ((raw.astype(float) - prof.black_level) * scale)[known], rtol=1e-5)
        assert ((st[~known] & 0x40) != 0).all()          # every missing pixel was reconstructed
        assert np.array_equal((st & 0x80) != 0, prof.mask)
