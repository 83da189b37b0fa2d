"""Packaging: a LICENSE file shipped in the wheel, one version source, CLI hints that
negotiate with stock sinks, property blurbs without machine-specific timings."""
from __future__ import annotations

import re
import subprocess
import sys
import tomllib
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def test_license_file_and_wheel_metadata():
    text = (ROOT / "LICENSE").read_text()
    assert text.startswith("BSD 3-Clause License") and "Copyright (c) 2026 the nrhdr authors" in text
    proj = tomllib.loads((ROOT / "pyproject.toml").read_text())
    assert proj["project"]["license"] == "BSD-3-Clause"
    assert proj["project"]["license-files"] == ["LICENSE"]


def test_one_version_source():
    proj = tomllib.loads((ROOT / "pyproject.toml").read_text())
    assert "version" not in proj["project"] and "version" in proj["project"]["dynamic"]
    assert proj["tool"]["setuptools"]["dynamic"]["version"] == {"attr": "nrhdr_core.__version__"}
    import nrhdr_core
    assert re.fullmatch(r"\d+\.\d+\.\d+", nrhdr_core.__version__)
    p = subprocess.run([sys.executable, "-m", "gst_plugins.cli", "--version"], cwd=ROOT, capture_output=True,
                       text=True, timeout=60)
    assert p.stdout.strip() == f"nrhdr {nrhdr_core.__version__}"


def test_simulate_hint_negotiates_with_stock_sinks(tmp_path, monkeypatch, capsys):
    """The pipeline `nrhdr simulate` prints converts before the display sink (window sinks take no gray)."""
    from gst_plugins import cli
    from nrhdr_core import simulate
    monkeypatch.setattr(simulate, "simulate_clip", lambda *a, **k: {"frames": 1, "width": 32, "height": 24,
                                                                    "fps": 30})
    assert cli.main(["simulate", "-o", str(tmp_path / "c"), "--width", "32", "--height", "24"]) == 0
    out = capsys.readouterr().out
    assert "! nrtonemap ! videoconvert ! autovideosink" in out


@pytest.mark.gst
def test_blurbs_quote_no_timings(gst):
    """Timings depend on the machine: they live in docs/BENCHMARKS.md, not in gst-inspect's blurbs."""
    for name in ("nrvalidity", "nrcrosstalk", "nrreconstruct", "nrtonemap", "nrexrsink"):
        el = gst.ElementFactory.make(name, None)
        for p in el.list_properties():
            if p.owner_type == el.__gtype__:
                assert not re.search(r"\d\s*(ms|s|fps|frames/s)\b", p.blurb), (name, p.name, p.blurb)
