"""The `nrhdr` command's core subcommands, in-process."""
import json

import numpy as np

from gst_plugins import cli
from nrhdr_core import io, profile


def test_simulate_synthetic_scene(tmp_path, capsys):
    rc = cli.main(["simulate", "-o", str(tmp_path / "clip"), "--frames", "2", "--width", "64",
                   "--height", "48", "--sequence", "tiff"])
    assert rc == 0
    assert (tmp_path / "clip" / "clip.raw").stat().st_size == 2 * 64 * 48 * 2
    assert io.read_image(tmp_path / "clip" / "raw_tiff" / "frame_00001.tif", np.uint16).shape == (48, 64, 1)
    assert "nrvalidity" in capsys.readouterr().out


def test_profile_command_and_regular_pattern(tmp_path):
    rc = cli.main(["profile", "-o", str(tmp_path / "cam.json"), "--width", "8", "--height", "6",
                   "--pattern", "regular", "--nd", "8"])
    assert rc == 0
    p = profile.load(tmp_path / "cam.json")
    assert p.nd == 8 and p.mask.sum() == 24 and json.loads((tmp_path / "cam.json").read_text())["nd"] == 8


def test_bad_scene_file_exits_2(tmp_path, capsys):
    rc = cli.main(["simulate", str(tmp_path / "none.exr"), "-o", str(tmp_path / "c"), "--frames", "1"])
    assert rc == 2
    assert "none.exr" in capsys.readouterr().err
