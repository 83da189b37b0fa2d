"""The paper's analyses of the ideal camera (section 2.3-2.4): SNR of regular, attenuated and all pixels
over flux (Fig. 3, Eq. 4-7), the share of known pixels per selection mode (Fig. 4) and the SNR after
reconstruction on flat fields (Fig. 5). Measured on simulated flat fields, drawn beside the equations."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from . import metrics, profile as profiles, reconstruction, sensor, validity


def expected_valid(flux_dn, prof) -> tuple[bool, bool]:
    """The 0 dB rule of section 2.3 / Fig. 4 applied to the *expected* SNR of each pixel class (Eq. 4, 5 with
    the profile's read noise): (regular valid, attenuated valid) for a flat field of `flux_dn` DN. Expected
    SNR = s / sqrt(g s + (g sigma_r)^2) for a signal of s DN (s = flux, or flux / ND behind the filter)."""
    g, c = prof.gain, (prof.gain * prof.read_noise) ** 2
    s0 = 0.5 * (g + np.sqrt(g * g + 4.0 * c))          # s^2 = g s + c: SNR = 0 dB
    return bool(flux_dn >= s0), bool(flux_dn / prof.nd >= s0)


def classify_expected(raw, prof, mode: str, flux_dn: float, max_clipped: float = 0.01):
    """Known pixels of a flat field for the selection modes of Fig. 3/4 with the 0 dB rule on the expected
    SNR (`expected_valid`); clipping is read from each pixel's code (section 2.3), and a class of which more
    than `max_clipped` clips is dropped whole (its unclipped rest is a truncated, biased sample). 'best'
    drops an attenuated pixel when one of its 8 neighbours is a known regular pixel. Returns (values, known)."""
    from scipy.ndimage import maximum_filter
    values, state = validity.classify(raw, prof, "all")
    clipped = (state & validity.REASON_MASK) == validity.CLIPPED
    values = ((raw.astype(np.float64) - prof.black_level) * np.where(prof.mask, prof.nd, 1.0))
    reg_ok, att_ok = expected_valid(flux_dn, prof)
    reg_ok = reg_ok and clipped[~prof.mask].mean() <= max_clipped
    att_ok = att_ok and clipped[prof.mask].mean() <= max_clipped
    reg = ~prof.mask & ~clipped & reg_ok
    att = prof.mask & ~clipped & att_ok
    if mode == "best":
        att &= ~maximum_filter(reg, size=3, mode="constant")
    elif mode != "all":
        raise ValueError(f"mode must be 'all' or 'best', got {mode!r}")
    return values, reg | att


def snr_sweep(prof, flux_norm: np.ndarray, rng: np.random.Generator, modes=("all", "best", "threshold"),
              l_mins=(), method: str | None = None, max_clipped: float = 0.01) -> dict:
    """For each normalised flux Phi' (1 = regular pixel at full well), capture a flat field and measure:
    SNR of the regular / attenuated pixels (Eq. 4, 5: over *all* pixels of the class, NaN once more than
    `max_clipped` of them clip), global SNR and known-pixel ratio per mode, and (with `method`) the global
    SNR after reconstruction for each l_min of `l_mins` (Fig. 5).

    Modes 'all' and 'best' apply the 0 dB rule to the expected SNR of the pixel class (`expected_valid`),
    as Eq. 4-7 do; SNR over a subset that passed a per-sample threshold would be biased upwards (the
    darkest samples of a class are the ones dropped). 'threshold' is the paper's practical rule: an
    attenuated pixel is known when its measured value reaches l_min (section 2.3, Fig. 9)."""
    res = {"flux": [float(f) for f in flux_norm], "snr_regular": [], "snr_attenuated": [],
           "mu_electrons": []}
    for m in modes:
        res[f"snr_global_{m}"], res[f"known_{m}"] = [], []
    for lm in l_mins:
        res[f"snr_recon_lmin{lm:g}"] = []
    for f in flux_norm:
        mu_e = f * prof.full_well
        fdn = mu_e * prof.gain
        raw = sensor.capture(np.full(prof.mask.shape, fdn), prof, rng)
        res["mu_electrons"].append(float(mu_e))
        v, s = validity.classify(raw, prof, "all")
        clipped = (s & validity.REASON_MASK) == validity.CLIPPED
        lin = (raw.astype(np.float64) - prof.black_level) * np.where(prof.mask, prof.nd, 1.0)
        for key, sel in (("snr_regular", ~prof.mask), ("snr_attenuated", prof.mask)):
            ok = sel & ~clipped
            res[key].append(_snr(lin[ok]) if ok.sum() >= (1 - max_clipped) * sel.sum() else float("nan"))
        for m in modes:
            if m == "threshold":
                v, s = validity.classify(raw, prof, m)
                k = validity.known_mask(s)
                vals = v
            else:
                vals, k = classify_expected(raw, prof, m, fdn, max_clipped)
            res[f"snr_global_{m}"].append(_snr(vals[k]))
            res[f"known_{m}"].append(float(k.mean()))
        for lm in l_mins:
            v, s = validity.classify(raw, prof, "threshold", l_min=lm)
            k = validity.known_mask(s)
            if k.all() or not k.any():
                res[f"snr_recon_lmin{lm:g}"].append(_snr(v) if k.all() else float("nan"))
                continue
            lo, up = validity.bounds(v, s)
            r = reconstruction.reconstruct(v, k, method=method or "linear", lower=lo, upper=up)
            res[f"snr_recon_lmin{lm:g}"].append(_snr(r))
    return res


def _snr(x):
    return metrics.snr_db(x) if np.size(x) > 2 else float("nan")


def ideal_profile(size: int = 96, seed: int = 0, nd: float = 6.35, l_min: float = 100.0, pattern="nonregular"):
    """The ideal camera of section 2.3: shot noise only, 1 DN per electron (no quantisation error on
    integer photon counts), 12 bit, clipping at 4094 (= full well, so Phi' = 1 is regular clipping)."""
    from . import mask as masks
    return profiles.make(masks.make_mask(pattern, size, size, seed=seed), nd=nd, l_min=l_min,
                         read_noise=0.0, gain=1.0, full_well=4094.0)


SNR_OUTPUTS = ("snr.png", "known_ratio.png", "snr_analysis.json")


def run_snr_analysis(out_dir, nd: float = 6.35, l_min: float = 100.0, seed: int = 0, size: int = 96,
                     points: int = 36, method: str = "fse", overwrite: bool = False) -> list[Path]:
    """Write snr.png (Fig. 3/5), known_ratio.png (Fig. 4) and snr_analysis.json for an ideal sensor
    (no read noise, 12 bit) with the given ND; returns the paths. Existing outputs are refused before any
    work unless `overwrite`; the three files appear together or not at all (outputs.staged_files)."""
    from . import io, outputs
    final = Path(out_dir)
    if not overwrite:
        io.refuse_existing([final / n for n in SNR_OUTPUTS])
    with outputs.staged_files(final / "snr_analysis", final) as tmp:
        _snr_files(tmp, nd, l_min, seed, size, points, method)
    return [final / n for n in SNR_OUTPUTS]


def _snr_files(out: Path, nd, l_min, seed, size, points, method) -> None:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    prof = ideal_profile(size, seed=seed, nd=nd, l_min=l_min)
    rng = np.random.default_rng(seed)
    flux = np.logspace(-4, np.log10(2 * nd), points)
    try:
        from . import fse  # noqa: F401
    except ImportError:
        method = "linear"
    r = snr_sweep(prof, flux, rng, l_mins=(100.0, 400.0), method=method)
    mu = np.array(r["mu_electrons"])
    fig, ax = plt.subplots(figsize=(7, 4.5))
    ax.semilogx(flux, sensor.snr_regular_db(mu), "k-", lw=1, label="Eq. 4 regular (ideal)")
    ax.semilogx(flux, sensor.snr_attenuated_db(mu, nd), "k--", lw=1, label="Eq. 5 attenuated (ideal)")
    ax.semilogx(flux, sensor.snr_global_db(mu, nd), "k:", lw=1, label="Eq. 7 global (ideal)")
    ax.semilogx(flux, r["snr_regular"], "o", ms=3, label="measured regular")
    ax.semilogx(flux, r["snr_attenuated"], "s", ms=3, label="measured attenuated")
    ax.semilogx(flux, r["snr_global_all"], "-", label="global, valid pixels")
    ax.semilogx(flux, r["snr_global_best"], "-", label="global, best pixel only")
    for lm in (100, 400):
        ax.semilogx(flux, r[f"snr_recon_lmin{lm}"], "-.", label=f"after {method} reconstruction, l_min={lm}")
    ax.set_xlabel("normalised radiant flux Φ' (1 = regular pixel full well)")
    ax.set_ylabel("SNR [dB]")
    ax.set_title(f"SNR of the non-regular HDR sensor, ND = {nd} (paper Fig. 3, 5)")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=7)
    fig.tight_layout()
    p1 = out / SNR_OUTPUTS[0]
    fig.savefig(p1, dpi=110)
    plt.close(fig)
    fig, ax = plt.subplots(figsize=(7, 3.5))
    for m in ("all", "best", "threshold"):
        ax.semilogx(flux, np.array(r[f"known_{m}"]) * 100, label={"all": "valid pixels",
                    "best": "best pixel only", "threshold": f"l_min = {l_min:g}"}[m])
    ax.set_xlabel("normalised radiant flux Φ'")
    ax.set_ylabel("known pixels [%]")
    ax.set_title("Ratio of known pixels (paper Fig. 4)")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    p2 = out / SNR_OUTPUTS[1]
    fig.savefig(p2, dpi=110)
    plt.close(fig)
    (out / SNR_OUTPUTS[2]).write_text(json.dumps({"nd": nd, "l_min": l_min, **r}, indent=1))
