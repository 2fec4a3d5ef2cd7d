"""`nac-ground logs calibrate`: a log-distance radio fitted to measured probes (distance, throughput).

Each probe's throughput is turned back into the SNR that gives it on average (the base radio's rate curve
averaged over its fading: monotone, so invertible between "nothing got through" and "the top rate"); probes
at either end are censored, since they only say the SNR was below or above. The SNR is then
    SNR = P_t - PL(d0) - 10 n log10(d / d0) - noise + shadowing,   shadowing ~ N(0, sigma)
and n, PL(d0) and sigma are fitted by maximum likelihood with the censored probes (a Tobit model), with 95 %
confidence intervals from the likelihood's curvature. The intervals take the probes as independent: probes
from one place share its shadowing, so for a run of a few places (a range sweep) they are too narrow. A shift
of every MCS threshold moves the SNR exactly as PL(d0) does, so positions and throughput alone cannot tell
them apart: the fit folds any MCS offset into PL(d0) and says so.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np
from scipy import optimize, special

from nac_onboard.errors import BadInput
from nac_onboard.radio.air_link import complex_normal, link_rates, rician_fade_db
from nac_onboard.radio.channel import ChannelModel

SNR_GRID_DB = np.arange(-20.0, 60.0, 0.05)
# A probe within 2 % of nothing, or within 10 % of the top rate, only says the SNR was below or above: a
# measured link tops out a little under the radio's top goodput (TCP and the shaper take their share), and MCS 6
# is 90 % of MCS 7, so little is lost by censoring that band.
CENSOR_LOW_FRACTION, CENSOR_HIGH_FRACTION = 0.02, 0.90
Z95 = 1.959964


class CalibrationError(BadInput):
    pass


def mean_rate_curve(base: ChannelModel, draws: int = 2000, seed: int = 0) -> np.ndarray:
    """The base radio's mean goodput at each SNR of SNR_GRID_DB over its Rician fading: what a probe long
    enough to average the fading measures. The rate is chosen from the SNR's mean in dB (fades faster than the
    rate adaptation, as on a moving link) and each fade meets it."""
    if not base.fading:
        return link_rates(base, SNR_GRID_DB).goodput_bps
    fade_db = rician_fade_db(base.rician_k_db, complex_normal(np.random.default_rng(seed), draws))
    truth = (SNR_GRID_DB[:, None] + fade_db[None, :]).ravel()
    estimate = np.repeat(SNR_GRID_DB + fade_db.mean(), draws)
    rates = link_rates(base, truth, estimate).goodput_bps
    return rates.reshape(len(SNR_GRID_DB), draws).mean(axis=1)


def fading_spread_db2(base: ChannelModel, curve: np.ndarray, samples_per_probe: int, probes: int = 300,
                      seed: int = 1) -> np.ndarray:
    """Per SNR of SNR_GRID_DB: the variance (dB^2) the fading leaves in a probe's inverted SNR when the probe
    averages `samples_per_probe` independent fades. Added to sigma^2 in the fit, so sigma is the shadowing's."""
    if not base.fading or samples_per_probe <= 0:
        return np.zeros(len(SNR_GRID_DB))
    coarse = SNR_GRID_DB[::20]
    shape = (len(coarse), probes, samples_per_probe)
    fade_db = rician_fade_db(base.rician_k_db, complex_normal(np.random.default_rng(seed), shape))
    mean_fade_db = float(np.mean(fade_db))
    truth = coarse[:, None, None] + fade_db
    estimate = np.broadcast_to(coarse[:, None, None] + mean_fade_db, shape)
    rates = link_rates(base, truth.ravel(), estimate.ravel()).goodput_bps.reshape(shape).mean(axis=2)
    snr, censor, _, _ = probe_snr(rates.ravel(), base, curve)
    kept = (censor == 0).reshape(len(coarse), probes)
    snr = np.where(kept, snr.reshape(len(coarse), probes), 0.0)
    count = kept.sum(axis=1)
    mean = snr.sum(axis=1) / np.maximum(count, 1)
    variance = (np.where(kept, (snr - mean[:, None]) ** 2, 0.0)).sum(axis=1) / np.maximum(count - 1, 1)
    return np.interp(SNR_GRID_DB, coarse, np.where(count >= 10, variance, 0.0))


def probe_snr(throughput_bps, base: ChannelModel, curve: np.ndarray | None = None):
    """(SNR dB per probe, -1/0/+1: censored below, measured, censored above, the two censoring SNRs)."""
    curve = mean_rate_curve(base) if curve is None else curve
    top = curve.max()
    low_rate, high_rate = CENSOR_LOW_FRACTION * top, CENSOR_HIGH_FRACTION * top
    low_snr = float(SNR_GRID_DB[np.argmax(curve >= low_rate)])
    high_snr = float(SNR_GRID_DB[np.argmax(curve >= high_rate)])
    y = np.asarray(throughput_bps, float)
    censor = np.where(y <= low_rate, -1, np.where(y >= high_rate, 1, 0))
    increasing = np.maximum.accumulate(curve) + np.arange(len(curve)) * 1e-9 * max(top, 1.0)
    snr = np.interp(y, increasing, SNR_GRID_DB)
    return snr, censor, low_snr, high_snr


def _negative_log_likelihood(params, x, snr, censor, low_snr, high_snr, fading_db2):
    a, n, log_sigma = params
    mu = a - n * x
    sigma = np.sqrt(math.exp(2 * log_sigma) + np.interp(mu, SNR_GRID_DB, fading_db2))
    z = (snr - mu) / sigma
    measured, low, high = censor == 0, censor < 0, censor > 0
    total = (-0.5 * z[measured] ** 2 - np.log(sigma[measured])).sum() - measured.sum() * 0.5 * math.log(2 * math.pi)
    total += special.log_ndtr((low_snr - mu[low]) / sigma[low]).sum()
    total += special.log_ndtr(-(high_snr - mu[high]) / sigma[high]).sum()
    return -float(total)


def _hessian(f, p, step=0.05):
    """Central differences; the step spans the likelihood's small kinks (the fading spread is interpolated on
    a 1 dB grid), which a finer one would read as curvature."""
    p = np.asarray(p, float)
    h = np.zeros((len(p), len(p)))
    for i in range(len(p)):
        for j in range(len(p)):
            e_i, e_j = np.eye(len(p))[i] * step, np.eye(len(p))[j] * step
            h[i, j] = (f(p + e_i + e_j) - f(p + e_i - e_j) - f(p - e_i + e_j) + f(p - e_i - e_j)) / (4 * step ** 2)
    return h


def fit_channel(distance_m, throughput_bps, base: ChannelModel, samples_per_probe: int = 10) -> dict:
    """Fit n, PL(d0) and sigma (see the module's text); the base radio gives everything else.
    samples_per_probe: independent fades a probe averages (a 1 s probe on a moving link: about 10)."""
    d = np.asarray(distance_m, float)
    y = np.asarray(throughput_bps, float)
    keep = np.isfinite(d) & (d > 0) & np.isfinite(y) & (y >= 0)
    d, y = d[keep], y[keep]
    curve = mean_rate_curve(base)
    snr, censor, low_snr, high_snr = probe_snr(y, base, curve)
    measured = censor == 0
    if measured.sum() < 3 or np.ptp(np.log10(d[measured])) < 0.05:
        raise CalibrationError(f"need throughput probes between nothing and the radio's top rate at 3 or more "
                               f"distances spread over some range; found {int(measured.sum())} such of {len(y)}")
    x = 10 * np.log10(d / base.ref_distance_m)
    x_mean = float(x[measured].mean())  # centred: the intercept and the slope are then nearly independent
    xc = x - x_mean
    slope, intercept = np.polyfit(xc[measured], snr[measured], 1)
    spread = np.std(snr[measured] - (intercept + slope * xc[measured]))
    start = [intercept, max(-slope, 0.5), math.log(max(spread, 0.5))]
    fading_db2 = fading_spread_db2(base, curve, samples_per_probe)

    def nll(p):
        return _negative_log_likelihood(p, xc, snr, censor, low_snr, high_snr, fading_db2)

    result = optimize.minimize(nll, start, method="Nelder-Mead",
                               options={"xatol": 1e-7, "fatol": 1e-9, "maxiter": 20_000})
    centre, n, log_sigma = result.x
    a = centre + n * x_mean
    sigma = math.exp(log_sigma)
    try:
        cov = np.linalg.inv(_hessian(nll, result.x))
        var_n, var_log_sigma = cov[1, 1], cov[2, 2]
        var_a = cov[0, 0] + x_mean ** 2 * cov[1, 1] + 2 * x_mean * cov[0, 1]
        se = np.sqrt(np.maximum([var_a, var_n, var_log_sigma], 0.0))
    except np.linalg.LinAlgError:
        se = np.full(3, math.nan)
    ref_loss = base.tx_power_dbm - base.noise_dbm - a
    residual_db = snr[measured] - (centre - n * xc[measured])
    return {
        "exponent": float(n), "exponent_ci": (float(n - Z95 * se[1]), float(n + Z95 * se[1])),
        "ref_loss_db": float(ref_loss), "ref_loss_ci_db": (float(ref_loss - Z95 * se[0]),
                                                            float(ref_loss + Z95 * se[0])),
        "sigma_db": sigma, "sigma_ci_db": _scale_interval(sigma, Z95 * se[2]),
        "probes": int(len(y)), "measured": int(measured.sum()), "censored_low": int((censor < 0).sum()),
        "censored_high": int((censor > 0).sum()), "rms_residual_db": float(np.sqrt(np.mean(residual_db ** 2))),
        "distance_min_m": float(d.min()), "distance_max_m": float(d.max()), "converged": bool(result.success),
        "note": "an MCS offset is folded into PL(d0): throughput and positions alone cannot separate them",
    }


def _scale_interval(value: float, log_half_width: float) -> tuple[float, float]:
    """value / e^w .. value * e^w. Probes that barely constrain sigma (all at a few places, little spread: a short
    run) give a w so wide that e^w overflows: the interval is then everything, 0 to infinity, not a crash."""
    if not math.isfinite(log_half_width) or log_half_width > 700:
        return 0.0, math.inf
    return value * math.exp(-log_half_width), value * math.exp(log_half_width)


def fitted_model(base: ChannelModel, fit: dict, name: str, source: str) -> ChannelModel:
    """The base radio with the fitted path loss and shadowing."""
    return dataclasses.replace(
        base, name=name, path_loss="log-distance", exponent=round(fit["exponent"], 4),
        ref_loss_db=round(fit["ref_loss_db"], 3), shadowing_sigma_db=round(fit["sigma_db"], 3), overhead_bits=0.0,
        notes=f"fitted to {fit['probes']} probes of {source} at {fit['distance_min_m']:.1f}-"
              f"{fit['distance_max_m']:.1f} m (rms residual {fit['rms_residual_db']:.2f} dB)",
        sources=f"n, PL(d0) and sigma: `nac-ground logs calibrate` on {source} (censored maximum likelihood; "
                f"95 % intervals n {fit['exponent_ci'][0]:.2f}-{fit['exponent_ci'][1]:.2f}, PL(d0) "
                f"{fit['ref_loss_ci_db'][0]:.1f}-{fit['ref_loss_ci_db'][1]:.1f} dB, sigma "
                f"{fit['sigma_ci_db'][0]:.2f}-{fit['sigma_ci_db'][1]:.2f} dB); the rest from {base.name}")
