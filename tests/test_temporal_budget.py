"""Temporal reconstruction under a budget (`TemporalReconstructor(budget=...)`, nrreconstruct temporal-budget;
docs/TEMPORAL.md "Budget"): a shot starts from the preview, the blocks refined a frame give FSE at most
`budget` blocks' worth of work,
the refinement is deterministic and converges to the unbounded temporal output on a static shot, cuts
restart from the preview, the element equals the core and batch equals the element."""
from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

from nrhdr_core import chain, profile, reconstruction, scene, sensor, simulate, validity
from nrhdr_core.states import NOISY, REASON_MASK, RECONSTRUCTED, VALID
from nrhdr_core.temporal import AREA_COST, MARGIN, TemporalReconstructor

sys.path.insert(0, str(Path(__file__).resolve().parent))
from test_temporal import H, W, prof  # noqa: E402, F401  (the 96 x 128 frame and its profile fixture)

BLOCKS = (H // 16) * (W // 16)          # 6 x 8 = 48 blocks of 16 x 16
BUDGET = 6
# a block's worth of FSE's work: a 16 x 16 block every pixel of which is unknown, in a band (its area with
# MARGIN rows of context above and below, AREA_COST a pixel, and its 256 unknown pixels)
BLOCK_WORK = AREA_COST * 16 * (16 + 2 * MARGIN) + 256
# the budgeted output of a settled static shot against the unbounded one, at the missing pixels: the median
# and the 90th percentile of |log2 difference| (stops). The two are not the same numbers: the budgeted run
# reconstructs a block once, from measured pixels averaged over at least 4 frames, the unbounded one
# averages the reconstructions of the first 4 frames (their clipped pixels differ most, the budgeted ones
# nearer the truth)
CONVERGED_MEDIAN, CONVERGED_P90 = 0.01, 0.05


@pytest.fixture(scope="module")
def fluxes(prof):
    """Two unrelated synthetic scenes (linear DN) of the frame's size."""
    out = []
    for seed in (7, 11):
        sc = scene.synthetic_hdr_scene(H, W, seed=seed).astype(np.float32)
        out.append(sc * np.float32(simulate.exposure_scale(sc, prof, 0.0)))
    return out


def frames(prof, flux, n, seed=3):
    """n classified frames of a static shot of `flux` (noise differs per frame)."""
    rng = np.random.default_rng(seed)
    return [validity.classify(sensor.capture(flux, prof, rng), prof, dark_policy="weighted") for _ in range(n)]


def run(tr, clip, prof):
    """Outputs and reports of `tr` over the classified frames `clip` (copies: the inputs stay)."""
    outs, reps = [], []
    for v, s in clip:
        v, s = v.copy(), s.copy()
        reps.append(tr.process(v, s, noise=prof))
        outs.append((v, s))
    return outs, reps


def alone(r):
    """The share of a frame's blocks reconstructed alone (no trusted past: outside the budget's choice)."""
    return r["fresh"] + r["no_prior"] + r["no_evidence"]


def log_err(truth, out, prof):
    return (np.log2(np.clip(out, 1.0, prof.white)) - np.log2(np.clip(truth, 1.0, prof.white))) ** 2


def test_a_budgeted_run_is_deterministic_and_keeps_its_budget(prof, fluxes):
    clip = frames(prof, fluxes[0], 10)
    a, ra = run(TemporalReconstructor(budget=BUDGET), clip, prof)
    b, rb = run(TemporalReconstructor(budget=BUDGET), clip, prof)
    for (va, sa), (vb, sb) in zip(a, b):
        np.testing.assert_array_equal(va.view(np.uint32), vb.view(np.uint32))
        np.testing.assert_array_equal(sa, sb)
    assert ra == rb
    assert all(r["work"] <= BUDGET * BLOCK_WORK for r in ra if alone(r) == 0)
    for v, s in a:
        miss = (s & REASON_MASK) != VALID
        assert np.isfinite(v).all() and np.all(s[miss] & RECONSTRUCTED)


def test_a_shot_starts_from_the_preview_alone(prof, fluxes):
    """The first frame under a budget is `reconstruct_frame` by the preview method, bit for bit."""
    (v, s), = frames(prof, fluxes[0], 1)
    v1, s1 = v.copy(), s.copy()
    rep = TemporalReconstructor(budget=BUDGET).process(v, s, noise=prof)
    assert rep["reset"] and rep["start"] == "preview" and rep["pending"] > 0.5 and rep["refined"] == 0.0
    reconstruction.reconstruct_frame(v1, s1, method="preview", noise=prof)
    np.testing.assert_array_equal(v, v1)
    np.testing.assert_array_equal(s, s1)


def test_a_budget_of_every_block_is_no_bound(prof, fluxes):
    clip = frames(prof, fluxes[0], 6)
    a, ra = run(TemporalReconstructor(budget=BLOCKS), clip, prof)
    b, _ = run(TemporalReconstructor(budget=0), clip, prof)
    assert ra[0]["start"] == "method"
    for (va, sa), (vb, sb) in zip(a, b):
        np.testing.assert_array_equal(va, vb)
        np.testing.assert_array_equal(sa, sb)


def test_refinement_converges_to_the_unbounded_output_of_a_static_shot(prof, fluxes):
    """Blocks wait at preview quality until refined, `budget` a frame; then nothing is pending, no block is
    refined any more, and the output equals the unbounded run's within CONVERGED_MEDIAN / CONVERGED_P90 and
    is no further from the truth."""
    n = 24
    clip = frames(prof, fluxes[0], n)
    a, ra = run(TemporalReconstructor(budget=BUDGET), clip, prof)
    b, _ = run(TemporalReconstructor(budget=0), clip, prof)
    pending = [r["pending"] for r in ra]
    assert pending[1] > 0.5
    assert all(p1 <= p0 + 1e-9 for p0, p1 in zip(pending[1:], pending[2:]))     # never more to do
    done = next(i for i, p in enumerate(pending) if p == 0 and i > 0)
    assert done <= 4 + BLOCKS // BUDGET + 2, pending
    assert all(r["refined"] == 0 and r["chosen"] == 0 for r in ra[-3:])          # settled: no reconstruction
    e_a, e_b = [], []
    for (va, sa), (vb, _) in zip(a[-4:], b[-4:]):
        miss = (sa & REASON_MASK) != VALID
        d = np.abs(np.log2(np.maximum(va[miss], 1.0)) - np.log2(np.maximum(vb[miss], 1.0)))
        assert np.median(d) < CONVERGED_MEDIAN and np.percentile(d, 90) < CONVERGED_P90
        e_a.append(log_err(fluxes[0], va, prof).mean())
        e_b.append(log_err(fluxes[0], vb, prof).mean())
    assert np.mean(e_a) <= 1.05 * np.mean(e_b)


def test_a_cut_restarts_from_the_preview(prof, fluxes):
    tr = TemporalReconstructor(budget=BUDGET)
    run(tr, frames(prof, fluxes[0], 14), prof)
    clip = frames(prof, fluxes[1], 3, seed=9)
    v, s = clip[0][0].copy(), clip[0][1].copy()
    rep = tr.process(v, s, noise=prof)
    assert rep["cut"] and rep["reset"] and rep["start"] == "preview"
    v1, s1 = clip[0][0].copy(), clip[0][1].copy()
    reconstruction.reconstruct_frame(v1, s1, method="preview", noise=prof)
    np.testing.assert_array_equal(v, v1)
    np.testing.assert_array_equal(s, s1)
    _, reps = run(tr, clip[1:], prof)
    assert not any(r["cut"] for r in reps) and reps[0]["pending"] > 0.5       # the new shot refines again


def test_bad_budgets_are_refused():
    for bad in (-1, 2.5, True):
        with pytest.raises(ValueError, match="budget"):
            TemporalReconstructor(budget=bad)
        with pytest.raises(ValueError, match="temporal_budget"):
            chain.ChainSettings(temporal="on", temporal_budget=bad)


def test_element_budget_matches_core_and_posts_the_refinement(gst, prof, fluxes):
    from conftest import hdr_buffer, run_appsrc
    sec = gst.SECOND
    clip = frames(prof, fluxes[0], 6, seed=6)
    bufs = [hdr_buffer(v.copy(), s.copy(), pts=i * sec // 30, duration=sec // 30) for i, (v, s) in enumerate(clip)]
    r = run_appsrc(f"nrreconstruct name=r method=fse preset=fast temporal=on temporal-budget={BUDGET} "
                   "post-stats=true", f"other/x-nrhdr,width={W},height={H},framerate=30/1", bufs, lockstep=True)
    assert r.error is None, r.error_text
    st = r.element_messages("nrhdr-frame-stats")
    core, reps = run(TemporalReconstructor(method="fse", preset="fast", budget=BUDGET), clip,
                     validity.default_noise())
    assert len(st) == len(clip)
    for i, (v, s) in enumerate(core):
        np.testing.assert_array_equal(r.samples[i][3][0], v)
        np.testing.assert_array_equal(r.samples[i][3][1], s)
        assert st[i].get_value("refined") == pytest.approx(reps[i]["refined"])
        assert st[i].get_value("pending") == pytest.approx(reps[i]["pending"])
        assert st[i].get_value("work") == pytest.approx(reps[i]["work"] / BLOCK_WORK)
    assert st[0].get_value("pending") > 0.5
    assert 0 < max(m.get_value("work") for m in st) <= BUDGET    # the posted work is in the budget's unit


@pytest.mark.gst
def test_the_element_pipeline_equals_batch_under_the_default_budget(tmp_path, gst_subprocess_env):
    """A steady shot with more blocks than the default budget (272 x 240: 255 blocks): `... ! nrreconstruct
    temporal=on ! nrexrsink` == nrhdr batch --temporal on, every pixel's bits and state byte, and the
    budget bounded the work (the first frame is the preview)."""
    from test_batch import nrhdr_batch
    from test_batch_temporal import assert_same_frames, element_exrs, sequential
    h, w = 240, 272
    assert (h // 16) * (w // 16) > chain.TEMPORAL_BUDGET
    prof = profile.default(h, w, seed=5)
    d = tmp_path / "steady"
    simulate.simulate_clip(scene.synthetic_hdr_scene(2 * h, 2 * w, seed=3), d, prof, frames=4, seed=5,
                           motion=simulate.Motion(pan=0.0, tilt=0.0, zoom=1.0, fov=0.8), progress=False)
    prof = profile.load(d / "camera.json")
    raws = np.fromfile(d / "clip.raw", "<u2").reshape(4, h, w)
    _, reports = sequential(raws, prof)
    assert reports[0]["start"] == "preview" and reports[1]["pending"] > 0
    rc, log = nrhdr_batch(d, "-o", tmp_path / "batch", "--workers", "0", "--temporal", "on", "--chunk", "10",
                          env=gst_subprocess_env)
    assert rc == 0, log
    element_exrs(d, w, h, tmp_path / "gst", gst_subprocess_env, timeout=300)
    assert_same_frames(tmp_path / "batch", tmp_path / "gst", 4)


@pytest.mark.parametrize("budget", [BUDGET, 0])
def test_a_restart_counts_every_block_with_a_pixel_not_measured_as_unsettled(prof, fluxes, budget):
    """After a frame alone every pixel not VALID averages at most one frame (fewer than `reuse_frames`): the
    blocks holding one are pending (a preview start) or refined (the method's start), counted from the input
    states."""
    v, s = frames(prof, fluxes[1], 1)[0]
    s[:, :48] = (s[:, :48] & ~np.uint8(REASON_MASK)) | VALID        # three block columns measured throughout
    share = ((s & REASON_MASK) != VALID).reshape(H // 16, 16, W // 16, 16).any(axis=(1, 3)).mean()
    assert 0 < share < 1
    rep = TemporalReconstructor(budget=budget).process(v.copy(), s.copy(), noise=prof)
    assert rep["reset"] and rep["start"] == ("preview" if budget else "method")
    assert rep["pending" if budget else "refined"] == pytest.approx(share)
    assert rep["refined" if budget else "pending"] == 0.0


def test_streams_refined_side_by_side_equal_the_streams_alone(prof, fluxes):
    """Two streams processed at the same time from two threads (as two pipelines do; the refinement's parts
    run on a shared pool) give the bits each gives alone."""
    from concurrent.futures import ThreadPoolExecutor
    clips = [frames(prof, f, 6, seed=5) for f in fluxes]
    alone = [run(TemporalReconstructor(budget=BUDGET), c, prof)[0] for c in clips]
    with ThreadPoolExecutor(2) as ex:
        both = list(ex.map(lambda c: run(TemporalReconstructor(budget=BUDGET), c, prof)[0], clips))
    for a, b in zip(alone, both):
        for (va, sa), (vb, sb) in zip(a, b):
            np.testing.assert_array_equal(va.view(np.uint32), vb.view(np.uint32))
            np.testing.assert_array_equal(sa, sb)


def test_the_default_budget_bounds_a_1080p_wide_frames_refinement_in_fse_work(prof):
    """nrreconstruct's and nrhdr batch's default (`chain.temporal_for` of the default settings): 75 blocks'
    worth of FSE's work a frame (five eighths of a 1920-wide block row every pixel of which is unknown),
    whatever the frame's size: every refining frame of a 1920-wide static shot gives FSE at most that much
    work beyond the blocks reconstructed alone, and refines whole runs of blocks (docs/TEMPORAL.md
    "Budget")."""
    h, w = 48, 1920
    p = profile.default(h, w, seed=5)
    flux = scene.synthetic_hdr_scene(h, w, seed=7).astype(np.float32)
    flux *= np.float32(simulate.exposure_scale(flux, p, 0.0))
    tr = chain.temporal_for(chain.ChainSettings(temporal="on"))
    assert tr.options["budget"] == chain.TEMPORAL_BUDGET == 75
    _, reps = run(tr, frames(p, flux, 3), p)
    blocks = reps[0]["blocks"]
    assert blocks == 3 * (w // 16) and reps[0]["start"] == "preview"
    for r in reps[1:]:
        assert round(r["chosen"] * blocks) >= w // 16 // 2
        assert alone(r) > 0 or 0 < r["work"] <= chain.TEMPORAL_BUDGET * BLOCK_WORK


def test_the_rows_where_the_preview_stands_in_most_are_refined_first(prof):
    """Under a budget of one block row, the block row with the most placeholders (missing pixels the preview
    filled: here clipped regular pixels of a bright stripe) is refined in the shot's second frame, whole,
    and a row above it with a few from the budget left then on."""
    flux = np.full((H, W), 300.0, np.float32)       # ND pixels below l-min: NOISY, unsettled in every block
    flux[20:24, 8:40] = 12000.0                     # block row 1: a few clipped regular pixels
    flux[48:64, :] = 12000.0                        # block row 3: clipped throughout
    flux *= np.float32(1.0) + np.float32(0.2) * np.sin(np.arange(W, dtype=np.float32) / 3.0)
    clip = frames(prof, flux, 3)
    outs, reps = run(TemporalReconstructor(budget=W // 16), clip, prof)
    held = ~np.isin(clip[0][1] & REASON_MASK, (VALID, NOISY))
    rows = np.arange(H)[:, None] // 16
    assert held[rows[:, 0] == 1].any() and held[rows[:, 0] == 3].sum() > 4 * held[rows[:, 0] == 1].sum()
    assert held[(rows[:, 0] != 1) & (rows[:, 0] != 3)].sum() == 0
    (v0, _), (v1, _), (v2, _) = outs
    changed = lambda a, b, r: np.mean(a[held & (rows == r)] != b[held & (rows == r)])
    assert round(reps[1]["chosen"] * reps[1]["blocks"]) >= W // 16
    assert changed(v1, v0, 3) > 0.9             # the stripe's row first, whole (the budget's rest to the next)
    assert changed(v2, v0, 1) > 0.9             # then the next


def stripe_shot(h, w, row, n):
    """The profile and n classified frames of an h x w static shot: flux 300 DN (ND pixels below l-min:
    NOISY) with a stripe of 12000 DN (regular pixels clipped) over block rows `row` and `row` + 1, rippled
    along the rows."""
    p = profile.default(h, w, seed=5)
    flux = np.full((h, w), 300.0, np.float32)
    flux[row * 16:row * 16 + 32, :] = 12000.0
    flux *= np.float32(1.0) + np.float32(0.2) * np.sin(np.arange(w, dtype=np.float32) / 3.0)
    return p, frames(p, flux, n)


def test_each_refining_frame_reconstructs_its_blocks_missing_pixels_about_once():
    """A static shot under a budget of half a block row over a clipped stripe two block rows high: every
    frame refines blocks within its budget's work (a run of one row or of the end of one and the start of the
    next) and gives the method about their own missing pixels, once (a band; windows of adjacent blocks in a
    mosaic would hold each other's missing pixels again: two to three times as many)."""
    h, w = 96, 512
    p, clip = stripe_shot(h, w, 2, 6)               # block rows 2 and 3: regular pixels clipped throughout
    budget = w // 16 // 2
    _, reps = run(TemporalReconstructor(budget=budget), clip, p)
    unknown = ((clip[0][1] & REASON_MASK) != VALID).reshape(h // 16, 16, w // 16, 16).sum(axis=(1, 3))
    most = int(unknown[2:4].max())
    assert most > 128
    for r in reps[1:]:
        refined = round(r["refined"] * r["blocks"])
        if r["refined"] > r["chosen"] or alone(r) > 0:
            continue                # (blocks a moved candidate fits, or alone: not the budget's)
        assert refined >= 1 and r["work"] <= budget * BLOCK_WORK
        assert 0 < r["reconstructed"] <= 1.25 * refined * most


def test_the_budget_bounds_fse_work_not_a_block_count():
    """A wide static shot whose blocks hold many unknown pixels (a clipped stripe), under a budget of 4
    blocks: 4 adjacent blocks of a 512-wide row cost FSE more than 4 blocks' worth (as a band, its 512
    columns of context; as a mosaic, each window holds its neighbours' unknown pixels too), so a frame
    refines fewer; every refining frame's work (`work`: the bands' and mosaics' as the band-or-mosaic
    choice counts it) stays within the budget, and the shot still settles."""
    p, clip = stripe_shot(64, 512, 1, 8)            # block rows 1 and 2: regular pixels clipped throughout
    budget = 4
    _, reps = run(TemporalReconstructor(budget=budget), clip, p)
    # (a frame whose motion estimate is not still refreshes the blocks a moved candidate fits: unbounded)
    refining = [r for r in reps[1:] if 0 < r["refined"] <= r["chosen"] and alone(r) == 0]
    assert refining
    assert all(0 < r["work"] <= budget * BLOCK_WORK for r in refining)
    assert any(round(r["chosen"] * r["blocks"]) < budget for r in refining)
    assert all(round(r["chosen"] * r["blocks"]) >= 1 for r in reps[1:] if r["pending"] > 0)
