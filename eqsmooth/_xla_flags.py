"""XLA:CPU settings that eqsmooth applies when it is imported.

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
so this takes effect only if `eqsmooth` is imported before the first JAX
computation. A flag the user has set already is left alone, and
`EQSMOOTH_KEEP_XLA_FLAGS=1` opts out altogether.
"""

import os


_FLAGS = ("--xla_cpu_enable_concurrency_optimized_scheduler=false",)


def apply_default_xla_flags() -> None:
    if os.environ.get("EQSMOOTH_KEEP_XLA_FLAGS", "") not in ("", "0"):
        return
    current = os.environ.get("XLA_FLAGS", "")
    extra = [f for f in _FLAGS if f.split("=")[0] not in current]
    if extra:
        os.environ["XLA_FLAGS"] = " ".join([current, *extra]).strip()
