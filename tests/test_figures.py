"""`nrhdr figures`: every figure and number, the refusal to overwrite, and the CLI."""
import json

import numpy as np
import pytest

from nrhdr_core import figures

REQUIRED = {  # figure -> quantities (substrings) that must carry the paper's value beside ours
    "fig02": ["regular: largest non-DC spectral peak", "nonregular: largest non-DC spectral peak"],
    "fig03": ["SNR_d1 - SNR_d0", "SNR_global - SNR_d0", "SNR_d0 at the lowest flux"],
    "fig04": ["mid-tones, valid pixels", "mid-tones, best pixel only"],
    "fig06": ["effective crosstalk, sensor crosstalk 1 %, ND 11"],
    "fig07": ["DN_valid", "DN_scaled", "usable share", "ND_eff (Eq. 8)", "ND measured"],
    "fig08": ["smallest ND_eff", "DR gain at 40 %", "DR gain at 20 %"],
    "fig09": ["slope of SNR_d0", "shift of SNR_d1"],
    "fig10": ["known pixels before reconstruction", "known regular pixels", "known attenuated pixels"],
}


@pytest.fixture(scope="module")
def tiny_run(tmp_path_factory):
    out = tmp_path_factory.mktemp("figs") / "out"
    nodata = tmp_path_factory.mktemp("nodata")           # Fig. 10 falls back to the synthetic scene
    doc = figures.run(out, tiny=True, data_dir=nodata, progress=False)
    return out, doc


def test_every_figure_written_and_readable(tiny_run):
    import matplotlib.image as mpimg
    out, doc = tiny_run
    names = [f"{k}.png" for k in figures.FIGURES] + ["fig08a.png", "fig08b.png"]
    for n in names:
        img = mpimg.imread(out / n)
        assert img.ndim == 3 and img.shape[0] > 100 and img.shape[1] > 100, n
        assert np.ptp(img[..., :3]) > 0.1, f"{n} is blank"
    idx = (out / "index.md").read_text()
    for k in figures.FIGURES:
        assert f"({k}.png)" in idx
    assert not [p for p in out.parent.iterdir() if p.name.startswith(".out.")], "temporary folder left"


def test_figures_json_has_paper_beside_ours(tiny_run):
    out, _ = tiny_run
    doc = json.loads((out / "figures.json").read_text())
    for fig, quantities in REQUIRED.items():
        rows = [r for r in doc["numbers"] if r["figure"] == fig]
        for q in quantities:
            hit = [r for r in rows if q in r["quantity"]]
            assert hit, f"{fig}: no number '{q}'"
            assert all(r["paper"] is not None and r["ours"] is not None for r in hit), hit


def test_numbers_follow_the_paper_where_physics_fixes_them(tiny_run):
    _, doc = tiny_run
    num = {r["quantity"]: r for r in doc["numbers"]}
    # Eq. 5 / Eq. 7 offsets of the measured curves (ideal camera)
    r = next(v for k, v in num.items() if k.startswith("SNR_d1 - SNR_d0"))
    assert r["ours"] == pytest.approx(-10 * np.log10(6.35), abs=0.6)
    # paper 2.1: the checkerboard's aliasing ambiguity defeats reconstruction, a non-regular mask does not
    zp = {m: next(v for k, v in num.items() if k.startswith(f"{m}: zone plate"))["ours"]
          for m in ("regular", "nonregular", "voidcluster")}
    assert zp["nonregular"] > zp["regular"] + 10 and zp["voidcluster"] > zp["regular"] + 10
    # Fig. 4's low end is the expected step exactly (0 dB rule on the expected SNR)
    r = next(v for k, v in num.items() if k.startswith("largest |measured - expected| known ratio"))
    assert r["ours"] == 0.0
    # Eq. 8 bookkeeping: DN_scaled = DN_valid * ND, usable share = ND_eff / ND
    dv = next(v for k, v in num.items() if "DN_valid" in k)["ours"]
    ds = next(v for k, v in num.items() if "DN_scaled = DN_valid" in k)["ours"]
    nd = next(v for k, v in num.items() if k.startswith("ND measured"))["ours"]
    assert ds == pytest.approx(dv * nd, rel=1e-3)
    # section 3.1's example: 1 % sensor crosstalk, ND 11 -> ~10 % effective
    assert num["effective crosstalk, sensor crosstalk 1 %, ND 11"]["ours"] == pytest.approx(10.0, abs=0.5)
    # the known-pixel split adds up
    k = [num[q]["ours"] for q in ("known pixels before reconstruction (l_min = 400)", "known regular pixels",
                                  "known attenuated pixels")]
    assert k[0] == pytest.approx(k[1] + k[2], abs=0.01)


def test_refuses_non_empty_folder_without_force(tmp_path):
    (tmp_path / "keep.txt").write_text("mine")
    with pytest.raises(ValueError, match="not empty"):
        figures.run(tmp_path, tiny=True, progress=False)
    assert [p.name for p in tmp_path.iterdir()] == ["keep.txt"]


def test_force_replaces_only_own_files(tmp_path):
    (tmp_path / "keep.txt").write_text("mine")
    figures.run(tmp_path, tiny=True, force=True, progress=False, only=("fig06",), data_dir=tmp_path / "x")
    assert (tmp_path / "keep.txt").read_text() == "mine"
    assert (tmp_path / "fig06.png").is_file() and (tmp_path / "figures.json").is_file()


def test_cli_figures_refuses_existing(tmp_path, capsys):
    from gst_plugins import cli
    (tmp_path / "x").write_text("x")
    assert cli.main(["figures", "-o", str(tmp_path), "--quick", "-q"]) == 2
    assert "not empty" in capsys.readouterr().err


def test_effective_crosstalk_formula():
    # section 3.1: 1 % of the light of a regular neighbour against 1/11 direct light -> 1/(1 + 9.09) ~ 9.9 %
    assert figures.effective_crosstalk(0.01, 11.0) == pytest.approx(0.01 / (0.01 + 1 / 11))
    # more ND, more effective crosstalk (Fig. 6b's curves are ordered)
    assert figures.effective_crosstalk(0.01, 32) > figures.effective_crosstalk(0.01, 6.35)
