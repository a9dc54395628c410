"""The stages of the pendulum example: prepare the recording, run the
workflow, and check its answer against the recording in two ways."""

import dataclasses
from pathlib import Path

import jax.numpy as jnp
import numpy as np

import eqsmooth.discover as dc

from . import data as D
from .energy import energy_balance, equivalent_rate, fit_dissipation
from .model import build_model, open_loop, viscous_only


RATE = 100.0  # Hz after subsampling (at 25-50 Hz the angle noise is not identifiable)
HORIZON_S = 2.0  # s, longest k-step prediction horizon


@dataclasses.dataclass(frozen=True)
class Prepared:
    """The calibrated recording, cut into identification and validation
    sequences at the subsampled rate."""

    segments: dict  # `data.load_segments`: raw 1 kHz segments and their dt
    calibration: dict  # rest offset and ω0² from the identification swings
    calibration_validation: dict  # the same from the validation swings (reported)
    omega0_sq: float  # stiffness of the nominal model
    angle_sigma: float  # angle noise at 1 kHz
    dt: float  # subsampled step
    train_raw: np.ndarray  # (S, 2, N) raw identification windows
    held_raw: np.ndarray  # (W, 2, N) raw validation windows
    train: dc.Sequences
    heldout: dc.Sequences
    horizon: int  # steps of the longest k-step prediction


def prepare(path: Path, rate: float, omega0_sq: float | None, quick: bool) -> Prepared:
    """Load, calibrate and cut the recording. `omega0_sq=None` takes the
    stiffness from the swing period; `quick` keeps the first 4 s of each
    identification segment and cuts the validation segments into 4 s
    windows (equal shapes for both sets: compiled once)."""
    data = D.load_segments(path)
    raw_dt = data["dt"]
    cal = D.calibrate(data["identification"], raw_dt)
    cal_validation = D.calibrate(data["validation"], raw_dt)  # reported, not used
    omega0_sq = cal["omega0_sq"] if omega0_sq is None else omega0_sq
    stride = int(round(1 / (rate * raw_dt)))
    dt = raw_dt * stride
    n = data["identification"].shape[-1]
    if quick:
        train_raw = D.windows(data["identification"], 4000, 1)
        held_raw = D.windows(data["validation"], 4000, 2)
    else:
        train_raw = D.windows(data["identification"], n, 1)
        held_raw = D.windows(data["validation"], n, 1)
    return Prepared(
        segments=data,
        calibration=cal,
        calibration_validation=cal_validation,
        omega0_sq=omega0_sq,
        angle_sigma=D.angle_noise_std(data["identification"][:, 0]),
        dt=dt,
        train_raw=train_raw,
        held_raw=held_raw,
        train=D.make_sequences(train_raw, stride, cal["offset"]),
        heldout=D.make_sequences(held_raw, stride, cal["offset"], centred_prior=True),
        horizon=int(round(HORIZON_S / dt)),
    )


def run_workflow(p: Prepared) -> dict:
    """The find-name-add-show workflow on the candidate library, and the
    authors' model (the ideal pendulum plus viscous friction only) fitted by
    the same Laplace evidence."""
    model = build_model(p.dt, p.omega0_sq, p.angle_sigma)
    report = dc.discover(model, p.train, p.heldout, horizon=p.horizon)
    authors = dc.discover(
        viscous_only(model), p.train, p.heldout, horizon=p.horizon, max_terms=1
    )
    return {"ideal": model, "report": report, "authors_report": authors}


def open_loop_check(p: Prepared, fits: dict) -> tuple[dict, dict]:
    """Open-loop simulations `{label: (W, N)}` of the validation data from the
    measured first state, and their RMS error against the measured angle."""
    offset = p.calibration["offset"]
    x0 = np.stack([p.held_raw[:, 0, 0] - np.pi - offset, p.held_raw[:, 1, 0]], -1)
    y = np.asarray(p.heldout.measurements)[..., 0]
    fitted = {
        "ideal": fits["ideal"],
        "viscous only": fits["authors_report"]["model"],
        "named": fits["report"]["model"],
    }
    sims = {
        k: np.asarray(open_loop(m, jnp.asarray(x0), p.heldout.length))[..., 0]
        for k, m in fitted.items()
    }
    return sims, {k: float(np.sqrt(np.mean((s - y) ** 2))) for k, s in sims.items()}


def coefficient_dict(report: dict) -> dict[str, float]:
    return {c["name"]: c["value"] for c in report["add"]["coefficients"]}


def energy_check(p: Prepared, fits: dict) -> dict:
    """Energy balance per swing on both sets, three friction laws fitted to
    it, and the energy-equivalent viscous rate each fitted model implies."""
    raw_dt, offset = p.segments["dt"], p.calibration["offset"]
    balance = {}
    for part in ("identification", "validation"):
        rows = energy_balance(p.segments[part], offset, p.omega0_sq, raw_dt)
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
        "viscous only": coefficient_dict(fits["authors_report"]),
        "named": coefficient_dict(fits["report"]),
    }
    balance["amplitude_grid"] = amp.tolist()
    balance["model_rates"] = {
        k: equivalent_rate(c, amp, p.omega0_sq).tolist() for k, c in laws.items()
    }
    return balance
