"""Temporal reconstruction (nrhdr_core.temporal, nrreconstruct temporal=on) against the simulator's truth:
static shots improve over frames and reuse their blocks, a known shift is found, a moving object and a
cut leave no ghost, the element restarts on a flush, and temporal=off changes nothing."""
from __future__ import annotations

import numpy as np
import pytest

from nrhdr_core import chain, profile, reconstruction, scene, sensor, simulate, validity
from nrhdr_core.states import NOISY, REASON_MASK, RECONSTRUCTED, VALID
from nrhdr_core.temporal import TemporalReconstructor

H, W = 96, 128


@pytest.fixture(scope="module")
def prof():
    return profile.default(H, W, seed=5)


@pytest.fixture(scope="module")
def views(prof):
    """Truth views (flux, linear DN) of two unrelated synthetic scenes, 40 px larger than the frame each
    way so that frames can be cut out at known offsets."""
    out = []
    for seed in (7, 11):
        sc = scene.synthetic_hdr_scene(H + 40, W + 40, seed=seed).astype(np.float32)
        out.append(sc * np.float32(simulate.exposure_scale(sc, prof, 0.0)))
    return out


def crop(view, dy=0, dx=0):
    """The frame whose content at (y, x) is view[20 + y - dy, 20 + x - dx]: content moved by (dy, dx)."""
    return np.ascontiguousarray(view[20 - dy:20 - dy + H, 20 - dx:20 - dx + W])


def frame(prof, flux, rng):
    raw = sensor.capture(flux, prof, rng)
    return validity.classify(raw, prof, dark_policy="weighted")


def log_err(truth, out, prof):
    """Mean squared log2 error (stops^2) up to the ND pixels' white."""
    t = np.log2(np.clip(truth, 1.0, prof.white))
    o = np.log2(np.clip(out, 1.0, prof.white))
    return (o - t) ** 2


def run(prof, fluxes, temporal, seed=3):
    """Outputs and reports of a clip: reconstructed alone (temporal None) or with `temporal`."""
    rng = np.random.default_rng(seed)
    outs, reps = [], []
    for f in fluxes:
        v, s = frame(prof, f, rng)
        if temporal is None:
            reconstruction.reconstruct_frame(v, s, method="fse", preset="fast", noise=prof)
            reps.append(None)
        else:
            reps.append(temporal.process(v, s, noise=prof))
        outs.append((v, s))
    return outs, reps


def test_static_error_drops_over_frames_below_single_frame(prof, views):
    """Below the regular pixels' clip (where noise dominates the error) the error falls frame after frame
    to well below single-frame; above it (the reconstruction's model error dominates) it is no worse."""
    fluxes = [crop(views[0])] * 8
    alone, _ = run(prof, fluxes, None)
    tr = TemporalReconstructor(method="fse", preset="fast")
    temp, reps = run(prof, fluxes, tr)
    lit = fluxes[0] < prof.regular_white
    e_alone = [log_err(f, v, prof) for f, (v, _) in zip(fluxes, alone)]
    e_temp = [log_err(f, v, prof) for f, (v, _) in zip(fluxes, temp)]
    assert reps[0]["reset"] and not any(r["reset"] for r in reps[1:])
    np.testing.assert_array_equal(e_temp[0], e_alone[0])       # the first frame is a frame alone
    low_t = [e[lit].mean() for e in e_temp]
    low_a = [e[lit].mean() for e in e_alone]
    assert low_t[7] < low_t[3] < low_t[1] < low_t[0]           # better as the past grows
    assert np.mean(low_t[4:]) < 0.4 * np.mean(low_a[4:])       # well below single-frame
    assert np.mean([e[~lit].mean() for e in e_temp[1:]]) <= 1.03 * np.mean([e[~lit].mean() for e in e_alone[1:]])


def test_steady_shot_reuses_most_blocks_and_reports_work(prof, views):
    fluxes = [crop(views[0])] * 8
    tr = TemporalReconstructor(method="fse", preset="fast")
    out, reps = run(prof, fluxes, tr)
    last = reps[-1]
    assert last["reused"] > 0.6 and last["fresh"] < 0.05 and not last["cut"]
    assert last["motion"] == (0.0, 0.0)
    shares = ("fresh", "refreshed", "reused", "no_prior", "no_evidence")
    assert sum(last[k] for k in shares) == pytest.approx(1.0)
    v, s = out[-1]
    miss = (s & REASON_MASK) != VALID
    assert last["missing"] == int(miss.sum())                   # every missing pixel written ...
    assert np.all(s[miss] & RECONSTRUCTED) and not np.any(s[~miss] & RECONSTRUCTED)   # ... and flagged
    assert np.isfinite(v).all()


@pytest.mark.parametrize("shift", [(0, 3), (-2, 5), (4, -1)])
def test_known_global_shift_is_recovered(prof, views, shift):
    tr = TemporalReconstructor()
    _, reps = run(prof, [crop(views[0]), crop(views[0], *shift)], tr)
    assert reps[1]["motion"] == (float(shift[0]), float(shift[1]))
    assert not reps[1]["cut"] and reps[1]["fresh"] < 0.3       # the shifted past is trusted


def test_moving_object_leaves_no_ghost(prof, views):
    """A bright square moves 12 px a frame over a still background: where it was, the temporal output is
    no worse than single-frame."""
    bg = crop(views[0])
    peak = float(np.percentile(bg, 99.5))

    def with_square(i):
        f = bg.copy()
        f[30:50, 10 + 12 * i:30 + 12 * i] = peak * 4
        return f

    fluxes = [with_square(i) for i in range(6)]
    alone, _ = run(prof, fluxes, None)
    temp, reps = run(prof, fluxes, TemporalReconstructor())
    assert not any(r["cut"] for r in reps) and reps[-1]["motion"] == (0.0, 0.0)
    assert reps[-1]["reused"] > 0.5 and reps[-1]["fresh"] + reps[-1]["no_prior"] > 0   # the square's blocks
    for i in range(1, 6):
        old = np.zeros((H, W), bool)
        old[26:54, 6 + 12 * (i - 1):34 + 12 * (i - 1)] = True   # the square's last position and its rim
        old[30:50, 10 + 12 * i:30 + 12 * i] = False             # minus where it is now
        e_t = log_err(fluxes[i], temp[i][0], prof)[old].mean()
        e_a = log_err(fluxes[i], alone[i][0], prof)[old].mean()
        assert e_t <= e_a * 1.05 + 1e-4, (i, e_t, e_a)


def test_cut_resets_to_single_frame(prof, views):
    """A cut to an unrelated scene: the frame is reconstructed alone, bit for bit, and nothing of the old
    scene survives."""
    rng = np.random.default_rng(9)
    tr = TemporalReconstructor()
    for _ in range(4):
        tr.process(*frame(prof, crop(views[0]), rng), noise=prof)
    v, s = frame(prof, crop(views[1]), rng)
    v1, s1 = v.copy(), s.copy()
    rep = tr.process(v, s, noise=prof)
    assert rep["cut"] and rep["reset"]
    reconstruction.reconstruct_frame(v1, s1, method="fse", preset="fast", noise=prof)
    np.testing.assert_array_equal(v, v1)
    np.testing.assert_array_equal(s, s1)
    rep2 = tr.process(*frame(prof, crop(views[1]), rng), noise=prof)
    assert not rep2["cut"] and rep2["fresh"] < 0.3                 # the new scene is the past now


def test_reset_forgets_the_past(prof, views):
    rng = np.random.default_rng(4)
    tr = TemporalReconstructor()
    for _ in range(3):
        tr.process(*frame(prof, crop(views[0]), rng), noise=prof)
    tr.reset()
    assert tr.process(*frame(prof, crop(views[0]), rng), noise=prof)["reset"]


def test_bad_options_are_refused():
    with pytest.raises(ValueError, match="method"):
        TemporalReconstructor(method="magic")
    with pytest.raises(TypeError, match="unknown option"):
        TemporalReconstructor(blok=8)
    with pytest.raises(ValueError, match="block"):
        TemporalReconstructor(block=0)


def test_chain_temporal_off_is_the_single_frame_path(prof, views):
    rng = np.random.default_rng(2)
    raw = sensor.capture(crop(views[0]), prof, rng)
    a = chain.process_frame(raw, prof, chain.ChainSettings(crosstalk="off"))
    v, s = validity.classify(raw, prof, dark_policy="weighted")
    reconstruction.reconstruct_frame(v, s, method="fse", preset="fast", noise=prof)
    np.testing.assert_array_equal(a[0], v)
    np.testing.assert_array_equal(a[1], s)
    with pytest.raises(ValueError, match="TemporalReconstructor"):
        chain.process_frame(raw, prof, chain.ChainSettings(crosstalk="off", temporal="on"))
    with pytest.raises(ValueError, match="temporal"):
        chain.ChainSettings(temporal="maybe")


def test_chain_temporal_on_equals_the_reconstructor(prof, views):
    rng = np.random.default_rng(2)
    raws = [sensor.capture(crop(views[0]), prof, rng) for _ in range(3)]
    s_on = chain.ChainSettings(crosstalk="off", temporal="on")
    tr_a, tr_b = chain.temporal_for(s_on), TemporalReconstructor(method="fse", preset="fast")
    for raw in raws:
        a = chain.process_frame(raw, prof, s_on, temporal=tr_a)
        v, s = validity.classify(raw, prof, dark_policy="weighted")
        tr_b.process(v, s, noise=prof)
        np.testing.assert_array_equal(a[0], v)
        np.testing.assert_array_equal(a[1], s)


# ---- nrreconstruct temporal=on ---------------------------------------------------------------------------

def test_element_temporal_matches_core_and_restarts_on_flush(gst, prof, views):
    from conftest import hdr_buffer, run_appsrc
    Gst = gst
    sec = Gst.SECOND
    rng = np.random.default_rng(6)
    frames = [frame(prof, crop(views[0]), rng) for _ in range(5)]
    bufs = [hdr_buffer(v, s, pts=i * sec // 30, duration=sec // 30) for i, (v, s) in enumerate(frames)]

    def before(i, pipeline):
        if i == 3:                        # a flush (as a flushing seek makes) before frame 3
            pad = pipeline.get_by_name("r").get_static_pad("sink")
            assert pad.send_event(Gst.Event.new_flush_start())
            assert pad.send_event(Gst.Event.new_flush_stop(True))
            seg = Gst.Segment()
            seg.init(Gst.Format.TIME)
            assert pad.send_event(Gst.Event.new_segment(seg))

    r = run_appsrc("nrreconstruct name=r method=fse preset=fast temporal=on post-stats=true",
                   f"other/x-nrhdr,width={W},height={H},framerate=30/1", bufs, before_push=before, lockstep=True)
    assert r.error is None, r.error_text
    st = r.element_messages("nrhdr-frame-stats")
    assert len(st) == 5 and {s.get_value("temporal") for s in st} == {"on"}
    fresh = [s.get_value("fresh") for s in st]
    assert fresh[0] == 1.0 and fresh[3] == 1.0                   # the first frame and the one after the flush
    assert fresh[1] < 0.3 and fresh[2] < 0.3 and fresh[4] < 0.3
    # the element's output is the core's, with the same restart
    tr = TemporalReconstructor(method="fse", preset="fast")
    for i, (v, s) in enumerate(frames):
        if i == 3:
            tr.reset()
        v, s = v.copy(), s.copy()
        tr.process(v, s, noise=validity.default_noise())
        np.testing.assert_array_equal(r.samples[i][3][0], v)
        np.testing.assert_array_equal(r.samples[i][3][1], s)


def test_element_temporal_with_method_auto_runs(gst, prof, views):
    from conftest import hdr_buffer, run_appsrc
    sec = gst.SECOND
    rng = np.random.default_rng(8)
    frames = [frame(prof, crop(views[0]), rng) for _ in range(3)]
    bufs = [hdr_buffer(v, s, pts=i * sec // 30, duration=sec // 30) for i, (v, s) in enumerate(frames)]
    r = run_appsrc("nrreconstruct method=auto temporal=on post-stats=true",
                   f"other/x-nrhdr,width={W},height={H},framerate=30/1", bufs, lockstep=True)
    assert r.error is None, r.error_text
    st = r.element_messages("nrhdr-frame-stats")
    assert len(st) == 3 and st[0].get_value("fresh") == 1.0 and st[2].get_value("fresh") < 0.3
    for _c, _p, _d, (v, s) in r.samples:
        miss = (s & REASON_MASK) != VALID
        assert np.isfinite(v).all() and np.all(s[miss] & RECONSTRUCTED)


# ---- cost follows change: reused blocks, a changed block, restarts from a steady state -------------------

def steady(prof, raw, n=7):
    """A TemporalReconstructor run over `n` frames of the same raw frame (no change at all), with the last
    output and report."""
    tr = TemporalReconstructor()
    for _ in range(n):
        v, s = validity.classify(raw, prof, dark_policy="weighted")
        rep = tr.process(v, s, noise=prof)
    return tr, v, s, rep


def test_unchanged_input_keeps_the_previous_output_of_reused_blocks(prof, views):
    """The same input again: every block is reused; missing pixels (not NOISY) keep exactly the previous
    output; measured pixels move from their previous output towards their measurement, never past it."""
    raw = sensor.capture(crop(views[0]), prof, np.random.default_rng(12))
    tr, v_prev, s_prev, rep = steady(prof, raw)
    assert rep["reused"] == 1.0 and rep["motion"] == (0.0, 0.0)
    v_in, s_in = validity.classify(raw, prof, dark_policy="weighted")
    v, s = v_in.copy(), s_in.copy()
    rep = tr.process(v, s, noise=prof)
    assert rep["reused"] == 1.0 and not rep["reset"]
    r = s_in & REASON_MASK
    kept = (r != VALID) & (r != NOISY)
    assert kept.sum() > 100
    np.testing.assert_array_equal(v[kept], v_prev[kept])
    np.testing.assert_array_equal(s, s_prev)                     # the same states and RECONSTRUCTED flags
    meas = r == VALID
    lo = np.minimum(v_prev[meas], v_in[meas])
    hi = np.maximum(v_prev[meas], v_in[meas])
    eps = 1e-6 * hi                                               # float32 rounding of the average
    assert np.all((v[meas] >= lo - eps) & (v[meas] <= hi + eps))
    assert np.any(v[meas] != v_prev[meas])                        # the average goes on


def test_a_changed_block_is_refreshed_and_the_rest_reused(prof, views):
    """One 16 x 16 block's content one stop brighter, the rest of the input unchanged: that block follows
    the new input (its measurements as they are, its missing pixels near the new truth), the others keep
    their previous output."""
    flux = crop(views[0])
    raw = sensor.capture(flux, prof, np.random.default_rng(13))
    tr, v_prev, _, _ = steady(prof, raw)
    ys, xs = slice(32, 48), slice(48, 64)
    brighter = flux.copy()
    brighter[ys, xs] *= 2
    raw2 = raw.copy()
    raw2[ys, xs] = sensor.capture(brighter, prof, np.random.default_rng(14))[ys, xs]
    v_in, s_in = validity.classify(raw2, prof, dark_policy="weighted")
    v, s = v_in.copy(), s_in.copy()
    rep = tr.process(v, s, noise=prof)
    blocks = rep["blocks"]
    assert not rep["cut"] and rep["fresh"] * blocks >= 1 and rep["reused"] * blocks >= blocks - 9
    r = s_in & REASON_MASK
    inside = np.zeros(v.shape, bool)
    inside[ys, xs] = True
    meas = inside & (r == VALID)
    np.testing.assert_array_equal(v[meas], v_in[meas])           # reconstructed alone: measurements kept
    miss = inside & (r != VALID) & (brighter < prof.regular_white) & (brighter > 4)
    err_new = np.abs(np.log2(v[miss] / brighter[miss]))
    err_old = np.abs(np.log2(v_prev[miss] / brighter[miss]))
    assert np.median(err_new) < 0.25 < np.median(err_old)
    far = np.zeros(v.shape, bool)
    far[:, 96:] = True                                            # two blocks and more from the change
    kept = far & (r != VALID) & (r != NOISY)
    np.testing.assert_array_equal(v[kept], v_prev[kept])


@pytest.mark.parametrize("how", ["reset", "cut"])
def test_restart_from_a_steady_state_is_a_frame_alone(prof, views, how):
    """From a steady state (most blocks reused), `reset()` or a cut to another scene: the frame is
    reconstructed alone, bit for bit, and the state restarts."""
    raw = sensor.capture(crop(views[0]), prof, np.random.default_rng(15))
    tr, _, _, rep = steady(prof, raw)
    assert rep["reused"] > 0.9
    if how == "reset":
        tr.reset()
        raw2 = raw
    else:
        raw2 = sensor.capture(crop(views[1]), prof, np.random.default_rng(16))
    v, s = validity.classify(raw2, prof, dark_policy="weighted")
    v1, s1 = v.copy(), s.copy()
    rep = tr.process(v, s, noise=prof)
    assert rep["reset"] and rep["cut"] == (how == "cut") and tr.frames == 1
    reconstruction.reconstruct_frame(v1, s1, method="fse", preset="fast", noise=prof)
    np.testing.assert_array_equal(v, v1)
    np.testing.assert_array_equal(s, s1)


def test_a_frame_with_a_pixel_filled_upstream_is_a_frame_alone_from_a_steady_state(prof, views):
    """From a steady state, a frame in which one missing pixel already carries RECONSTRUCTED (filled
    upstream) goes to the single-frame path: bit for bit `reconstruct_frame`'s output, with every other
    block of the input as it came (nothing of the reuse left in it)."""
    raw = sensor.capture(crop(views[0]), prof, np.random.default_rng(17))
    tr, _, _, rep = steady(prof, raw)
    assert rep["reused"] > 0.9
    v, s = validity.classify(raw, prof, dark_policy="weighted")
    miss = np.argwhere((s & REASON_MASK) != VALID)
    y, x = miss[len(miss) // 2]
    s[y, x] |= RECONSTRUCTED
    v1, s1 = v.copy(), s.copy()
    rep = tr.process(v, s, noise=prof)
    assert rep["reset"] and not rep["cut"]
    reconstruction.reconstruct_frame(v1, s1, method="fse", preset="fast", noise=prof)
    np.testing.assert_array_equal(v, v1)
    np.testing.assert_array_equal(s, s1)
