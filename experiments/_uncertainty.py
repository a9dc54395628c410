"""Per-sequence and per-fold scores of Gaussian estimates, shared by the
experiments' uncertainty results (disk tracking, KITTI).

The per-frame numbers (NLL, NEES, χ² CDF) come from
[`eqsmooth.learn.gaussian_calibration`][]; this module averages them per
sequence and pools the valid sequences of a fold. Scores are computed in
float64 whatever the process's JAX precision.
"""

import math

import jax
import numpy as np

import eqsmooth.learn as L


# Coverage levels of the calibration curve (0.68 for the "1σ" region).
LEVELS = (0.1, 0.2, 0.3, 0.4, 0.5, 0.6, 0.68, 0.7, 0.8, 0.9, 0.95)


def sequence_scores(error, covariance, levels=LEVELS) -> dict:
    """Per-sequence scores of errors `(N, T, d)` (truth − estimate) under
    covariances `(N, T, d, d)`. A sequence with a covariance that is not
    finite and positive definite on some frame is `valid = False` (its
    scores NaN)."""
    e = np.asarray(error, np.float64)
    c = np.asarray(covariance, np.float64)
    with jax.enable_x64(True):
        g = L.gaussian_calibration(e, c)
        frame_valid = np.asarray(g.valid)
        nees = np.asarray(g.nees)
        nll = np.asarray(g.nll)
        cdf = np.asarray(g.cdf)
    d = g.dim
    valid = frame_valid.all(axis=1)
    nees = np.where(valid[:, None], nees, np.nan)
    nll = np.where(valid[:, None], nll, np.nan)
    t = nees.shape[1]
    lo, hi = L.nees_band(d, t)
    flo, fhi = L.chi2_quantile(0.025, d), L.chi2_quantile(0.975, d)
    mean_nees = nees.mean(axis=1)
    with np.errstate(invalid="ignore"):
        return dict(
            valid=valid,
            frames=t,
            dim=d,
            nll=nll.mean(axis=1),
            nees=mean_nees,
            nees_in_band=(mean_nees >= lo) & (mean_nees <= hi),
            frames_in_band=((nees >= flo) & (nees <= fhi)).mean(axis=1),
            covered={q: (valid[:, None] & (cdf <= q)).mean(axis=1) for q in levels},
            nll_frames=nll,
        )


def fold_summary(scores: dict) -> dict:
    """One fold's pooled numbers from `sequence_scores` (valid sequences)."""
    v = scores["valid"]
    nll_frames = scores["nll_frames"][v]
    t = scores["frames"]

    def mean(a):
        return float(a[v].mean()) if v.any() else math.nan

    return dict(
        sequences=int(v.size),
        invalid_sequences=int((~v).sum()),
        nll=mean(scores["nll"]),
        nll_median_frame=float(np.median(nll_frames)) if v.any() else math.nan,
        nees=mean(scores["nees"]),
        nees_median_sequence=float(np.median(scores["nees"][v]))
        if v.any()
        else math.nan,
        sequences_in_band=mean(scores["nees_in_band"]),
        frames_in_band=mean(scores["frames_in_band"]),
        coverage={str(q): mean(c) for q, c in scores["covered"].items()},
        scored_frames_per_sequence=t,
    )
