"""`make validate-crosstalk` (benchmarks/crosstalk_validation.py) never replaces the committed results with
a partial run: without natural scenes, with --quick or a subset of sensors it writes elsewhere,
and it refuses to overwrite an explicit output that exists."""

import pytest
from conftest import load_benchmark


@pytest.fixture
def bench(tmp_path, monkeypatch):
    mod = load_benchmark("crosstalk_validation", "xt_validation")
    (tmp_path / "noscenes").mkdir()
    committed = tmp_path / "results" / "crosstalk_validation.json"
    committed.parent.mkdir()
    committed.write_text('{"committed": true}\n')
    img = tmp_path / "img"
    img.mkdir()
    (img / "crosstalk_modes.png").write_bytes(b"committed plot")
    monkeypatch.setattr(mod, "SCENES_DIR", tmp_path / "noscenes")
    monkeypatch.setattr(mod, "DEFAULT_JSON", committed)
    monkeypatch.setattr(mod, "DEFAULT_IMG", img)
    monkeypatch.setattr(mod, "PARTIAL_DIR", tmp_path / "partial")
    return mod, committed, img, tmp_path


def test_partial_run_leaves_committed_results_alone(bench):
    mod, committed, img, tmp = bench
    assert mod.main(["--quick", "--sensors", "none"]) == 0
    assert committed.read_text() == '{"committed": true}\n'
    assert (img / "crosstalk_modes.png").read_bytes() == b"committed plot"
    assert (tmp / "partial" / "crosstalk_validation.json").is_file()
    assert (tmp / "partial" / "img" / "crosstalk_modes.png").is_file()


def test_explicit_existing_output_is_refused(bench, capsys):
    mod, committed, img, tmp = bench
    target = tmp / "mine.json"
    target.write_text("keep")
    assert mod.main(["--quick", "--sensors", "none", "--json", str(target)]) == 2
    assert target.read_text() == "keep"
    assert "exist" in capsys.readouterr().err
