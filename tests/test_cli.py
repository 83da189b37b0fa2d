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


def test_profile_command_sensor_format(tmp_path, capsys):
    """A 16-bit stream (the Aravis fake camera's Mono16): white level 65535, clip code one below (the paper's
    DN_max margin), what the data are written in the profile; a white level the bit depth cannot hold exits 2."""
    rc = cli.main(["profile", "-o", str(tmp_path / "cam.json"), "--width", "8", "--height", "6",
                   "--bit-depth", "16", "--black-level", "64", "--alignment", "msb", "--out-of-range", "error",
                   "--gain", "10"])
    assert rc == 0
    p = profile.load(tmp_path / "cam.json")
    assert (p.bit_depth, p.white_level, p.clip_code, p.black_level) == (16, 65535, 65534, 64.0)
    assert (p.alignment, p.out_of_range, p.gain) == ("msb", "error", 10.0)
    rc = cli.main(["profile", "-o", str(tmp_path / "bad.json"), "--width", "8", "--height", "6",
                   "--bit-depth", "10", "--white-level", "4000"])
    assert rc == 2 and "white_level" in capsys.readouterr().err and not (tmp_path / "bad.json").exists()


def test_bad_scene_file_exits_2(tmp_path, capsys):
    rc = cli.main(["simulate", str(tmp_path / "none.exr"), "-o", str(tmp_path / "c"), "--frames", "1"])
    assert rc == 2
    assert "none.exr" in capsys.readouterr().err


def test_nrhdr_core_imports_no_argparse():
    """The command line lives in gst_plugins/cli/ only: no nrhdr_core module imports argparse."""
    import ast
    from pathlib import Path
    root = Path(__file__).resolve().parents[1] / "nrhdr_core"
    found = []
    for f in sorted(root.rglob("*.py")):
        for node in ast.walk(ast.parse(f.read_text(), str(f))):
            names = ([a.name for a in node.names] if isinstance(node, ast.Import)
                     else [node.module or ""] if isinstance(node, ast.ImportFrom) else [])
            found += [f"{f.name}:{node.lineno}" for n in names if n.split(".")[0] == "argparse"]
    assert len(list(root.rglob("*.py"))) > 10 and not found, found


def test_command_table_lists_every_subcommand():
    """`cli.COMMANDS` is the one list of subcommands: the parser holds exactly those, each with its
    command function in the module the table names."""
    import argparse
    import importlib
    ap = cli.build_parser()
    sub = next(a for a in ap._actions if isinstance(a, argparse._SubParsersAction))
    assert list(sub.choices) == [name for name, _ in cli.COMMANDS]
    for name, module in cli.COMMANDS:
        mod = importlib.import_module(f"gst_plugins.cli.{module}")
        func = sub.choices[name].get_default("func")
        assert func.__module__ == mod.__name__ and func.__name__ == "cmd_" + name.replace("-", "_")


def test_warmup_compiles_through_chain_warmup_only_and_never_suggests_itself(monkeypatch, capfd):
    """`nrhdr warmup`: one `chain.warmup` call per stage line, together every stage of the chain with the
    elements' array types; no pipeline runs, so nothing printed while it compiles asks the user to run
    `nrhdr warmup` (the elements' compile report says that)."""
    from numba import njit

    from gst_plugins import runtime
    from nrhdr_core import chain
    calls = []

    temporal = []

    def fake_warmup(settings, tone=False, calibrated=True, *, stages=chain.STAGES, transfers=(), elements=False):
        calls.append((tuple(stages), tuple(transfers), elements))
        sets = [settings] if isinstance(settings, chain.ChainSettings) else list(settings)
        temporal.extend((s.method, s.temporal_budget) for s in sets if s.temporal == "on")

        @njit
        def fresh(x):          # a cold cache: one compilation per stage
            return x + 1
        fresh(len(calls))

    monkeypatch.setattr(chain, "warmup", fake_warmup)
    monkeypatch.setattr(runtime, "run_pipeline", lambda *a, **k: pytest.fail("nrhdr warmup ran a pipeline"))
    assert cli.main(["warmup"]) == 0
    out, err = capfd.readouterr()
    lines = [x for x in out.splitlines() if x.startswith("nrhdr warmup: [")]
    assert len(lines) == len(calls) == 8
    assert all("1 function(s) compiled into the cache" in x for x in lines)
    assert "run 'nrhdr warmup'" not in out + err and "numba compiled" not in out + err
    assert {s for st, _, _ in calls for s in st} == set(chain.STAGES)
    assert {t for _, tr, _ in calls for t in tr} == set(chain.TRANSFERS)
    assert all(el for _, _, el in calls)
    # nrreconstruct temporal=on with every method, with and without a refinement budget
    assert {m for m, _ in temporal} == set(chain.METHODS)
    assert {b == 0 for _, b in temporal} == {True, False}
    assert cli.main(["warmup", "--check"]) == 1       # each stage compiled: the cache was cold
