"""Energy balance: a check of the friction law that needs no model of the noise."""

import numpy as np

from .data import swing_extrema
from .model import COULOMB_EPS


def energy_balance(
    segments: np.ndarray, offset: float, omega0_sq: float, dt: float
) -> np.ndarray:
    """Per full swing: `(amplitude, ΔE, ∫|φ̇|dt, ∫φ̇²dt, ∫|φ̇|³dt)`, shape `(S, 5)`.

    At a turning point the velocity is zero, so the energy per unit inertia
    lost between turning points k and k+2 (one full swing, same side) is
    `ΔE = ω0² (cos A_{k+2} − cos A_k)`, and `ΔE = ∫ φ̇ F(φ̇) dt` for any friction
    law `φ̈ = … − F(φ̇)`: viscous, Coulomb and quadratic drag contribute
    `γ ∫φ̇²`, `μ ∫|φ̇|` and `d ∫|φ̇|³`. Full swings, not half swings: an error
    δ in the rest offset biases a half swing's ΔE by about ±2 ω0² δ sin A
    (alternating sign) but cancels over a full one. Swings do not overlap.
    """
    rows = []
    for seg in segments:
        phi, omega = seg[0] - np.pi - offset, seg[1]
        ext = swing_extrema(phi, omega, dt)
        for k in range(0, len(ext) - 2, 2):
            (t0, a0), (t1, a1) = ext[k], ext[k + 2]
            v = omega[int(np.ceil(t0 / dt)) : int(np.floor(t1 / dt)) + 1]
            rows.append(
                (
                    (abs(a0) + 2 * abs(ext[k + 1, 1]) + abs(a1)) / 4,
                    omega0_sq * (np.cos(a1) - np.cos(a0)),
                    np.sum(np.abs(v)) * dt,
                    np.sum(v * v) * dt,
                    np.sum(np.abs(v) ** 3) * dt,
                )
            )
    return np.asarray(rows)


_BALANCE_COLUMNS = {"Coulomb friction": 2, "viscous damping": 3, "quadratic drag": 4}


def fit_dissipation(rows: np.ndarray, terms: tuple[str, ...]) -> dict:
    """Least squares of the swings' energy losses on the chosen friction terms."""
    X = rows[:, [_BALANCE_COLUMNS[t] for t in terms]]
    y = rows[:, 1]
    beta, *_ = np.linalg.lstsq(X, y, rcond=None)
    res = y - X @ beta
    s2 = res @ res / (len(y) - len(terms))
    se = np.sqrt(np.diag(np.linalg.inv(X.T @ X)) * s2)
    return {
        t: {"value": float(b), "std_error": float(e)}
        for t, b, e in zip(terms, beta, se)
    } | {"rms_residual": float(np.sqrt(np.mean(res * res))), "swings": len(y)}


def friction_law(coefficients: dict[str, float], omega: np.ndarray) -> np.ndarray:
    """`F(φ̇)` of the named dissipative terms (the others dissipate nothing)."""
    F = np.zeros_like(omega)
    for name, c in coefficients.items():
        if name == "viscous damping":
            F = F + c * omega
        elif name == "Coulomb friction":
            F = F + c * np.tanh(omega / COULOMB_EPS)
        elif name == "quadratic drag":
            F = F + c * omega * np.abs(omega)
        elif name == "cubic damping":
            F = F + c * omega**3
    return F


def equivalent_rate(
    coefficients: dict[str, float], amplitude: np.ndarray, omega0_sq: float
) -> np.ndarray:
    """Energy-equivalent viscous rate `∫φ̇F(φ̇) / ∫φ̇²` over an ideal half swing.

    The viscous rate that would dissipate the same energy as the friction law
    on a swing of the given amplitude (1 ms RK4 of the ideal pendulum).
    """
    h = 1e-3
    x = np.stack([np.asarray(amplitude, float), np.zeros(len(amplitude))])
    num = np.zeros(len(amplitude))
    den = np.zeros(len(amplitude))
    done = np.zeros(len(amplitude), bool)

    def f(x):
        return np.stack([x[1], -omega0_sq * np.sin(x[0])])

    for _ in range(int(2 * np.pi / np.sqrt(omega0_sq) / h) + 200):
        k1 = f(x)
        k2 = f(x + 0.5 * h * k1)
        k3 = f(x + 0.5 * h * k2)
        x_new = x + h / 6 * (k1 + 2 * k2 + 2 * k3 + f(x + h * k3))
        done |= (x_new[1] > 0) & (x[1] < 0)  # the half-swing ends at φ̇ = 0
        v = np.where(done, 0.0, x_new[1])
        num += h * v * friction_law(coefficients, v)
        den += h * v * v
        x = x_new
        if done.all():
            break
    return num / den
