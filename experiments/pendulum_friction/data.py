"""The MultiArm-Pendulum recording: segments, calibration, sequences.

Kaheman et al. 2022, one arm swinging freely, angle and a filtered angular
velocity sampled at 1 kHz (see `../shared/data/README.md`).
"""

from pathlib import Path

import numpy as np

import eqsmooth.discover as dc

from .._data import data_root


DEFAULT_DATA = data_root() / "pendulum" / "single_pendulum_freeswing_1khz.mat"
SOURCE = "https://github.com/dynamicslab/MultiArm-Pendulum"


def load_segments(path: Path) -> dict:
    """The identification and validation segments as `(S, 2, N)` arrays.

    Row 0 is the angle θ [rad] (hanging equilibrium near π), row 1 the
    angular velocity [rad/s]; all segments are cut to the shortest length.
    """
    from scipy.io import loadmat
    from scipy.io.matlab import MatReadError

    try:
        mat = loadmat(str(path))
    except (MatReadError, ValueError, OSError, TypeError) as err:
        raise ValueError(
            f"{path}: not a MATLAB file of the MultiArm-Pendulum recording ({err})"
        ) from None
    missing = [k for k in ("Y_id", "Y_vad", "dt") if k not in mat]
    if missing:
        raise ValueError(
            f"{path}: the recording lacks {missing}; expected the MultiArm-Pendulum "
            f"benchmark's single_pendulum_freeswing_1khz.mat ({SOURCE}) with Y_id "
            "(identification segments), Y_vad (validation segments) and dt"
        )
    ident = [np.asarray(a[0], float) for a in mat["Y_id"]]
    valid = [np.asarray(a[0], float) for a in mat["Y_vad"]]
    n = min(a.shape[1] for a in ident + valid)
    dt = float(np.asarray(mat["dt"]).ravel()[0])
    return {
        "identification": np.stack([a[:, :n] for a in ident]),
        "validation": np.stack([a[:, :n] for a in valid]),
        "dt": dt,
    }


def angle_noise_std(theta: np.ndarray, window: int = 21) -> float:
    """Standard deviation of the 1 kHz angle about a local cubic fit.

    A Savitzky-Golay residual: over `window` ms the motion is a smooth cubic,
    so what is left is sensor noise (corrected for the fit's degrees of
    freedom).
    """
    from scipy.signal import savgol_filter

    r = np.concatenate([a - savgol_filter(a, window, 3) for a in theta])
    return float(np.std(r) * np.sqrt(window / (window - 4)))


def swing_extrema(phi: np.ndarray, omega: np.ndarray, dt: float) -> np.ndarray:
    """Times and angles `(E, 2)` of the turning points of one segment.

    Turning points are where the velocity row changes sign; each is refined
    by a parabola fitted to ±30 ms of the angle.
    """
    idx = np.nonzero(np.sign(omega[1:]) != np.sign(omega[:-1]))[0]
    keep: list[int] = []
    for i in idx:
        if not keep or i - keep[-1] > 100:
            keep.append(int(i))
    out = []
    for i in keep:
        lo, hi = i - 30, i + 31
        if lo < 0 or hi > phi.size:
            continue
        c = np.polyfit((np.arange(lo, hi) - i) * dt, phi[lo:hi], 2)
        tv = -c[1] / (2 * c[0])
        out.append((i * dt + tv, np.polyval(c, tv)))
    return np.asarray(out)


def calibrate(segments: np.ndarray, dt: float) -> dict:
    """Rest offset and ω0² of the ideal pendulum from the swings.

    Offset: the centre of three successive turning points,
    (e₋ + 2e₀ + e₊)/4, which cancels a slowly decaying amplitude. Stiffness:
    the full period between turning points k−1 and k+1 against the ideal
    pendulum's period 4 K(sin²(A/2)) / ω0 at amplitude A. Friction changes
    neither to first order (viscous damping shifts the period by γ²/8ω0²,
    about 1e-5 here).
    """
    from scipy.special import ellipk

    offsets, w2 = [], []
    for seg in segments:
        ext = swing_extrema(seg[0] - np.pi, seg[1], dt)
        mid = (ext[:-2, 1] + 2 * ext[1:-1, 1] + ext[2:, 1]) / 4
        period = ext[2:, 0] - ext[:-2, 0]
        amp = (
            np.abs(ext[:-2, 1] - mid)
            + 2 * np.abs(ext[1:-1, 1] - mid)
            + np.abs(ext[2:, 1] - mid)
        ) / 4
        offsets.append(mid)
        w2.append((4 * ellipk(np.sin(amp / 2) ** 2) / period) ** 2)
    offsets, w2 = np.concatenate(offsets), np.concatenate(w2)
    return {
        "offset": float(np.mean(offsets)),
        "offset_spread": float(np.std(offsets)),
        "omega0_sq": float(np.mean(w2)),
        "omega0_sq_spread": float(np.std(w2)),
        "cycles": int(w2.size),
    }


def windows(segments: np.ndarray, length: int, per_segment: int) -> np.ndarray:
    """`per_segment` consecutive windows of `length` raw samples from every
    segment, as one `(W, 2, length)` array."""
    out = []
    for seg in segments:
        for k in range(per_segment):
            w = seg[:, k * length : (k + 1) * length]
            if w.shape[1] < length:
                raise ValueError(
                    f"windows: a segment of {seg.shape[1]} samples holds fewer than "
                    f"{per_segment} windows of {length}"
                )
            out.append(w)
    return np.stack(out)


def make_sequences(
    raw: np.ndarray, stride: int, offset: float, *, centred_prior: bool = False
) -> dc.Sequences:
    """Subsampled sequences: y = θ − π − offset, initial guesses from both rows.

    For fitting, the first-state prior has mean zero (its spread, the model's
    `prior_sigma`, is fitted with the other noise scales): a prior centred on
    the first measurement would use that measurement twice, and its fitted
    scale would collapse to zero. For held-out evaluation
    (`centred_prior=True`) the prior is centred on the measured first state,
    so the filter behind the k-step predictions starts converged instead of
    spending its first steps finding the swing.
    """
    seg = raw[:, :, ::stride]
    phi = seg[:, 0] - np.pi - offset
    init = np.stack([phi, seg[:, 1]], -1)
    x0 = init[:, 0] if centred_prior else np.zeros_like(init[:, 0])
    return dc.Sequences(phi[..., None], x0, initial_states=init)
