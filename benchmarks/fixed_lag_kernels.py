"""Why a fixed-lag update with loop closures costs more at lag 10: the
compiled `update_rows` program's work per Levenberg-Marquardt iteration.

For the `--per-update` problem of `benchmarks.fixed_lag` (an SE(2) chain,
odometry and a pose fix per step; with closures, one every 4th step to the
pose `span` steps back, `max_back = span`), the program of a late update is
lowered and compiled, and this records XLA's flop and byte counts, the
kernels in the body of the window solve's LM loop (fusions, dots, custom
calls), and the median and minimum time of the compiled call over
`--calls` calls, the variants interleaved (a loaded machine: compare within
a run).

    OPENBLAS_NUM_THREADS=1 python -m benchmarks.fixed_lag_kernels \\
        --json benchmarks/results/fixed_lag_kernels.json
"""

import re
import statistics
import time

import jax

from . import _common as common, fixed_lag


jax.config.update("jax_enable_x64", True)

from eqsmooth.filters import _fixed_lag_update as update_module  # noqa: E402


def _late_call(lag: int, span: int, closures: bool, steps: int):
    """The arguments of the last `update_rows` call of a per-update run."""
    calls, jitted = [], update_module._advance_rows_of_arrays

    def spy(*args, **kwargs):
        calls.append((args, kwargs))
        return jitted(*args, **kwargs)

    update_module._advance_rows_of_arrays = spy
    try:
        data = fixed_lag.problem(steps, span, closures)
        fixed_lag.per_update_record(None, data, lag, span)
    finally:
        update_module._advance_rows_of_arrays = jitted
    return calls[-1]


def _loop_body_kernels(hlo: str) -> dict:
    """Kernel counts in the body of the least-squares `while` (the LM loop)."""
    loop = re.search(
        r"while\(.*body=%([\w.\-]+).*op_name=\"[^\"]*least_squares\)/while\"",
        hlo,
    )
    if loop is None:
        return {}
    body = hlo.split(f"\n%{loop.group(1)} ", 1)[1].split("\n}", 1)[0]
    kinds = re.findall(r"= \S+ (fusion|dot|custom-call|scatter|copy)\(", body)
    return {f"loop_{k.replace('-', '_')}s": kinds.count(k) for k in set(kinds)}


def main(argv=None):
    parser = common.cli(__doc__)
    parser.add_argument("--lag", type=int, default=10)
    parser.add_argument("--spans", type=int, nargs="*", default=[4, 8])
    parser.add_argument("--steps", type=int, default=40)
    parser.add_argument("--calls", type=int, default=200)
    a = parser.parse_args(argv)
    jitted = update_module._advance_rows_of_arrays
    variants = [("no closures", 1, False)] + [
        (f"closures, max_back {s}", s, True) for s in a.spans
    ]
    records, calls = [], []
    for name, span, closures in variants:
        args, kwargs = _late_call(a.lag, span, closures, a.steps)
        compiled = jitted.lower(*args, **kwargs).compile()
        config = dict(lag=a.lag, variant=name, max_back=span if closures else None)
        fields = common.xla_cost(compiled) | _loop_body_kernels(compiled.as_text())
        records.append(common.record("fixed_lag_kernels", config, **fields))
        calls.append((args, kwargs))
    times = [[] for _ in calls]
    for _ in range(a.calls):
        for t, (args, kwargs) in zip(times, calls):
            t0 = time.perf_counter()
            jax.block_until_ready(jitted(*args, **kwargs))
            t.append(time.perf_counter() - t0)
    for rec, t in zip(records, times):
        rec |= dict(median_ms=1e3 * statistics.median(t), min_ms=1e3 * min(t))
    columns = ["variant", "flops", "loop_fusions", "loop_dots", "median_ms", "min_ms"]
    common.print_and_save(records, columns, a.json)


if __name__ == "__main__":
    main()
