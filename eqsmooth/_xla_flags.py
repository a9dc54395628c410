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
backend with it; a flag this jaxlib lacks is left out with a warning, and
`eqsmooth.enable_compilation_cache` leaves it out quietly.
"""

import os
import subprocess
import sys
import warnings


SCHEDULER_FLAG = "--xla_cpu_enable_concurrency_optimized_scheduler=false"
FAST_COMPILE_FLAG = "--xla_cpu_use_fusion_emitters=false"


def _known_to_xla(flags: str) -> str | None:
    """`None` if JAX's CPU backend starts with `XLA_FLAGS=flags`, else the end
    of what the failed start printed (XLA aborts the process on a flag it
    does not know, so a subprocess is asked)."""
    env = {**os.environ, "XLA_FLAGS": flags, "JAX_PLATFORMS": "cpu"}
    probe = subprocess.run(
        [sys.executable, "-c", "import jax; jax.devices('cpu')"],
        env=env,
        capture_output=True,
        text=True,
    )
    return None if probe.returncode == 0 else probe.stderr[-300:]


def add_xla_flags(wanted: list[str], *, warn: bool) -> str:
    """Append to `XLA_FLAGS` each flag of `wanted` that the user has not set
    (to either value) and that this jaxlib knows; with `warn`, a
    `UserWarning` names each flag left out. One probe for all the new flags,
    and one per flag only when that probe fails. Returns the new value."""
    current = os.environ.get("XLA_FLAGS", "")
    new = [flag for flag in wanted if flag.split("=")[0] not in current]
    if new and _known_to_xla(" ".join([current, *new]).strip()) is not None:
        kept = []
        for flag in new:
            failure = _known_to_xla(f"{current} {flag}".strip())
            if failure is None:
                kept.append(flag)
            elif warn:
                warnings.warn(
                    f"set_xla_cpu_flags: JAX's CPU backend did not start with "
                    f"{flag!r} in XLA_FLAGS, so it was left out (this jaxlib, "
                    f"{_jaxlib_version()}, may not know it); nothing else changes. "
                    f"The probe's last output: {failure!r}",
                    stacklevel=3,
                )
        new = kept
    current = " ".join([current, *new]).strip()
    if current:
        os.environ["XLA_FLAGS"] = current
    return os.environ.get("XLA_FLAGS", "")


def _jaxlib_version() -> str:
    from importlib.metadata import PackageNotFoundError, version

    try:
        return f"jaxlib {version('jaxlib')}"
    except PackageNotFoundError:
        return "jaxlib of unknown version"


def set_xla_cpu_flags(
    *, serial_scheduler: bool = True, fast_compile: bool = False
) -> str:
    """Append opt-in XLA:CPU flags to the `XLA_FLAGS` environment variable.

    XLA reads the variable when JAX starts its backend, so call this before
    the first JAX computation. A flag the user has set already (to either
    value) is left alone. Every flag is added only if a subprocess starts
    JAX's CPU backend with it, since XLA aborts the process on a flag it does
    not know (XLA renames and retires its flags between jaxlib releases); a
    `UserWarning` names each flag left out, and the program runs as before
    without it.

    **Arguments:**

    - `serial_scheduler`: add
        `--xla_cpu_enable_concurrency_optimized_scheduler=false`. It lowers
        the odds of a jaxlib 0.10 CPU hang in programs that run several
        batched LAPACK kernels concurrently (see "Running on CPU" in the
        getting-started guide); eqsmooth's own chain solver no longer needs
        it. Results do not change.
    - `fast_compile`: add `--xla_cpu_use_fusion_emitters=false`, XLA's
        earlier fusion emitters, which compile faster with the same run
        times (the performance page has the figures).

    **Returns:** the new value of `XLA_FLAGS`.
    """
    wanted = [SCHEDULER_FLAG] if serial_scheduler else []
    if fast_compile:
        wanted.append(FAST_COMPILE_FLAG)
    return add_xla_flags(wanted, warn=True)
