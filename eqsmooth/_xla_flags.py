"""An opt-in XLA:CPU setting: `eqsmooth.set_xla_cpu_flags()`.

`import eqsmooth` changes no environment variable. Call
`set_xla_cpu_flags()` before the first JAX computation to turn off XLA's
concurrency-optimised CPU scheduler; the history below says why one might.

jaxlib 0.10's CPU runtime can wait forever for the result of a program that
has many independent operations, such as the levels of block cyclic
reduction on a long chain: `jax.block_until_ready` never returns and every
thread sleeps (a native stack shows the Eigen and LLVM worker threads idle
on condition variables and the main thread waiting for the output buffer).
Reproducer: `benchmarks/xla_cpu_hang.py`, the jitted `cyclic_reduction_solve`
of a `T = 100000`, `D = 5` chain called 20 times per process. Alternating
the two settings over 6 pairs of processes, all 6 with JAX's defaults hung
(after 0 to 19 calls) and none of the 6 with XLA's concurrency-optimised
scheduler turned off; 11 further processes with it off did not hang either.
`XLA_FLAGS=--xla_cpu_multi_thread_eigen=false`, a workaround reported for
similar hangs, did not help here, and neither did turning XNNPACK off. The
hang is not specific to that program: `benchmarks/train_step.py` hung the
same way at `T = 2000` in two separate runs.

A native stack of a hung `train_step.py` (with the flag) names the cause:
jaxlib's batched LAPACK kernels (`lapack_dtrsm_ffi` -> `ParallelBatchMap`)
split their batch over XLA's intra-op thread pool and block on a counter;
when as many run concurrently as the pool has threads, all of them wait and
no thread is left for the pieces. The flag lowers the concurrency and with
it the odds (0 of 17 reproducer processes hung), but it does not remove
them: with the flag on, that training step at `T = 2000` hung in 5 of 5
tries of the truncated and implicit adjoints.

Since then the chain solver avoids the cause itself: its solves and
selected inversion use no LAPACK kernel, and the LAPACK calls of its
factorisation depend on each other, so never two run at once
(`eqsmooth/solve/_small_blocks.py`). With that change the truncated and
implicit training steps at `T = 2000` finish. The flag stays for other
programs with independent batched LAPACK calls.

The scheduler only reorders independent operations, so turning it off
changes no result. XLA reads `XLA_FLAGS` when JAX first starts its backend,
so the function takes effect only if called before the first JAX
computation. A flag the user has set already is left alone.
"""

import os


_FLAGS = ("--xla_cpu_enable_concurrency_optimized_scheduler=false",)


def set_xla_cpu_flags() -> str:
    """Turn off XLA:CPU's concurrency-optimised scheduler (opt-in).

    Appends `--xla_cpu_enable_concurrency_optimized_scheduler=false` to the
    `XLA_FLAGS` environment variable unless that flag is set already. XLA
    reads the variable when JAX starts its backend, so call this before the
    first JAX computation. It lowers the odds of a jaxlib 0.10 CPU hang in
    programs that run several batched LAPACK kernels concurrently (see
    "Running on CPU" in the getting-started guide); eqsmooth's own chain
    solver no longer needs it. Results do not change.

    **Returns:** the new value of `XLA_FLAGS`.
    """
    current = os.environ.get("XLA_FLAGS", "")
    extra = [f for f in _FLAGS if f.split("=")[0] not in current]
    if extra:
        os.environ["XLA_FLAGS"] = " ".join([current, *extra]).strip()
    return os.environ.get("XLA_FLAGS", "")
