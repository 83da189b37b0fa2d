"""benchmarks/reconstruction.py --docs: the section it writes into docs/BENCHMARKS.md from a run's rows (targets,
tables, plot), between the section's markers and nowhere else; no run needed (made-up rows)."""
import re

import pytest
from conftest import load_benchmark


@pytest.fixture(scope="module")
def bench():
    return load_benchmark("reconstruction", "bench_reconstruction")


def _row(case, image, method, psnr, seconds, known=0.5, **kw):
    return dict(case=case, image=image, method=method, psnr=psnr, ssim=psnr / 100, seconds=seconds, mpix=0.39,
                known=known, **kw)


def _rows():
    rows = []
    for im in ("a", "b"):
        for known, d in ((0.5, 0.0), (0.25, -4.0), (0.1, -8.0)):
            rows.append(_row("kodak", im, "fse balanced", 33.0 + d + (im == "b"), 0.2, known))
            rows.append(_row("kodak", im, "OpenCV FSR_FAST", 32.0 + d, 20.0, known))
        rows.append(_row("crops", im, "fse best", 31.0, 0.5))
        rows.append(_row("crops", im, "OpenCV FSR_BEST", 25.0, 24.0))
        hdr = dict(psnr_log=36.0, psnr_log_missing=31.0, clipped=0.05 if im == "a" else 0.1, dark=0.1)
        rows.append(_row("hdr", im, "fse fast", 33.0, 0.02, **hdr))
        rows.append(_row("hdr", im, "fse balanced log", 34.0, 0.07, **hdr))    # not one of the doc's rows
    rows.append(dict(case="preview640", method="fse preview", seconds=0.02, fps=50.0, psnr=30.0))
    return rows


def test_section_from_rows(bench):
    text = bench.docs_section(_rows(), 2)
    # targets from the rows: +1.5 dB over FSR_FAST at 100x its speed, FSR_BEST beaten, 50 frames/s
    assert "| FSE `balanced`: PSNR >= FSR_FAST + 0.3 dB (Kodak, 50 % known) | +1.50 dB | yes |" in text
    assert "| FSE `balanced`: >= 20x faster than FSR_FAST (Kodak, 50 %) | 100.0x | yes |" in text
    assert "| FSE `best`: PSNR >= FSR_BEST (crops) | +6.00 dB, 48x faster | yes |" in text
    assert "| FSE `preview` preset: >= 30 frames/s at 640 x 480, 50 % missing | 50.0 frames/s | yes |" in text
    # the frontier of each case in one row
    assert len(re.findall(r"^\| PSNR frontier", text, re.M)) == 1
    assert "Kodak 50 % +1.50, Kodak 25 % +1.50, Kodak 10 % +1.50, crops +6.00 dB | yes |" in text
    # the Kodak / crops table: means, ordered by Kodak 50 % PSNR, crop-only methods after, "-" where not run
    lines = [ln for ln in text.splitlines() if ln.startswith("| ")]
    order = [ln.split(" | ")[0][2:] for ln in lines if ln.endswith("(a crop) |") or ln.count("(0.") >= 3]
    assert order == ["fse balanced", "OpenCV FSR_FAST", "fse best", "OpenCV FSR_BEST"]
    assert "| fse balanced | 33.50 (0.3350) | 29.50 (0.2950) | 25.50 (0.2550) | - | 0.200 |" in text
    assert "| OpenCV FSR_BEST | - | - | - | 25.00 (0.2500) | 24 (a crop) |" in text
    # HDR captures: the doc's rows only, the scenes' clipped range
    assert "| fse fast | 33.00 | 36.00 | 31.00 | 0.3300 | 0.020 |" in text and "balanced log |" not in text
    assert "2 shared scenes, noise-free; 5.0-10.0 % clipped" in text
    assert "img/reconstruction_pareto.png" in text and "numba's default 2 threads" in text
    assert not re.search(r"\b20\d\d-\d\d-\d\d\b|\d\d:\d\d", text)       # no run date (tests/test_docs.py)


def test_write_docs_replaces_the_marked_section_only(bench, tmp_path, monkeypatch):
    (tmp_path / "docs" / "img").mkdir(parents=True)
    doc = tmp_path / "docs" / "BENCHMARKS.md"
    before, after = "# Benchmarks\n\nintro\n", "\n\n## Next\n\nkept\n"
    doc.write_text(before + "<!-- reconstruction:begin -->\nold table\n<!-- reconstruction:end -->" + after)
    png = tmp_path / "plot.png"
    png.write_bytes(b"\x89PNG made up")
    monkeypatch.setattr(bench, "ROOT", tmp_path)
    bench.write_docs(_rows(), {"threads": 2}, png)
    text = doc.read_text()
    assert text.startswith(before) and text.endswith(after) and "old table" not in text
    assert bench.docs_section(_rows(), 2) in text
    assert (tmp_path / "docs" / "img" / "reconstruction_pareto.png").read_bytes() == png.read_bytes()
    # no markers: an error, the file as it was
    doc.write_text("# Benchmarks\n")
    with pytest.raises(SystemExit, match="markers"):
        bench.write_docs(_rows(), {"threads": 2}, png)
    assert doc.read_text() == "# Benchmarks\n"
