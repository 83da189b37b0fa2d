"""`nrhdr env` then plain gst-launch-1.0 in a clean shell (only PATH and HOME set), as the README's recipe
says."""
from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

pytestmark = pytest.mark.gst
ROOT = Path(__file__).resolve().parents[1]


def test_nrhdr_env_then_plain_gst_launch(tiny_clip, tmp_path):
    if shutil.which("gst-launch-1.0") is None:
        pytest.skip("gst-launch-1.0 not installed")
    d, prof, raws = tiny_clip
    clean = {"PATH": "/usr/bin:/bin", "HOME": str(tmp_path / "home"), "XDG_CACHE_HOME": str(tmp_path / "cache")}
    # `nrhdr env` as the venv's command would run it (this checkout first on sys.path)
    p = subprocess.run([sys.executable, "-m", "gst_plugins.cli", "env"], cwd=ROOT, capture_output=True,
                       text=True, env=dict(clean, PYTHONPATH=str(ROOT)), timeout=60)
    assert p.returncode == 0, p.stderr
    exports = p.stdout
    names = [ln.split("=", 1)[0] for ln in exports.splitlines()]
    assert names == ["export GST_PLUGIN_PATH", "export PYTHONPATH", "export GST_REGISTRY"]
    assert "site-packages" in exports and str(tmp_path / "cache") in exports
    out = tmp_path / "png"
    out.mkdir()
    script = (f'eval "$(cat {tmp_path / "exports.sh"})"\n'
              f"gst-launch-1.0 -e filesrc location={d / 'clip.raw'} ! rawvideoparse format=gray16-le "
              f"width={prof.width} height={prof.height} framerate=5/1 'plane-strides=<{2 * prof.width}>' ! "
              f"nrvalidity profile={d / 'camera.json'} ! nrcrosstalk ! nrreconstruct method=preview ! "
              f"nrtonemap ! videoconvert ! pngenc ! multifilesink location={out}/f_%03d.png\n")
    (tmp_path / "exports.sh").write_text(exports)
    r = subprocess.run(["/bin/bash", "-c", script], env=clean, capture_output=True, text=True, timeout=180)
    assert r.returncode == 0, r.stdout + r.stderr
    assert len(list(out.glob("f_*.png"))) == len(raws)
    assert not os.path.exists(tmp_path / "home" / ".cache" / "gstreamer-1.0"), "user registry was written"


@pytest.mark.parametrize("first_import", ["import gst_plugins; gst_plugins.register_all()",
                                          "from gst_plugins.elements._common import HdrInfo"])
def test_app_in_the_same_registry_does_not_poison_it(gst_subprocess_env, tmp_path, first_import):
    """An app (venv Python, GST_REGISTRY_FORK=no, so the registry scan runs in-process) sharing the
    exports' GST_REGISTRY must cache the python plugin WITH its elements: plain gst-launch run later in the
    same shell still finds them (the registry-cache trap, caused before by half-imported modules)."""
    env = dict(gst_subprocess_env, GST_REGISTRY=str(tmp_path / "registry.bin"), GST_REGISTRY_FORK="no")
    p = subprocess.run([sys.executable, "-c", first_import], cwd=ROOT, env=env, capture_output=True, text=True,
                       timeout=120)
    assert p.returncode == 0, p.stderr
    assert (tmp_path / "registry.bin").exists()
    env.pop("GST_REGISTRY_FORK")
    p = subprocess.run(["gst-inspect-1.0", "python"], env=env, capture_output=True, text=True, timeout=120)
    for name in ("nrvalidity", "nrcrosstalk", "nrreconstruct", "nrtonemap", "nrexrsink"):
        assert name in p.stdout, p.stdout
