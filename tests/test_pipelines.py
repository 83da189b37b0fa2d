"""The shipped pipelines (pipelines/*.sh, gst-launch-1.0 through `nrhdr launch`), `nrhdr inspect` and the
embedding example, run as subprocesses on a tiny generated clip (64x48, 5 frames)."""
from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

pytestmark = pytest.mark.gst

ROOT = Path(__file__).resolve().parents[1]
PIPELINES = ROOT / "pipelines"
VALID, RECONSTRUCTED, ATTENUATED = 0, 0x40, 0x80


def run(cmd, env, cwd=None, timeout=120):
    p = subprocess.run([str(c) for c in cmd], env=env, cwd=cwd, capture_output=True, text=True,
                       timeout=timeout)
    return p.returncode, p.stdout + p.stderr


def test_shipped_pipelines_exist_and_use_nrhdr_launch():
    names = {p.name for p in PIPELINES.glob("*.sh")}
    assert {"raw_to_png.sh", "raw_to_exr.sh", "raw_to_display.sh", "raw_to_display_headless.sh"} <= names
    for n in names - {"common.sh"}:
        text = (PIPELINES / n).read_text()
        # nr_launch: common.sh's signal-forwarding wrapper; nrhdr hdr10: the two-pass HDR10 encoder
        assert '"$NRHDR" launch' in text or "nr_launch " in text or '"$NRHDR" hdr10' in text, n
        assert (PIPELINES / n).stat().st_mode & 0o111, f"{n} is not executable"


def test_raw_to_png(gst_subprocess_env, tiny_clip, tmp_path):
    from nrhdr_core import io
    d, prof, raws = tiny_clip
    rc, out = run(["bash", PIPELINES / "raw_to_png.sh", d, tmp_path / "png"], gst_subprocess_env)
    assert rc == 0, out
    files = sorted((tmp_path / "png").glob("frame_*.png"))
    assert [f.name for f in files] == [f"frame_{i:05d}.png" for i in range(len(raws))]
    for f in files:
        img = io.read_image(f, np.uint8)
        assert img.shape == (prof.height, prof.width, 1)
        assert img.max() > img.min()


def test_raw_to_exr(gst_subprocess_env, tiny_clip, tmp_path):
    from nrhdr_core import io
    d, prof, raws = tiny_clip
    rc, out = run(["bash", PIPELINES / "raw_to_exr.sh", d, tmp_path / "exr"], gst_subprocess_env)
    assert rc == 0, out
    files = sorted((tmp_path / "exr").glob("frame_*.exr"))
    assert [f.name for f in files] == [f"frame_{i:05d}.exr" for i in range(len(raws))]
    for i, f in enumerate(files):
        v, st = io.read_exr(f)
        assert v.shape == (prof.height, prof.width) and st is not None
        # measured (valid) pixels keep Eq. 3: (code - black) * (ND if attenuated else 1)
        known = (st & 0x0F) == VALID
        scale = np.where(prof.mask, prof.nd, 1.0)
        exp = (raws[i].astype(np.float64) - prof.black_level) * scale
        np.testing.assert_allclose(v[known], exp[known], rtol=1e-5)
        assert np.array_equal((st & ATTENUATED) != 0, prof.mask)
        assert ((st[~known] & RECONSTRUCTED) != 0).all()
        assert 0 < (~known).mean() < 1


def test_raw_to_display_headless(gst_subprocess_env, tiny_clip):
    d, prof, raws = tiny_clip
    env = dict(gst_subprocess_env, SYNC="false")
    rc, out = run(["bash", PIPELINES / "raw_to_display_headless.sh", d], env)
    assert rc == 0, out
    assert "Got EOS" in out


@pytest.mark.parametrize("xdg", [None, "/nonexistent-runtime-dir"])
def test_raw_to_display_falls_back_without_a_display(gst_subprocess_env, tiny_clip, xdg):
    """Without a display (autovideosink would pick waylandsink, which crashes without XDG_RUNTIME_DIR) the
    preview script plays into fakesink, says so, and runs to EOS (in real time: 5 frames at 5 fps)."""
    d, prof, raws = tiny_clip
    env = {k: v for k, v in gst_subprocess_env.items() if k != "XDG_RUNTIME_DIR"}
    if xdg is not None:
        env["XDG_RUNTIME_DIR"] = xdg
    rc, out = run(["bash", PIPELINES / "raw_to_display.sh", d], env)
    assert rc == 0, out
    assert "Got EOS" in out and "no display" in out and "fakesink" in out


def test_pipeline_without_clip_says_how_to_make_one(gst_subprocess_env, tmp_path):
    rc, out = run(["bash", PIPELINES / "raw_to_png.sh"], gst_subprocess_env, cwd=tmp_path)
    assert rc != 0
    assert "demo_out/clip is not a clip folder" in out and "nrhdr simulate" in out


def test_nrhdr_inspect_documents_every_element(gst_subprocess_env):
    from gst_plugins import runtime
    expect = {
        "nrvalidity": ["profile", "mode", "l-min", "Filter/Converter/Video", "GRAY16_LE", "other/x-nrhdr"],
        "nrcrosstalk": ["profile", "mode", "Filter/Effect/Video"],
        "nrreconstruct": ["method", "preset", "use-bounds", "Filter/Effect/Video",
                          "changeable in NULL, READY, PAUSED or PLAYING state"],
        "nrtonemap": ["normalise", "white", "exposure", "contrast", "smoothing", "GRAY8", "GRAY16_LE",
                      "Range:"],
        "nrexrsink": ["location", "write-state", "Sink/Video"],
    }
    for name, words in expect.items():
        p = subprocess.run(["gst-inspect-1.0", name], env=runtime.gst_env(gst_subprocess_env),
                           capture_output=True, text=True, timeout=60)
        assert p.returncode == 0, p.stdout + p.stderr
        for w in words:
            assert w in p.stdout, (name, w)


def test_gst_env_and_plugin_dir():
    from gst_plugins import runtime
    env = runtime.gst_env({"PYTHONPATH": "/x", "PATH": "/usr/bin"})
    assert (runtime.plugin_dir() / "python" / "nrvalidity.py").is_file()
    assert env["GST_PLUGIN_PATH"].split(":")[0] == str(runtime.plugin_dir())
    pp = env["PYTHONPATH"].split(":")
    assert pp[0] == str(ROOT) and pp[-1] == "/x"
    import sysconfig
    assert sysconfig.get_paths()["purelib"] in pp
    assert env["GST_REGISTRY"].endswith(".bin")
    assert runtime.gst_env({"GST_REGISTRY": "/tmp/r.bin"})["GST_REGISTRY"] == "/tmp/r.bin"


def test_record_app_example(gst_subprocess_env, tiny_clip, tmp_path):
    d, prof, raws = tiny_clip
    app = ROOT / "examples" / "record_app.py"
    rc, out = run([sys.executable, app, d, tmp_path / "rec", "--method", "nearest"], gst_subprocess_env)
    assert rc == 0, out
    assert len(list((tmp_path / "rec" / "exr").glob("frame_*.exr"))) == len(raws)
    assert len(list((tmp_path / "rec" / "png").glob("frame_*.png"))) == len(raws)
    assert "reconstructed" in out
    # an error (frame size differs from the profile) ends with a message naming the element, exit 1
    (tmp_path / "bad").mkdir()
    rc, out = run([sys.executable, app, d, tmp_path / "bad", "--width", "32"], gst_subprocess_env)
    assert rc == 1, out
    assert "nrvalidity" in out and "but the stream is 32x" in out


def test_loader_and_register_all_in_one_process(gst_subprocess_env):
    """An app that sees the loader-registered elements (GST_PLUGIN_PATH) and also calls register_all():
    one class per element, no 'could not create new GType', the element works."""
    code = (
        "import os; os.environ['GST_REGISTRY_FORK'] = 'no'\n"
        "import gi; gi.require_version('Gst', '1.0')\n"
        "from gi.repository import Gst; Gst.init(None)\n"
        "f = Gst.ElementFactory.find('nrvalidity'); assert f is not None and f.get_plugin_name() == 'python'\n"
        "import gst_plugins; gst_plugins.register_all(); gst_plugins.register_all()\n"
        "e = Gst.ElementFactory.make('nrvalidity', None)\n"
        "print(type(e).__module__, e.get_name())\n"
    )
    rc, out = run([sys.executable, "-c", code], gst_subprocess_env)
    assert rc == 0, out
    assert "gst_plugins.elements.nrvalidity nrvalidity0" in out
    assert "GType" not in out and "Traceback" not in out


def test_runtime_launch_and_inspect_exit_codes(gst_subprocess_env, tiny_clip, monkeypatch, capfd):
    """runtime.launch / runtime.inspect (behind `nrhdr launch` / `nrhdr inspect`) return the tools' exit
    codes: 0 for a good pipeline, non-zero for a failing one or an unknown element."""
    from gst_plugins import runtime
    d, prof, raws = tiny_clip
    monkeypatch.setenv("GST_REGISTRY", gst_subprocess_env["GST_REGISTRY"])
    good = ["filesrc", f"location={d / 'clip.raw'}", "!", "rawvideoparse", "format=gray16-le", "width=64",
            "height=48", "framerate=5/1", "!", "nrvalidity", f"profile={d / 'camera.json'}", "!", "fakesink"]
    assert runtime.launch(good) == 0
    bad = [a.replace("width=64", "width=32") for a in good]
    assert runtime.launch(bad) != 0
    assert runtime.inspect(["nrexrsink"]) == 0
    assert runtime.inspect(["nrnosuchelement"]) != 0
    out = capfd.readouterr()
    assert "but the stream is 32x48" in out.err and "write-state" in out.out
