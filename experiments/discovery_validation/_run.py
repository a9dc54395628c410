"""What the resumable Monte Carlo runs share: a cell's random streams and
runs, picking up an earlier run's records, the run's provenance, saving
after every cell, and the log."""

import json
import time
from pathlib import Path

import numpy as np

from benchmarks._common import cli_command, machine, write_json, write_text

from .oscillator import _git, B, guarded_run


def stream(system: int, effect: int, level: float, noise: float, num: int) -> list:
    """The key of a cell's random streams (data set `s` draws from
    `SeedSequence(key + [s])`): the system's and the effect's tags, the level
    and the measurement noise factor, and the number of sequences where it is
    not the default `B` (which keeps the streams it always had)."""
    key = [2026, 37, system, effect, int(round(level * 1000)), int(round(noise * 10))]
    return key + [num] if num != B else key


def cell_runs(key, seeds, simulate, model, log, label: str, c):
    """The workflow on the data sets `seeds` (an iterable of stream numbers),
    each `simulate(rng)` from its stream of `key`: yields `(seed, out, snr)`
    for every run, counting the crashes (logged) in `c["crashes"]`."""
    for s in seeds:
        rng = np.random.default_rng(np.random.SeedSequence(key + [s]))
        data, snr = simulate(rng)
        out = guarded_run(data, model, log, f"{label} seed {s}")
        if out is None:
            c["crashes"] += 1
            continue
        yield s, out, snr


def resume(path, key):
    """The records saved at `path` by an earlier run (none when there is no
    such file), the commands that made them, and the `key(record)` of each:
    the cells already done."""
    records, commands = [], []
    if path and Path(path).exists():
        earlier = json.loads(Path(path).read_text())
        records = earlier["records"]
        commands = earlier["info"].get("commands", [earlier["info"]["command"]])
    return records, commands, {key(r) for r in records}


def cell_key(r: dict, system: str, level) -> tuple:
    """What a saved cell is, for `resume`: its `r[system]` (the system, or
    library), effect, `level`, measurement noise factor and sequences per
    data set."""
    noise = r["measurement_noise_factor"]
    return (r[system], r["effect"], level, noise, r.get("sequences", B))


def run_info(commands=None) -> dict:
    """Provenance of this run: its command, every command of the run so far
    (`commands` from `resume`, then this one; not recorded when None), the
    commit and the machine."""
    info = {"command": cli_command()}
    if commands is not None:
        info["commands"] = [*commands, info["command"]]
    info["git"] = "{} (uncommitted: {})".format(*_git())
    info["machine"] = machine()
    return info


def run_lines(info: dict) -> list[str]:
    """The report's lines on the run (`run_info`): its commands (each
    resumed run adds its own) or command, the machine, the commit and the
    wall time."""
    m = info["machine"]
    if "commands" in info:
        commands = "; ".join(f"`{c}`" for c in info["commands"])
        head = f"- commands (cells are resumed and added across runs): {commands}"
    else:
        head = f"- command: `{info['command']}`"
    return [
        head,
        f"- machine: {m.get('cores')} cores, {m.get('cpu')}; JAX {m.get('jax')}",
        f"- git: {info['git']}",
        f"- wall time {info['total_s'] / 60:.1f} min",
    ]


def saver(args, records, info, render, t0):
    """`save()` for a resumable run: the records as JSON and `render`'s
    markdown, where `args.json` and `args.markdown` say."""

    def save():
        info["total_s"] = time.perf_counter() - t0
        if args.json:
            write_json(args.json, records, {"info": info})
        if args.markdown:
            write_text(args.markdown, render(records, info))

    return save


def log(msg):
    print(msg, flush=True)
