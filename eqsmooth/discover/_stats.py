"""Small statistics helpers (chi-square tails, whiteness) without scipy."""

import jax.numpy as jnp
import jax.scipy.special as jss
import numpy as np


def chi2_sf(x, df) -> float:
    """Upper tail `P(χ²_df > x)`."""
    if df <= 0:
        return 1.0
    return float(jss.gammaincc(jnp.asarray(df / 2.0), jnp.asarray(max(x, 0.0) / 2.0)))


def chi2_two_sided(x, df) -> float:
    """Two-sided p-value of a chi-square statistic (too small or too large)."""
    upper = chi2_sf(x, df)
    return float(min(1.0, 2.0 * min(upper, 1.0 - upper)))


def normal_two_sided(z) -> float:
    return float(jss.erfc(jnp.asarray(abs(z) / np.sqrt(2.0))))


def normal_quantile(p) -> float:
    return float(jss.ndtri(jnp.asarray(p)))


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
