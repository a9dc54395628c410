"""Opt-in XLA:CPU settings: `eqsmooth.set_xla_cpu_flags()`.

`import eqsmooth` changes no environment variable. Call
`set_xla_cpu_flags()` before the first JAX computation to turn off XLA's
concurrency-optimised CPU scheduler, and `set_xla_cpu_flags(fast_compile=True)`
to compile with XLA's earlier fusion emitters.

The scheduler. jaxlib 0.10's CPU runtime can wait forever for the result of
a program with many independent batched LAPACK calls (`jax.block_until_ready`
never returns and every thread sleeps): jaxlib's batched LAPACK kernels
(`lapack_dtrsm_ffi` -> `ParallelBatchMap`) split their batch over XLA's
intra-op thread pool and block on a counter, and when as many run
concurrently as the pool has threads, all of them wait and no thread is left
for the pieces. Turning the concurrency-optimised scheduler off lowers the
concurrency and with it the odds of the hang, but does not remove them
(`XLA_FLAGS=--xla_cpu_multi_thread_eigen=false`, a workaround reported for
similar hangs, did not help, and neither did turning XNNPACK off). The
chain solver avoids the cause itself: its solves and selected inversion use
no LAPACK kernel, and the LAPACK calls of its factorisation depend on each
other, so never two run at once (`eqsmooth/solve/_linear/_small_blocks.py`).
The flag stays for other programs with independent batched LAPACK calls. The
scheduler only reorders independent operations, so turning it off changes no
result. The measurements are described on the getting-started page.

Compile time. XLA:CPU compiles fused element-wise kernels with MLIR-based
emitters by default; `--xla_cpu_use_fusion_emitters=false` selects its
earlier LLVM IR emitters, which compile faster with the same run times (the
performance page has the figures).

XLA reads `XLA_FLAGS` when JAX first starts its backend, so the function
takes effect only if called before the first JAX computation; a flag the user
has set already is left alone. XLA aborts the process on a flag it does not
know, so a flag is added only after a subprocess has started JAX's CPU
backend with it.
"""

import os
import subprocess
import sys
import warnings


_SCHEDULER_FLAG = "--xla_cpu_enable_concurrency_optimized_scheduler=false"
_FAST_COMPILE_FLAG = "--xla_cpu_use_fusion_emitters=false"


def _known_to_xla(flags: str) -> bool:
    """Whether JAX's CPU backend starts with `XLA_FLAGS=flags` (XLA aborts the
    process on an unknown flag, so this asks a subprocess); warns if not."""
    env = {**os.environ, "XLA_FLAGS": flags, "JAX_PLATFORMS": "cpu"}
    probe = subprocess.run(
        [sys.executable, "-c", "import jax; jax.devices('cpu')"],
        env=env,
        capture_output=True,
        text=True,
    )
    if probe.returncode != 0:
        warnings.warn(
            f"set_xla_cpu_flags: JAX's CPU backend did not start with "
            f"XLA_FLAGS={flags!r}, so the flag was not added (this jaxlib may "
            f"not know it). The probe's last output: {probe.stderr[-300:]!r}",
            stacklevel=3,
        )
    return probe.returncode == 0


def set_xla_cpu_flags(
    *, serial_scheduler: bool = True, fast_compile: bool = False
) -> str:
    """Append opt-in XLA:CPU flags to the `XLA_FLAGS` environment variable.

    XLA reads the variable when JAX starts its backend, so call this before
    the first JAX computation. A flag the user has set already (to either
    value) is left alone.

    **Arguments:**

    - `serial_scheduler`: add
        `--xla_cpu_enable_concurrency_optimized_scheduler=false`. It lowers
        the odds of a jaxlib 0.10 CPU hang in programs that run several
        batched LAPACK kernels concurrently (see "Running on CPU" in the
        getting-started guide); eqsmooth's own chain solver no longer needs
        it. Results do not change.
    - `fast_compile`: add `--xla_cpu_use_fusion_emitters=false`, XLA's
        earlier fusion emitters, which compile faster with the same run
        times (the performance page has the figures). Added only if a subprocess starts
        JAX's CPU backend with it, since XLA aborts on an unknown flag; a
        `UserWarning` says when it was left out.

    **Returns:** the new value of `XLA_FLAGS`.
    """
    current = os.environ.get("XLA_FLAGS", "")
    wanted = [_SCHEDULER_FLAG] if serial_scheduler else []
    if fast_compile:
        wanted.append(_FAST_COMPILE_FLAG)
    for flag in wanted:
        if flag.split("=")[0] in current:
            continue
        candidate = f"{current} {flag}".strip()
        if flag == _FAST_COMPILE_FLAG and not _known_to_xla(candidate):
            continue
        current = candidate
    if current:
        os.environ["XLA_FLAGS"] = current
    return os.environ.get("XLA_FLAGS", "")
