"""Find, name, add and show bearing friction on a real pendulum recording.

What it shows: the model-discrepancy workflow of `eqsmooth.discover` on real
measurements (the MultiArm-Pendulum benchmark of Kaheman et al. 2022: one arm
swinging freely, angle sampled at 1 kHz; see `../shared/data/README.md`).
The nominal model is the ideal, frictionless pendulum
φ̈ = −ω0² sin φ (φ = θ − π − offset), integrated with RK4 over the subsampled
step. Its stiffness ω0² and the encoder's rest offset are calibrated from the
oscillation period and the centre of the swings on the identification
segments (quantities friction leaves unchanged to first order). Only the
angle is used as a measurement (the velocity row of the file is a filtered
derivative of it, about 1 ms late; it only seeds the initial guesses).

The workflow fits the noise scales, tests the ideal model against a library
of candidate effects (friction laws, stiffness errors, constant torque,
sensor bias/scale/delay) on the 4 identification segments, names the
missing effects by Laplace evidence, fits their coefficients with confidence
intervals, and compares the models on the 2 validation segments
(log-likelihood per step, k-step prediction error, open-loop simulation).
The candidates are accelerations of the continuous dynamics, so a viscous
coefficient is a damping rate in s^-1. The authors' model (ideal pendulum
plus viscous friction) is fitted the same way, and its rate printed next to
the published 0.067 s^-1. A model-free check of the friction law comes from
the energy lost per swing. Writes `report.json` and `pendulum.png`; the
story is in docs/tutorial/pendulum.md.

Runtime on 2 CPU cores: about 1 minute with `--quick` (the first 4 s of each
identification segment, the validation segments cut into 4 s windows; 2
minutes when the cores are shared), about 4 minutes without (full 9.2 s
segments); mostly compilation. Both use 100 Hz: at 25-50 Hz the angle noise
cannot be told from process noise and its fitted scale runs off to zero.

    python examples/06_discover_pendulum.py --quick --out results/pendulum

Data: `single_pendulum_freeswing_1khz.mat` from the MultiArm-Pendulum
benchmark (https://github.com/dynamicslab/MultiArm-Pendulum, MIT licence),
expected at `../shared/data/pendulum/` next to the repository (or pass
`--data PATH`). Without it the script says so and exits with status 0.
"""

import argparse
import dataclasses
import json
import sys
import textwrap
import time
from pathlib import Path

import jax


jax.config.update("jax_enable_x64", True)

import equinox as eqx  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

import eqsmooth.discover as dc  # noqa: E402


REPO = Path(__file__).resolve().parents[1]
DEFAULT_DATA = REPO.parent / "shared/data/pendulum/single_pendulum_freeswing_1khz.mat"
SOURCE = "https://github.com/dynamicslab/MultiArm-Pendulum"
PUBLISHED_OMEGA0_SQ = 64.2  # s^-2 (Kaheman et al. 2022)
PUBLISHED_VISCOUS_RATE = 0.067  # s^-1
COULOMB_EPS = 0.05  # rad/s, smoothing velocity of the Coulomb term
RATE = 100.0  # Hz after subsampling (at 25-50 Hz the angle noise is not identifiable)
SIGMA_A = 0.05  # rad s^-1.5, starting density of the random acceleration
PRIOR_SIGMA = np.array([1.0, 8.0])  # first state (φ, φ̇) ~ N(0, diag²): swing size
HORIZON_S = 2.0  # s, longest k-step prediction horizon


# ---------------------------------------------------------------------------
# Data
# ---------------------------------------------------------------------------


def load_segments(path: Path) -> dict:
    """The identification and validation segments as `(S, 2, N)` arrays.

    Row 0 is the angle θ [rad] (hanging equilibrium near π), row 1 the
    angular velocity [rad/s]; all segments are cut to the shortest length.
    """
    from scipy.io import loadmat

    mat = loadmat(str(path))
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


# ---------------------------------------------------------------------------
# Energy balance: a check of the friction law that needs no model of the noise
# ---------------------------------------------------------------------------


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


# ---------------------------------------------------------------------------
# Model: the ideal pendulum (RK4 over the step) and its candidate effects
# ---------------------------------------------------------------------------


def _field(x, omega0_sq):
    return jnp.stack([x[1], -omega0_sq * jnp.sin(x[0])])


def pendulum_step(x, u, params):
    """Nominal model: one RK4 step of the frictionless pendulum, x = (φ, φ̇)."""
    dt, w2 = params["dt"], params["omega0_sq"]
    k1 = _field(x, w2)
    k2 = _field(x + 0.5 * dt * k1, w2)
    k3 = _field(x + 0.5 * dt * k2, w2)
    k4 = _field(x + dt * k3, w2)
    return x + dt / 6 * (k1 + 2 * k2 + 2 * k3 + k4)


def measure_angle(x, params):
    return x[:1]


def _accel(kind: str, phi, omega, eps: float):
    if kind == "constant":
        return jnp.ones_like(phi)
    if kind == "viscous":
        return -omega
    if kind == "drag":
        return -omega * jnp.abs(omega)
    if kind == "coulomb":
        return -jnp.tanh(omega / eps)
    if kind == "cubic_damping":
        return -(omega**3)
    if kind == "spring":
        return -phi
    if kind == "cubic_stiffness":
        return -(phi**3)
    raise ValueError(f"unknown acceleration {kind!r}")


@dataclasses.dataclass(frozen=True)
class ContinuousAcceleration:
    """A candidate acceleration `c·a(φ, φ̇)` of the continuous dynamics.

    Its effect over one step is the velocity kick `dt·a(x_mid)` at the
    nominal half-step state `x_mid = x + dt/2·f(x)`, so a fitted coefficient
    is a continuous-time quantity (for viscous damping the rate γ of
    φ̈ = … − γ φ̇, in s^-1). Against a 1 ms RK4 simulation of the damped
    pendulum over 9 s this kick dissipates the right energy within 0.5% at
    50 Hz (viscous, Coulomb, quadratic drag; amplitudes 0.4 and 1.6 rad),
    where the Euler-style kick `dt·a(x)` of
    [`mechanical_library`][eqsmooth.discover.mechanical_library] dissipates
    0.5-1.1% too little. (The exact derivative of the RK4 step with respect to
    `c` is as accurate and triples the compile time.)
    """

    kind: str
    dt: float
    omega0_sq: float
    eps: float = COULOMB_EPS

    def __call__(self, x, u):
        mid = x + 0.5 * self.dt * _field(x, self.omega0_sq)
        a = _accel(self.kind, mid[0], mid[1], self.eps)
        return jnp.stack([jnp.zeros_like(a), self.dt * a])


_DYNAMICS = (
    ("constant torque", "constant", 0, "rad/s^2", "φ̈ += c"),
    ("viscous damping", "viscous", 1, "1/s", "φ̈ -= c φ̇"),
    ("quadratic drag", "drag", 1, "1/rad", "φ̈ -= c φ̇|φ̇|"),
    ("Coulomb friction", "coulomb", 1, "rad/s^2", "φ̈ -= c tanh(φ̇/ε)"),
    ("cubic damping", "cubic_damping", 1, "s/rad^2", "φ̈ -= c φ̇³"),
    ("spring error", "spring", 0, "1/s^2", "φ̈ -= c φ"),
    ("cubic stiffness", "cubic_stiffness", 0, "1/(rad^2 s^2)", "φ̈ -= c φ³"),
)


def pendulum_library(dt: float, omega0_sq: float) -> tuple[dc.Candidate, ...]:
    """Friction laws, stiffness errors and a constant torque (continuous time),
    plus the angle sensor's bias, scale and delay from
    [`mechanical_library`][eqsmooth.discover.mechanical_library]."""
    out = [
        dc.Candidate(
            name,
            ContinuousAcceleration(kind, dt, omega0_sq),
            "dynamics",
            sign,
            unit,
            desc,
        )
        for name, kind, sign, unit, desc in _DYNAMICS
    ]
    sensors = dc.mechanical_library(
        [0],
        [1],
        2,
        dt=dt,
        measured_positions=[0],
        include=["sensor bias", "sensor scale", "sensor delay"],
    )
    return tuple(out) + sensors


def build_model(dt: float, omega0_sq: float, angle_sigma: float) -> dc.ChainModel:
    """The ideal pendulum with the candidate library and starting noise levels.

    Process noise: a white random acceleration of density `SIGMA_A`, whose
    exact discretisation has standard deviations `σ_a (√(dt³/3), √dt)` on
    angle and velocity (the chain model keeps the diagonal). Measurement
    noise: the angle noise measured at 1 kHz. First state: `PRIOR_SIGMA`
    around zero. The workflow refits one multiplier for each of the three.
    """
    q = SIGMA_A * np.array([np.sqrt(dt**3 / 3), np.sqrt(dt)])
    params = {"dt": jnp.asarray(dt), "omega0_sq": jnp.asarray(omega0_sq)}
    return dc.ChainModel(
        pendulum_step,
        measure_angle,
        params,
        q,
        np.array([angle_sigma]),
        PRIOR_SIGMA,
        pendulum_library(dt, omega0_sq),
    )


@eqx.filter_jit
def open_loop(model: dc.ChainModel, x0, steps: int):
    """Noise-free simulations `(B, steps, 2)` of the model's mean dynamics."""

    def one(x):
        def step(x, _):
            return model.transition(x, jnp.zeros(1, x.dtype)), x

        return jax.lax.scan(step, x, None, length=steps)[1]

    return jax.vmap(one)(x0)


# ---------------------------------------------------------------------------
# Report
# ---------------------------------------------------------------------------


def p_text(p: float) -> str:
    return f"{p:.1e}" if p > 0 else "< 1e-300"  # below double precision


def coefficient_dict(report: dict) -> dict[str, float]:
    return {c["name"]: c["value"] for c in report["add"]["coefficients"]}


def figure(summary: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(2, 2, figsize=(11, 7.5))
    styles = {"ideal": "C3", "viscous only": "C0", "named": "C2"}

    ax = axes[0, 0]
    sim = summary["open_loop"]
    t = np.asarray(sim["time"])
    ax.plot(t, sim["data"], "k", lw=0.8, label="measured")
    for label, ys in sim["models"].items():
        ax.plot(t, ys, color=styles[label], lw=0.8, label=label)
    ax.set_xlim(t[-1] - 2.0, t[-1])
    ax.set_xlabel("time in the validation segment [s]")
    ax.set_ylabel("φ [rad]")
    ax.set_title("open-loop simulation, last 2 s of a validation segment")
    ax.legend(fontsize=8, loc="upper right")

    ax = axes[0, 1]
    step = summary["first_step"]
    names = [c["name"] for c in step]
    gains = [max(c["log_marginal_gain"], 0.1) for c in step]
    ax.barh(names[::-1], gains[::-1], color="C0")
    ax.set_xscale("log")
    ax.set_xlabel("log-evidence gain of each candidate alone [nats]")
    ax.set_title(textwrap.fill("name: " + summary["verdict"], 60), fontsize=9)

    ax = axes[1, 0]
    for label, rmse in summary["k_step_rmse"].items():
        k = np.arange(1, len(rmse) + 1) * summary["dt"]
        ax.plot(k, rmse, color=styles[label], label=label)
    ax.set_xlabel("prediction horizon [s]")
    ax.set_ylabel("held-out k-step RMSE of φ [rad]")
    ax.set_yscale("log")
    ax.legend(fontsize=8)
    ax.set_title("show: prediction from filtered states, validation data")

    ax = axes[1, 1]
    eb = summary["energy_balance"]
    for part, marker in (("identification", "o"), ("validation", "s")):
        rows = np.asarray(eb[part]["rows"])
        ax.plot(
            rows[:, 0],
            rows[:, 1] / rows[:, 3],
            marker,
            ms=3,
            alpha=0.6,
            label=f"swings ({part})",
        )
    amp = np.asarray(eb["amplitude_grid"])
    for label, rate in eb["model_rates"].items():
        ax.plot(amp, rate, color=styles[label], label=label)
    ax.axhline(
        PUBLISHED_VISCOUS_RATE, color="grey", ls="--", label="published 0.067 s$^{-1}$"
    )
    ax.set_xlabel("swing amplitude [rad]")
    ax.set_ylabel("energy-equivalent viscous rate [s$^{-1}$]")
    ax.set_ylim(0.0, 0.16)
    ax.legend(fontsize=7)
    ax.set_title("friction law: energy lost per swing")
    fig.tight_layout()
    fig.savefig(path, dpi=80)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="4 s windows (CI)")
    parser.add_argument("--out", type=Path, default=Path("results/pendulum"))
    parser.add_argument("--data", type=Path, default=DEFAULT_DATA)
    parser.add_argument(
        "--rate",
        type=float,
        default=RATE,
        help="subsampled rate [Hz]; 1000 must be a multiple of it",
    )
    parser.add_argument(
        "--omega0-sq",
        type=float,
        default=None,
        help="stiffness of the nominal model [s^-2] (default: from the swing "
        f"period; the published value is {PUBLISHED_OMEGA0_SQ})",
    )
    args = parser.parse_args()
    if not args.data.is_file():
        print(
            f"no pendulum data at {args.data}: download single_pendulum_freeswing_1khz"
            f".mat from {SOURCE} (see ../shared/data/README.md) and pass --data PATH."
        )
        return 0
    start = time.perf_counter()
    data = load_segments(args.data)
    raw_dt = data["dt"]
    cal = calibrate(data["identification"], raw_dt)
    cal_validation = calibrate(data["validation"], raw_dt)  # reported, not used
    omega0_sq = cal["omega0_sq"] if args.omega0_sq is None else args.omega0_sq
    angle_sigma = angle_noise_std(data["identification"][:, 0])
    stride = int(round(1 / (args.rate * raw_dt)))
    dt = raw_dt * stride
    n = data["identification"].shape[-1]
    if args.quick:  # equal shapes for both sets: compiled once
        train_raw = windows(data["identification"], 4000, 1)
        held_raw = windows(data["validation"], 4000, 2)
    else:
        train_raw = windows(data["identification"], n, 1)
        held_raw = windows(data["validation"], n, 1)
    train = make_sequences(train_raw, stride, cal["offset"])
    heldout = make_sequences(held_raw, stride, cal["offset"], centred_prior=True)
    horizon = int(round(HORIZON_S / dt))
    print(
        f"data: {len(train_raw)} identification and {len(held_raw)} validation "
        f"sequences of {train.length} steps at {1 / dt:.0f} Hz; angle noise "
        f"{angle_sigma:.2e} rad (1 kHz); rest offset {cal['offset'] * 1e3:.2f} mrad; "
        f"ω0² = {omega0_sq:.3f} s^-2 (swing period: {cal['omega0_sq']:.3f} ± "
        f"{cal['omega0_sq_spread']:.3f} over {cal['cycles']} cycles; published "
        f"{PUBLISHED_OMEGA0_SQ}; validation swings {cal_validation['omega0_sq']:.3f}, "
        f"offset {cal_validation['offset'] * 1e3:.2f} mrad)"
    )

    model = build_model(dt, omega0_sq, angle_sigma)
    report = dc.discover(model, train, heldout, horizon=horizon)
    # The authors' model: the ideal pendulum plus viscous friction only,
    # fitted by the same Laplace evidence.
    viscous = model.candidates[model.index("viscous damping")]
    authors = dc.ChainModel(
        pendulum_step,
        measure_angle,
        model.params,
        model.process_sigma,
        model.measurement_sigma,
        model.prior_sigma,
        (viscous,),
    )
    authors_report = dc.discover(authors, train, heldout, horizon=horizon, max_terms=1)

    # Open-loop simulations of the validation data from the measured first state.
    x0 = np.stack([held_raw[:, 0, 0] - np.pi - cal["offset"], held_raw[:, 1, 0]], -1)
    steps = heldout.length
    y = np.asarray(heldout.measurements)[..., 0]
    fitted = {
        "ideal": model,
        "viscous only": authors_report["model"],
        "named": report["model"],
    }
    sims = {
        k: np.asarray(open_loop(m, jnp.asarray(x0), steps))[..., 0]
        for k, m in fitted.items()
    }
    sim_rms = {k: float(np.sqrt(np.mean((s - y) ** 2))) for k, s in sims.items()}

    # Energy balance per swing, and what each fitted law implies.
    rows_id = energy_balance(data["identification"], cal["offset"], omega0_sq, raw_dt)
    rows_va = energy_balance(data["validation"], cal["offset"], omega0_sq, raw_dt)
    balance = {}
    for part, rows in (("identification", rows_id), ("validation", rows_va)):
        balance[part] = {
            "rows": rows.tolist(),
            "viscous only": fit_dissipation(rows, ("viscous damping",)),
            "viscous + Coulomb": fit_dissipation(
                rows, ("viscous damping", "Coulomb friction")
            ),
            "Coulomb + drag": fit_dissipation(
                rows, ("Coulomb friction", "quadratic drag")
            ),
        }
    amp = np.linspace(0.2, 1.65, 30)
    laws = {
        "viscous only": coefficient_dict(authors_report),
        "named": coefficient_dict(report),
    }
    balance["amplitude_grid"] = amp.tolist()
    balance["model_rates"] = {
        k: equivalent_rate(c, amp, omega0_sq).tolist() for k, c in laws.items()
    }
    elapsed = time.perf_counter() - start

    # ------------------------------------------------------------------ print
    fnd = report["find"]
    st = fnd["score_test"]
    print(f"\nverdict: {report['verdict']}  ({elapsed:.0f} s)")
    print(
        f"find: score test chi2({st['df']}) = {st['statistic']:.1f}, "
        f"p = {p_text(st['p_value'])} ({st['covariance']}); Ljung-Box p = "
        f"{p_text(fnd['whiteness'][0]['p_value'])}; not identifiable: "
        f"{fnd['not_identifiable']}"
    )
    loc = fnd["localisation"][0]
    print(
        f"      largest bias: {loc['where']} in [{loc['bin'][0]:.2f}, "
        f"{loc['bin'][1]:.2f}]: mean whitened residual {loc['mean_whitened']:+.2f} "
        f"(z = {loc['z']:.1f})"
    )
    for i, s in enumerate(report["name"]["steps"]):
        runner = s["candidates"][1] if len(s["candidates"]) > 1 else None
        gain = s["candidates"][0]["log_marginal_gain"]
        print(
            f"name step {i + 1}: {s['best']} (+{gain:.1f}"
            f" nats, LR p = {p_text(s['p_value'])}, gate {s['gate']:.1e})"
            + (
                f"; runner-up {runner['name']} (+{runner['log_marginal_gain']:.1f})"
                if runner
                else ""
            )
        )
    print("add (named terms fitted together):")
    for c in report["add"]["coefficients"]:
        lo, hi = c["interval"]
        print(
            f"  {c['name']}: {c['value']:.4g} (95% CI [{lo:.4g}, {hi:.4g}])"
            + ("" if c["sign_ok"] else "  <- sign against physics")
        )
    noise = report["add"]["noise_scales"]
    print(
        f"  noise: σ_a = {SIGMA_A * noise['process']:.3g} rad s^-1.5, angle "
        f"{angle_sigma * noise['measurement']:.2e} rad"
    )
    for c in authors_report["add"]["coefficients"]:
        lo, hi = c["interval"]
        print(
            f"viscous-only model: rate {c['value']:.4f} s^-1 (95% CI [{lo:.4f}, "
            f"{hi:.4f}]); published {PUBLISHED_VISCOUS_RATE} s^-1"
        )

    def coef(fit, name, digits):
        c = fit[name]
        return f"{c['value']:.{digits}f} ± {c['std_error']:.{digits}f}"

    for part in ("identification", "validation"):
        b = balance[part]
        v, vc, cd = b["viscous only"], b["viscous + Coulomb"], b["Coulomb + drag"]
        print(
            f"energy balance ({part}, {v['swings']} swings): viscous only "
            f"{coef(v, 'viscous damping', 4)} s^-1; viscous "
            f"{coef(vc, 'viscous damping', 4)} s^-1 + Coulomb "
            f"{coef(vc, 'Coulomb friction', 3)} rad/s^2; Coulomb "
            f"{coef(cd, 'Coulomb friction', 3)} rad/s^2 + drag "
            f"{coef(cd, 'quadratic drag', 5)} 1/rad"
        )
    sh, sha = report["show"], authors_report["show"]
    ks = [k for k in (0.1, 0.5, 1.0, 2.0) if round(k / dt) <= horizon]
    print("show (validation data):")
    rows = (
        ("ideal", sh["before"]),
        ("viscous only", sha["after"]),
        ("named", sh["after"]),
    )
    print(
        "  model          loglik/step  NIS    Ljung-Box p  open-loop RMS  "
        + "  ".join(f"{k:.1f}s-RMSE" for k in ks)
    )
    for label, m in rows:
        r = m["k_step_rmse"]
        ll, lb = m["log_marginal_per_step"], p_text(m["whiteness_p_values"][0])
        print(
            f"  {label:13s}  {ll:11.4f}  {m['nis_mean']:5.2f}  {lb:>11s}  "
            f"{sim_rms[label]:13.4f}  "
            + "  ".join(f"{r[int(round(k / dt)) - 1]:9.5f}" for k in ks)
        )
    print(
        "  (open-loop RMS: simulation from the measured first state over each "
        "whole validation sequence; k-step RMSE: from filtered states)"
    )

    # ------------------------------------------------------------------ write
    args.out.mkdir(parents=True, exist_ok=True)
    summary = {
        "command": " ".join(sys.argv),
        "runtime_s": elapsed,
        "dt": dt,
        "data": {
            "file": str(args.data),
            "identification_sequences": len(train_raw),
            "validation_sequences": len(held_raw),
            "steps": train.length,
            "angle_noise_1khz": angle_sigma,
            "calibration": cal,
            "calibration_validation": cal_validation,
            "omega0_sq": omega0_sq,
        },
        "published": {
            "omega0_sq": PUBLISHED_OMEGA0_SQ,
            "viscous_rate": PUBLISHED_VISCOUS_RATE,
        },
        "verdict": report["verdict"],
        "workflow": dc.to_json(report),
        "viscous_only": dc.to_json(authors_report),
        "open_loop_rms": sim_rms,
        "energy_balance": balance,
    }
    (args.out / "report.json").write_text(json.dumps(summary, indent=1, default=str))
    j = 0  # the first validation sequence
    plot = {
        "verdict": report["verdict"],
        "dt": dt,
        "first_step": report["name"]["steps"][0]["candidates"]
        if report["name"]["steps"]
        else [],
        "k_step_rmse": {
            "ideal": sh["before"]["k_step_rmse"],
            "viscous only": sha["after"]["k_step_rmse"],
            "named": sh["after"]["k_step_rmse"],
        },
        "open_loop": {
            "time": (np.arange(steps) * dt).tolist(),
            "data": y[j].tolist(),
            "models": {k: s[j].tolist() for k, s in sims.items()},
        },
        "energy_balance": balance,
    }
    try:
        figure(plot, args.out / "pendulum.png")
    except ImportError:
        print("matplotlib not installed: no figure (pip install -e '.[examples]')")
    print(f"wrote {args.out / 'report.json'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
