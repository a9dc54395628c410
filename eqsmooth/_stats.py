"""Small statistics helpers without scipy: chi-square tails and quantiles,
whiteness, the information after nuisance parameters (used by the
discovery workflow and by `eqsmooth.learn`'s calibration).

Plain Python floats: these run once per test outside compiled code, where
JAX's special functions would each compile a small program on first use
(about 1.4 s of a first `discover` call; measured 2026-11-28, commit 469e178).
"""

import math
import statistics

import numpy as np


def _log_prefactor(a: float, x: float) -> float:
    return -x + a * math.log(x) - math.lgamma(a)


def gamma_q(a: float, x: float) -> float:
    """Regularised upper incomplete gamma function `Q(a, x)`, `a > 0`.

    The power series of `P = 1 − Q` where `x < a + 1` (it converges fast
    there and `Q` is not small), otherwise the continued fraction of `Q`
    (evaluated by the modified Lentz method), which keeps its relative
    accuracy far in the tail.
    """
    if not a > 0:
        raise ValueError(f"gamma_q: a must be positive, got {a}")
    if not x > 0:
        return 1.0
    if math.isinf(x):
        return 0.0
    if x < a + 1.0:
        term = total = 1.0 / a
        n = a
        for _ in range(100_000):
            n += 1.0
            term *= x / n
            total += term
            if abs(term) <= abs(total) * 1e-17:
                break
        return min(1.0, max(0.0, 1.0 - total * math.exp(_log_prefactor(a, x))))
    tiny = 1e-300
    b = x + 1.0 - a
    c = 1.0 / tiny
    d = 1.0 / b
    h = d
    for i in range(1, 100_000):
        an = -i * (i - a)
        b += 2.0
        d = an * d + b
        d = tiny if abs(d) < tiny else d
        c = b + an / c
        c = tiny if abs(c) < tiny else c
        d = 1.0 / d
        delta = d * c
        h *= delta
        if abs(delta - 1.0) <= 1e-16:
            break
    return min(1.0, max(0.0, math.exp(_log_prefactor(a, x)) * h))


def chi2_sf(x, df) -> float:
    """Upper tail `P(χ²_df > x)`."""
    if df <= 0:
        return 1.0
    x = float(x)
    if math.isnan(x):
        return math.nan
    return gamma_q(df / 2.0, max(x, 0.0) / 2.0)


def noncentral_chi2_sf(x, df, noncentrality) -> float:
    """Upper tail `P(χ²_df(λ) > x)` of the noncentral chi-square, as the
    Poisson(λ/2) mixture of central tails (summed out from the mixture's
    mode, where its weights are largest, until they stop counting)."""
    lam = float(noncentrality)
    if lam < 0 or df <= 0:
        raise ValueError(
            f"noncentral_chi2_sf: need df > 0 and noncentrality >= 0, got "
            f"df={df}, noncentrality={lam}"
        )
    if lam == 0.0:
        return chi2_sf(x, df)
    half = 0.5 * lam
    mode = int(half)

    def weight(j: int) -> float:
        return math.exp(-half + j * math.log(half) - math.lgamma(j + 1.0))

    total = 0.0
    for direction in (1, -1):
        j = mode if direction == 1 else mode - 1
        while j >= 0:
            w = weight(j)
            total += w * chi2_sf(x, df + 2 * j)
            if w < 1e-17 and abs(j - mode) > 5:
                break
            j += direction
    return min(1.0, max(0.0, total))


def detectable_noncentrality(df, level: float, power: float) -> float:
    """The noncentrality `λ` at which a `χ²_df` test at `level` rejects with
    probability `power` (bisection on [`noncentral_chi2_sf`][])."""
    if not (0.0 < level < 1.0 and 0.0 < power < 1.0):
        raise ValueError(
            f"detectable_noncentrality: level and power must lie in (0, 1), got "
            f"{level}, {power}"
        )
    return noncentrality_for_power(chi2_quantile(1.0 - level, df), df, power)


def noncentrality_for_power(crit: float, df, power: float) -> float:
    """The noncentrality `λ` at which `P(χ²_df(λ) > crit) = power`."""
    return _solve_increasing(lambda lam: noncentral_chi2_sf(crit, df, lam), power, 1.0)


def chi2_quantile(p: float, df) -> float:
    """`x` with `P(χ²_df ≤ x) = p` (bisection on [`chi2_sf`][])."""
    if not 0.0 < p < 1.0:
        raise ValueError(f"chi2_quantile: p must lie in (0, 1), got {p}")
    return _solve_increasing(lambda x: 1.0 - chi2_sf(x, df), p, max(1.0, float(df)))


def _solve_increasing(f, target: float, start: float) -> float:
    """`x ≥ 0` with `f(x) = target` for an increasing `f`: doubling from
    `start` until bracketed, then bisection to a relative 1e-12."""
    lo, hi = 0.0, start
    while f(hi) < target:
        lo, hi = hi, 2.0 * hi
    for _ in range(200):
        mid = 0.5 * (lo + hi)
        if f(mid) < target:
            lo = mid
        else:
            hi = mid
        if hi - lo <= 1e-12 * hi:
            break
    return 0.5 * (lo + hi)


def chi2_two_sided(x, df) -> float:
    """Two-sided p-value of a chi-square statistic (too small or too large)."""
    upper = chi2_sf(x, df)
    return float(min(1.0, 2.0 * min(upper, 1.0 - upper)))


def normal_two_sided(z) -> float:
    return math.erfc(abs(float(z)) / math.sqrt(2.0))


def normal_quantile(p) -> float:
    p = float(p)
    if p <= 0.0 or p >= 1.0:
        return -math.inf if p == 0.0 else math.inf if p == 1.0 else math.nan
    return statistics.NormalDist().inv_cdf(p)


def ljung_box(e, lags) -> tuple[float, float]:
    """Pooled Ljung-Box statistic of whitened series `e` `(B, T)`.

    Autocorrelations are pooled over sequences (each sequence contributes its
    own lagged products, never across sequence boundaries);
    `Q = B T (T + 2) Σ_k ρ_k² / (T − k)`, compared with `χ²(lags)`.
    """
    e = np.asarray(e, dtype=float)
    e = e - e.mean()
    B, T = e.shape
    lags = int(min(lags, T - 2))
    denom = np.sum(e * e)
    q = 0.0
    for k in range(1, lags + 1):
        rho = np.sum(e[:, k:] * e[:, :-k]) / denom
        q += rho * rho / (T - k)
    q *= B * T * (T + 2)
    return float(q), chi2_sf(q, lags)


def efficient_information(
    info: np.ndarray, test: np.ndarray, nuisance: np.ndarray
) -> np.ndarray:
    """The information of the `test` parameters after the `nuisance` ones:
    the Schur complement `I_tt − I_tn I_nn⁺ I_nt` of the information matrix
    `info` (a pseudo-inverse, since noise scales the data cannot identify
    leave `I_nn` singular)."""
    Icc = info[np.ix_(test, test)]
    if len(nuisance):
        Icn = info[np.ix_(test, nuisance)]
        Inn = info[np.ix_(nuisance, nuisance)]
        return Icc - Icn @ np.linalg.pinv(Inn) @ Icn.T
    return Icc
