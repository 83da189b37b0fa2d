"""The paper's ideal-camera analysis (section 2.3, Fig. 3-5) from `nrhdr_core.analysis`."""
import numpy as np
import pytest

from nrhdr_core import analysis, profile


def test_known_ratio_regimes_fig4():
    nd, l_min = 6.35, 100.0
    p = profile.default(48, 48, seed=1, nd=nd, l_min=l_min, read_noise=0.0)
    fw_dn = p.full_well * p.gain  # flux in DN at full well
    # Phi' values (1 = regular full well) chosen inside each regime of Fig. 4, far from the edges
    att_lmin = l_min * nd / fw_dn             # attenuated pixels reach l_min
    reg_clip = p.clip_code / fw_dn            # regular pixels clip
    att_clip = p.clip_code * nd / fw_dn       # attenuated pixels clip
    flux = np.array([att_lmin / 3, np.sqrt(att_lmin * reg_clip), np.sqrt(reg_clip * att_clip),
                     att_clip * 1.5])
    r = analysis.snr_sweep(p, flux, np.random.default_rng(0), l_mins=(), method="linear")
    assert r["known_threshold"] == pytest.approx([0.5, 1.0, 0.5, 0.0], abs=0.01)
    assert r["known_all"] == pytest.approx([1.0, 1.0, 0.5, 0.0], abs=0.01)
    assert r["known_best"] == pytest.approx([0.5, 0.5, 0.5, 0.0], abs=0.01)
    # where both classes are valid, global SNR (valid pixels) sits below regular (Eq. 7 < Eq. 4)
    assert r["snr_global_all"][1] < r["snr_regular"][1]
    # above regular clipping only attenuated pixels remain: global = attenuated SNR
    assert r["snr_global_all"][2] == pytest.approx(r["snr_attenuated"][2], abs=0.3)


def test_reconstruction_raises_flat_field_snr_fig5():
    # Fig. 5: filling missing pixels of a noisy flat field averages noise: SNR after >= SNR of known
    p = profile.default(48, 48, seed=2, read_noise=0.0)
    fw_dn = p.full_well * p.gain
    flux = np.array([0.5 * 100 * p.nd / fw_dn])  # attenuated below l_min=100: half the pixels missing
    r = analysis.snr_sweep(p, flux, np.random.default_rng(1), modes=("threshold",), l_mins=(100.0,),
                           method="linear")
    assert r["known_threshold"][0] == pytest.approx(0.5, abs=0.01)
    assert r["snr_recon_lmin100"][0] > r["snr_global_threshold"][0]


def test_run_writes_plots(tmp_path):
    paths = analysis.run_snr_analysis(tmp_path, size=24, points=5, method="nearest")
    assert [p.name for p in paths] == ["snr.png", "known_ratio.png", "snr_analysis.json"]
    assert all(p.stat().st_size > 1000 for p in paths)
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted(p.name for p in paths)   # no temp, no lock
    (tmp_path / "notes.txt").write_text("mine")
    with pytest.raises(FileExistsError):                        # an earlier run is kept unless overwrite
        analysis.run_snr_analysis(tmp_path, size=24, points=5, method="nearest")
    analysis.run_snr_analysis(tmp_path, size=24, points=5, method="nearest", overwrite=True)
    assert (tmp_path / "notes.txt").read_text() == "mine"


def test_low_end_matches_eq4_eq5_and_expected_snr_rule():
    # far below Phi' ~ 1e-3 too the SNR is over all pixels of the class (Eq. 4, 5) and the 0 dB rule uses the
    # expected SNR
    from nrhdr_core import sensor
    p = analysis.ideal_profile(128, seed=4, nd=6.35)
    flux = np.array([1e-4, 2e-4, 6e-4, 3e-3])              # mu = 0.4 .. 12 electrons
    r = analysis.snr_sweep(p, flux, np.random.default_rng(7), modes=("all", "best"), l_mins=())
    mu = np.array(r["mu_electrons"])
    assert r["snr_regular"] == pytest.approx(sensor.snr_regular_db(mu), abs=0.6)
    assert r["snr_attenuated"] == pytest.approx(sensor.snr_attenuated_db(mu, 6.35), abs=1.0)
    # expected 0 dB rule (shot noise only, 1 DN/e-): regular valid from 1 e-, attenuated from ND e-
    exp = [0.5 * (m >= 1) + 0.5 * (m / 6.35 >= 1) for m in mu]
    assert r["known_all"] == pytest.approx(exp, abs=1e-12)
    # best pixel only: attenuated pixels count only without a regular 8-neighbour
    from scipy.ndimage import maximum_filter
    lone = float(np.mean(p.mask & ~maximum_filter(~p.mask, size=3, mode="constant")))
    assert r["known_best"] == pytest.approx([0.5 * (m >= 1) + lone * (m / 6.35 >= 1) for m in mu], abs=1e-12)
    # where only the regular class is valid, the global SNR is the regular SNR; where both are, Eq. 7
    assert np.isnan(r["snr_global_all"][0]) and r["snr_global_all"][2] == pytest.approx(r["snr_regular"][2], abs=1e-9)
    assert r["snr_global_all"][3] == pytest.approx(sensor.snr_global_db(mu[3], 6.35), abs=0.6)
