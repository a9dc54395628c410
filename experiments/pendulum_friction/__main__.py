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
story is in docs/tutorial/pendulum.md. The stages live in
`experiments/pendulum_friction/` (data and calibration, model and candidates,
energy balance, experiment, report); this script runs them.

Runtime on 2 CPU cores: about 1 minute with `--quick` (the first 4 s of each
identification segment, the validation segments cut into 4 s windows; 2
minutes when the cores are shared), about 4 minutes without (full 9.2 s
segments); mostly compilation. Both use 100 Hz: at 25-50 Hz the angle noise
cannot be told from process noise and its fitted scale runs off to zero.

    python -m experiments.pendulum_friction --quick --out results/pendulum

Data: `single_pendulum_freeswing_1khz.mat` from the MultiArm-Pendulum
benchmark (https://github.com/dynamicslab/MultiArm-Pendulum, MIT licence),
expected at `../shared/data/pendulum/` next to the repository (or pass
`--data PATH`, or set `EQSMOOTH_DATA` to the folder that holds `pendulum/`).
Without it the script stops with an error that names the path it looked at.
"""

import argparse
import sys
import time
from pathlib import Path

import jax


jax.config.update("jax_enable_x64", True)


from .._data import require  # noqa: E402
from . import experiment as E, report as R  # noqa: E402
from .data import DEFAULT_DATA, SOURCE  # noqa: E402


def parse_args(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="4 s windows (CI)")
    parser.add_argument("--out", type=Path, default=Path("results/pendulum"))
    parser.add_argument("--data", type=Path, default=DEFAULT_DATA)
    parser.add_argument(
        "--rate",
        type=float,
        default=E.RATE,
        help="subsampled rate [Hz]; 1000 must be a multiple of it",
    )
    parser.add_argument(
        "--omega0-sq",
        type=float,
        default=None,
        help="stiffness of the nominal model [s^-2] (default: from the swing "
        f"period; the published value is {R.PUBLISHED_OMEGA0_SQ})",
    )
    return parser.parse_args(argv)


def main(argv=None) -> int:
    args = parse_args(argv)
    try:
        require(
            args.data, "the pendulum recording", f"{SOURCE} (MIT licence)", "--data"
        )
    except FileNotFoundError as error:
        sys.exit(f"error: {error}")
    start = time.perf_counter()
    prepared = E.prepare(args.data, args.rate, args.omega0_sq, args.quick)
    print(R.data_line(prepared))
    fits = E.run_workflow(prepared)
    sims, sim_rms = E.open_loop_check(prepared, fits)
    balance = E.energy_check(prepared, fits)
    elapsed = time.perf_counter() - start
    R.print_results(prepared, fits, sim_rms, balance, elapsed)
    command = " ".join(sys.argv)
    R.write(
        args.out, command, args.data, prepared, fits, sims, sim_rms, balance, elapsed
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
