"""`nrhdr batch --temporal on` (nrhdr_core.batch chunks; docs/BATCH.md "Temporal reconstruction in
chunks") on tiny clips (64x48): one chunk = the sequential `TemporalReconstructor` bit for bit, chunks whose
warm-up reaches the element's state (the clip's start, or a scene cut both runs reset at) = the sequential
run, the element pipeline = batch, a chunk as the unit of resume, the options' checks.

Run as a script it prints the table of docs/BATCH.md (how chunking changes a chunk's first frames):
    .venv/bin/python tests/test_batch_temporal.py
"""
from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parent))
from test_batch import assert_same_exr, exr_frames, nrhdr_batch  # noqa: E402

H, W = 48, 64


def settings(**kw):
    from nrhdr_core import chain
    return chain.ChainSettings(temporal="on", **kw)


class Recording:
    """A TemporalReconstructor that keeps the report of every frame (`chain.process_frame` calls only
    `process`)."""

    def __init__(self, tr):
        self.tr, self.reports = tr, []

    def process(self, values, state, noise=None):
        r = self.tr.process(values, state, noise=noise)
        self.reports.append(r)
        return r


def sequential(raws, prof, start=0, **kw):
    """nrreconstruct temporal=on (other settings: `kw`) over frames start.. in order: [(values, state)],
    [report]."""
    from nrhdr_core import chain
    s = settings(**kw)
    rec = Recording(chain.temporal_for(s))
    out = [chain.process_frame(raws[i], prof, s, temporal=rec) for i in range(start, len(raws))]
    return out, rec.reports


def same(a, b) -> bool:
    return np.array_equal(a[0].view(np.uint32), b[0].view(np.uint32)) and np.array_equal(a[1], b[1])


def element_exrs(clip, w, h, out, env, timeout=180) -> None:
    """`nrhdr launch filesrc ! rawvideoparse ! nrvalidity ! nrcrosstalk ! nrreconstruct method=fse preset=fast
    temporal=on ! nrexrsink write-state=true` over the clip folder's raw frames into `out`."""
    cmd = [sys.executable, "-m", "gst_plugins.cli", "launch", "-q", "filesrc", f"location={clip / 'clip.raw'}",
           "!", "rawvideoparse", "format=gray16-le", f"width={w}", f"height={h}", "framerate=30/1",
           f"plane-strides=<{2 * w}>", "!", "nrvalidity", f"profile={clip / 'camera.json'}", "!", "nrcrosstalk",
           "!", "nrreconstruct", "method=fse", "preset=fast", "temporal=on", "!", "nrexrsink",
           "write-state=true", f"location={out}/frame_%05d.exr"]
    p = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=timeout)
    assert p.returncode == 0, p.stdout + p.stderr


def assert_same_frames(a_dir, b_dir, n) -> None:
    """Folders a_dir and b_dir hold frame_00000.exr .. frame_{n-1} with the same float32 bits and states."""
    a, b = exr_frames(a_dir), exr_frames(b_dir)
    assert [f.name for f in a] == [f.name for f in b] == [f"frame_{i:05d}.exr" for i in range(n)]
    for fa, fb in zip(a, b):
        assert_same_exr(fa, fb)


def write_clip(out, raws, prof):
    """A clip folder (clip.raw, clip.json, camera.json) of the raw frames `raws`."""
    from nrhdr_core import io, profile
    out = Path(out)
    out.mkdir(parents=True)
    profile.save(prof, out / "camera.json")
    with io.RawVideoWriter(out / "clip.raw", prof.width, prof.height) as w:
        for r in raws:
            w.write(r)
    (out / "clip.json").write_text(json.dumps(
        {"format": "nrhdr-clip", "version": 1, "width": prof.width, "height": prof.height, "fps": 30,
         "frames": len(raws), "raw": "clip.raw", "pixel_format": "GRAY16_LE", "profile": "camera.json"}))
    return out


def cut_clip(out, frames=12, cut=5, seed=4):
    """A steady shot of a synthetic scene, cut at frame `cut` to the scene turned upside down (noise
    differs per frame)."""
    from nrhdr_core import profile, scene, sensor, simulate
    prof = profile.default(H, W, seed=seed)
    sc = scene.synthetic_hdr_scene(H, W, seed=3).astype(np.float32)
    a = sc * np.float32(simulate.exposure_scale(sc, prof, 0.0))
    fluxes = (a, np.ascontiguousarray(a[::-1, ::-1]))
    rng = np.random.default_rng(seed)
    raws = np.stack([sensor.capture(fluxes[i >= cut], prof, rng) for i in range(frames)])
    d = write_clip(out, raws, prof)
    return d, profile.load(d / "camera.json"), raws


@pytest.fixture(scope="module")
def steady(tmp_path_factory):
    """64x48 x 7 frames of a steady shot (a simulated clip without motion): the temporal state builds up."""
    from nrhdr_core import profile, scene, simulate
    prof = profile.default(H, W, seed=5)
    d = tmp_path_factory.mktemp("tbatch") / "steady"
    simulate.simulate_clip(scene.synthetic_hdr_scene(4 * H, 4 * W, seed=3), d, prof, frames=7, seed=5,
                           motion=simulate.Motion(pan=0.0, tilt=0.0, zoom=1.0, fov=0.8), progress=False)
    raws = np.fromfile(d / "clip.raw", "<u2").reshape(7, H, W)
    return d, profile.load(d / "camera.json"), raws


def read_out(folder, n):
    from nrhdr_core import io
    return [io.read_exr(Path(folder) / f"frame_{i:05d}.exr") for i in range(n)]


def test_the_warm_up_covers_a_steady_shot(steady):
    """After `chain.warmup` of the temporal settings (`nrhdr warmup`'s temporal stage) a steady shot, whose
    still blocks settle and are finished from the past, without a budget and under one (the frame's 12
    blocks are within the default budget: no bound), needs no kernel signature the warm-up did not make
    (argument types and array layouts: a new one is a compilation in the element, mid-stream)."""
    from numba.core.registry import CPUDispatcher

    from nrhdr_core import chain, temporal
    _d, prof, raws = steady
    chain.warmup(settings(), stages=("reconstruction",), elements=True)
    kernels = {k: f for k, f in vars(temporal).items() if isinstance(f, CPUDispatcher)}
    warm = {k: set(f.signatures) for k, f in kernels.items()}
    _out, reports = sequential(raws, prof)
    assert any(r["refreshed"] + r["reused"] > 0 for r in reports)       # the still blocks' path ran
    _out, reports = sequential(raws, prof, temporal_budget=2)            # and under a budget
    assert reports[0]["start"] == "preview" and any(r["chosen"] > 0 for r in reports[1:])
    assert {k: set(f.signatures) - warm[k] for k, f in kernels.items() if set(f.signatures) - warm[k]} == {}


def test_one_chunk_and_chunks_warmed_from_the_start_equal_the_sequential_run(steady, tmp_path):
    """One chunk over the clip (plain loop) = nrreconstruct temporal=on's core over the clip in order, bit
    for bit; chunks of 3 on 2 Dask workers whose overlap reaches frame 0 (6 >= the last chunk's start)
    compute the same state, so the same bits; with overlap 1 (and the raw frames sent by the client) a
    chunk's frames are a stream's that starts at its warm-up, and differ from the sequential run's."""
    d, prof, raws = steady
    seq, reports = sequential(raws, prof)
    assert [r["reset"] for r in reports] == [True] + [False] * (len(raws) - 1)
    assert any(r["refreshed"] + r["reused"] > 0 for r in reports)       # the past was used
    rc, log = nrhdr_batch(d, "-o", tmp_path / "one", "--workers", "0", "--temporal", "on", "--chunk", "100")
    assert rc == 0 and "in 1 chunks of 100 frames" in log and "temporal=on" in log, log
    for i, f in enumerate(read_out(tmp_path / "one", len(raws))):
        assert same(f, seq[i]), i
    rc, log = nrhdr_batch(d, "-o", tmp_path / "dask", "--workers", "2", "--temporal", "on", "--chunk", "3",
                          "--overlap", "6")
    assert rc == 0 and "in 3 chunks of 3 frames (overlap 6)" in log, log
    for i, f in enumerate(read_out(tmp_path / "dask", len(raws))):
        assert same(f, seq[i]), i
    # overlap 1, the workers sent the raw frames (--transfer data): a chunk's frames are those of a stream
    # that starts at its warm-up's first frame; from frame 3 on they differ from the sequential run
    rc, log = nrhdr_batch(d, "-o", tmp_path / "short", "--workers", "2", "--transfer", "data", "--temporal", "on",
                          "--chunk", "3", "--overlap", "1")
    assert rc == 0, log
    short = read_out(tmp_path / "short", len(raws))
    for c0 in (0, 3, 6):
        w = max(0, c0 - 1)
        stream, _ = sequential(raws, prof, start=w)
        for i in range(c0, min(c0 + 3, len(raws))):
            assert same(short[i], stream[i - w]), i
    assert all(same(short[i], seq[i]) for i in range(3))     # the first chunk starts where the clip does
    assert not same(short[3], seq[3]) and not same(short[6], seq[6])


def test_a_scene_cut_in_the_warm_up_gives_the_sequential_state(tmp_path):
    """After a frame reconstructed alone (a cut) the state is a function of that frame only: a chunk whose
    warm-up holds the cut that the sequential run resets at, and that resets there too, equals the
    sequential run from the cut on, bit for bit, however short the warm-up. Without the cut in the warm-up
    (overlap 0) the chunk's first frame is reconstructed alone where the sequential run has a past."""
    d, prof, raws = cut_clip(tmp_path / "clip", frames=12, cut=5)
    seq, reports = sequential(raws, prof)
    assert reports[5]["reset"] and reports[5]["cut"], reports[5]
    warmed, rep_w = sequential(raws, prof, start=4)                 # what the chunk at 6 with overlap 2 runs
    assert rep_w[1]["reset"]
    rc, log = nrhdr_batch(d, "-o", tmp_path / "o2", "--workers", "0", "--temporal", "on", "--chunk", "6",
                          "--overlap", "2")
    assert rc == 0, log
    out = read_out(tmp_path / "o2", len(raws))
    for i in range(len(raws)):
        assert same(out[i], seq[i]), i
    rc, log = nrhdr_batch(d, "-o", tmp_path / "o0", "--workers", "0", "--temporal", "on", "--chunk", "6",
                          "--overlap", "0")
    assert rc == 0, log
    out0 = read_out(tmp_path / "o0", len(raws))
    assert all(same(out0[i], seq[i]) for i in range(6))
    assert not same(out0[6], seq[6])


@pytest.mark.gst
def test_the_element_pipeline_equals_batch(steady, tmp_path, gst_subprocess_env):
    """`... ! nrreconstruct temporal=on ! nrexrsink` over the clip == nrhdr batch --temporal on (one chunk,
    and chunks warmed up from the clip's start), every pixel's float32 bits and state byte. Batch runs
    first: it fills numba's cache (docs/BATCH.md, numba's cache and the last bits)."""
    d, prof, raws = steady
    rc, log = nrhdr_batch(d, "-o", tmp_path / "batch", "--workers", "1", "--temporal", "on", "--chunk", "2",
                          "--overlap", "6", env=gst_subprocess_env)
    assert rc == 0, log
    element_exrs(d, W, H, tmp_path / "gst", gst_subprocess_env)
    assert_same_frames(tmp_path / "batch", tmp_path / "gst", len(raws))
    seq, _ = sequential(raws, prof)
    assert not same(seq[-1], sequential(raws[-1:], prof)[0][0])     # the past changed the last frame


def test_a_chunk_is_the_unit_of_resume(steady, tmp_path):
    """A frame missing in the middle of a chunk: the rerun recomputes that chunk whole (with its warm-up)
    and only it; the files equal the first run's. Another chunking is another output: refused, naming it."""
    d, _, raws = steady
    out = tmp_path / "out"
    args = ("--workers", "0", "--temporal", "on", "--chunk", "3", "--overlap", "1")
    rc, log = nrhdr_batch(d, "-o", out, *args)
    assert rc == 0, log
    assert json.loads((out / "batch.json").read_text())["chunks"] == {"chunk": 3, "overlap": 1}
    ref = tmp_path / "ref"
    ref.mkdir()
    for f in exr_frames(out):
        (ref / f.name).write_bytes(f.read_bytes())
    (out / "frame_00004.exr").unlink()
    kept = {f.name: f.stat().st_mtime_ns for f in exr_frames(out)}
    rc, log = nrhdr_batch(d, "-o", out, *args)
    assert rc == 0, log
    assert f"{len(raws) - 3} already done, 3 to compute in 1 chunks of 3 frames (overlap 1)" in log, log
    for name, mtime in kept.items():
        if name not in ("frame_00003.exr", "frame_00005.exr"):
            assert (out / name).stat().st_mtime_ns == mtime, name
    for f in exr_frames(ref):
        assert_same_exr(out / f.name, f)
    rc, log = nrhdr_batch(d, "-o", out, "--workers", "0", "--temporal", "on", "--chunk", "3", "--overlap", "2")
    assert rc == 2 and "chunks.overlap: 1 -> 2" in log, log
    rc, log = nrhdr_batch(d, "-o", out, "--workers", "0")
    assert rc == 2 and "settings.temporal: 'on' -> 'off'" in log, log


def test_chunk_options_are_checked(steady, tmp_path):
    d, _, _ = steady
    for opts, text in ((("--temporal", "on", "--chunk", "0"), "--chunk"),
                       (("--temporal", "on", "--overlap", "-1"), "--overlap"),
                       (("--temporal", "on", "--chunk", "2.5"), "--chunk"),
                       (("--temporal", "sometimes"), "--temporal"),
                       (("--chunk", "4"), "--chunk is for the temporal reconstruction's chunks: add --temporal on"),
                       (("--overlap", "4"), "--overlap is for the temporal")):
        rc, log = nrhdr_batch(d, "-o", tmp_path / "o", "--workers", "0", *opts)
        assert rc == 2 and text in log, (opts, log)
    assert not (tmp_path / "o").exists()


def test_a_failing_frame_fails_alone_and_restarts_the_state(steady, tmp_path):
    """Frames out = frames in: a frame that cannot be read is reported and the others are written; the frame
    after it is reconstructed alone (the state restarts, as after a cut), so from there the chunk equals a
    run that starts at that frame. A truncated last frame fails by number in a chunked run."""
    from nrhdr_core import batch
    d, prof, raws = steady

    def read(i):
        if i == 3:
            raise ValueError("frame 3 unreadable")
        return raws[i]

    got = list(batch.chunk_frames(read, batch.Chunk(1, 7, 0), prof, None, settings()))
    assert [i for i, _ in got] == list(range(1, 7))
    assert isinstance(got[2][1], ValueError)
    after, reports = sequential(raws, prof, start=4)
    assert reports[0]["reset"]
    for (i, f), g in zip(got[3:], after):
        assert same(f, g), i
    clip = tmp_path / "clip"
    clip.mkdir()
    for f in d.iterdir():
        if f.is_file():
            (clip / f.name).write_bytes(f.read_bytes())
    (clip / "clip.raw").write_bytes((clip / "clip.raw").read_bytes()[:-100])
    rc, log = nrhdr_batch(clip, "-o", tmp_path / "out", "--workers", "0", "--temporal", "on", "--chunk", "4")
    assert rc == 1 and f"frame {len(raws) - 1} of " in log and "truncated" in log, log
    assert len(exr_frames(tmp_path / "out")) == len(raws) - 1


# ---- the table of docs/BATCH.md ------------------------------------------------------------------------

def chunking_table(kind="static", height=96, width=128, frames=48, chunk=8, overlaps=(0, 2, 4, 8, 16)):
    """Per overlap and frame index j within a chunk, over the chunks whose warm-up does not reach frame 0:
    the share of pixels whose float32 bits differ from the sequential run, the largest and the RMS
    |log2 difference| (stops, values below 1 as 1), and the RMS log2 error against the simulator's truth
    (up to the ND pixels' white) of the chunked and the sequential frames."""
    import tempfile

    from nrhdr_core import batch, chain, io, profile, scene, simulate
    prof = profile.default(height, width, seed=5)
    d = Path(tempfile.mkdtemp(prefix="nrhdr-chunks-")) / "clip"
    simulate.simulate_clip(scene.synthetic_hdr_scene(4 * height, 4 * width, seed=3), d, prof, frames=frames,
                           seed=5, motion=simulate.Motion(pan={"static": 0.0, "pan": 0.03}[kind], tilt=0.0,
                                                          zoom=1.0, fov=0.8), progress=False)
    src = batch.open_source(d)
    prof = profile.load(src.profile)
    raws = [src.read(i) for i in range(frames)]
    truth = [io.read_exr(d / "truth" / f"frame_{i:05d}.exr")[0] for i in range(frames)]
    s = settings()
    chain.warmup(s)

    def run(c):
        return [o for _, o in batch.chunk_frames(raws.__getitem__, c, prof, None, s)]

    def log2(v):
        return np.log2(np.clip(v, 1.0, prof.white))

    seq = run(batch.Chunk(0, frames, 0))
    rows = {}
    for k in overlaps:
        acc = np.zeros((5, chunk))
        n = 0
        for c0 in range(chunk, frames - chunk + 1, chunk):
            if c0 - k <= 0:
                continue
            n += 1
            for j, (v, _) in enumerate(run(batch.Chunk(c0, c0 + chunk, c0 - k))):
                ref, t = seq[c0 + j][0], log2(truth[c0 + j])
                dd = np.abs(np.log2(np.maximum(v, 1)) - np.log2(np.maximum(ref, 1)))
                acc[0, j] += (v.view(np.uint32) != ref.view(np.uint32)).mean()
                acc[1, j] = max(acc[1, j], dd.max())
                acc[2, j] += (dd ** 2).mean()
                acc[3, j] += ((log2(v) - t) ** 2).mean()
                acc[4, j] += ((log2(ref) - t) ** 2).mean()
        rows[k] = (n, acc[0] / n, acc[1], np.sqrt(acc[2] / n), np.sqrt(acc[3] / n), np.sqrt(acc[4] / n))
    return rows


if __name__ == "__main__":
    for kind in ("static", "pan"):
        print(f"\n{kind}: 128x96, 48 frames, chunk 8; per frame index j in the chunk: pixels differing / max "
              f"|d log2| / RMS d log2 (stops) / RMS log2 error of chunked : sequential vs truth")
        for k, (n, share, mx, rms, e_c, e_s) in chunking_table(kind).items():
            print(f"overlap {k:2d} ({n} chunks): " + " | ".join(
                f"{100 * share[j]:.0f}% {mx[j]:.2f} {rms[j]:.3f} {e_c[j]:.3f}:{e_s[j]:.3f}" for j in range(len(share))))


def test_temporal_budget_reaches_the_reconstructor(steady, tmp_path):
    """--temporal-budget 2 (of the 64x48 frame's 12 blocks) = nrreconstruct temporal=on temporal-budget=2's
    core over the clip, bit for bit; it bounds the refinement (where only chosen blocks are refined, FSE's
    work stays within 2 blocks' worth: `temporal.AREA_COST` a pixel of the parts, 1 an unknown pixel, a block's
    worth a fully unknown block in a band with `temporal.MARGIN` rows of context) and its frames differ from
    the default budget's, which covers the whole frame; without --temporal on it is refused before any
    frame."""
    from nrhdr_core.temporal import AREA_COST, MARGIN
    d, prof, raws = steady
    seq, reports = sequential(raws, prof, temporal_budget=2)
    block_work = AREA_COST * 16 * (16 + 2 * MARGIN) + 256
    assert all(r["work"] <= 2 * block_work for r in reports
               if r["refined"] <= r["chosen"] and r["fresh"] + r["no_prior"] + r["no_evidence"] == 0)
    assert any(r["chosen"] > 0 for r in reports)
    rc, log = nrhdr_batch(d, "-o", tmp_path / "b2", "--workers", "0", "--temporal", "on", "--chunk", "100",
                          "--temporal-budget", "2")
    assert rc == 0, log
    out = read_out(tmp_path / "b2", len(raws))
    for i, f in enumerate(out):
        assert same(f, seq[i]), i
    default, _ = sequential(raws, prof)
    assert not all(same(a, b) for a, b in zip(seq, default))
    rc, log = nrhdr_batch(d, "-o", tmp_path / "off", "--workers", "0", "--temporal-budget", "2")
    assert rc == 2 and "--temporal-budget" in log and "--temporal on" in log, log
    assert not (tmp_path / "off").exists() or not any((tmp_path / "off").iterdir())
