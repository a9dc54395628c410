"""What the pendulum example prints, writes (`report.json`) and plots."""

import json
import textwrap
from pathlib import Path

import numpy as np

import eqsmooth.discover as dc

from .experiment import Prepared
from .model import SIGMA_A


PUBLISHED_OMEGA0_SQ = 64.2  # s^-2 (Kaheman et al. 2022)
PUBLISHED_VISCOUS_RATE = 0.067  # s^-1


def data_line(p: Prepared) -> str:
    cal, cal_v = p.calibration, p.calibration_validation
    return (
        f"data: {len(p.train_raw)} identification and {len(p.held_raw)} validation "
        f"sequences of {p.train.length} steps at {1 / p.dt:.0f} Hz; angle noise "
        f"{p.angle_sigma:.2e} rad (1 kHz); rest offset {cal['offset'] * 1e3:.2f} mrad; "
        f"ω0² = {p.omega0_sq:.3f} s^-2 (swing period: {cal['omega0_sq']:.3f} ± "
        f"{cal['omega0_sq_spread']:.3f} over {cal['cycles']} cycles; published "
        f"{PUBLISHED_OMEGA0_SQ}; validation swings {cal_v['omega0_sq']:.3f}, "
        f"offset {cal_v['offset'] * 1e3:.2f} mrad)"
    )


def p_text(p: float) -> str:
    return f"{p:.1e}" if p > 0 else "< 1e-300"  # below double precision


def ci_text(c: dict, fmt: str) -> str:
    """A fitted coefficient's `95% CI [lo, hi]`, the bounds formatted by `fmt`."""
    lo, hi = c["interval"]
    return f"95% CI [{lo:{fmt}}, {hi:{fmt}}]"


def print_results(
    p: Prepared, fits: dict, sim_rms: dict, balance: dict, elapsed: float
) -> None:
    """The verdict, each step of the workflow, the energy balance and the
    held-out comparison of the three models."""
    report, authors_report = fits["report"], fits["authors_report"]
    dt, horizon = p.dt, p.horizon
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
        print(
            f"  {c['name']}: {c['value']:.4g} ({ci_text(c, '.4g')})"
            + ("" if c["sign_ok"] else "  <- sign against physics")
        )
    noise = report["add"]["noise_scales"]
    print(
        f"  noise: σ_a = {SIGMA_A * noise['process']:.3g} rad s^-1.5, angle "
        f"{p.angle_sigma * noise['measurement']:.2e} rad"
    )
    for c in authors_report["add"]["coefficients"]:
        print(
            f"viscous-only model: rate {c['value']:.4f} s^-1 ({ci_text(c, '.4f')}); "
            f"published {PUBLISHED_VISCOUS_RATE} s^-1"
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


def write(
    out: Path,
    command: str,
    data_path: Path,
    p: Prepared,
    fits: dict,
    sims: dict,
    sim_rms: dict,
    balance: dict,
    elapsed: float,
) -> None:
    """`report.json` (every number) and `pendulum.png` (four panels)."""
    report, authors_report = fits["report"], fits["authors_report"]
    sh, sha = report["show"], authors_report["show"]
    dt, train_raw, held_raw, train = p.dt, p.train_raw, p.held_raw, p.train
    steps = p.heldout.length
    y = np.asarray(p.heldout.measurements)[..., 0]
    out.mkdir(parents=True, exist_ok=True)
    summary = {
        "command": command,
        "runtime_s": elapsed,
        "dt": dt,
        "data": {
            "file": str(data_path),
            "identification_sequences": len(train_raw),
            "validation_sequences": len(held_raw),
            "steps": train.length,
            "angle_noise_1khz": p.angle_sigma,
            "calibration": p.calibration,
            "calibration_validation": p.calibration_validation,
            "omega0_sq": p.omega0_sq,
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
    (out / "report.json").write_text(json.dumps(summary, indent=1, default=str))
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
        figure(plot, out / "pendulum.png")
    except ImportError:
        print("matplotlib not installed: no figure (pip install -e '.[examples]')")
    print(f"wrote {out / 'report.json'}")


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
