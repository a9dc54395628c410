"""One call for fast first answers: XLA's faster compiler flags and JAX's
persistent compilation cache."""

import os
from pathlib import Path

import jax

from ._xla_flags import add_xla_flags, FAST_COMPILE_FLAG, SCHEDULER_FLAG


def default_cache_dir() -> Path:
    """`$XDG_CACHE_HOME/eqsmooth/jax` (by default `~/.cache/eqsmooth/jax`)."""
    root = os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache"
    return Path(root) / "eqsmooth" / "jax"


def enable_compilation_cache(
    cache_dir: str | os.PathLike | None = None, *, fast_compile: bool = True
) -> Path:
    """Turn on JAX's persistent compilation cache (and, by default, XLA:CPU's
    faster fusion emitters), so that a program compiled once is read back
    by every later process instead of being compiled again.

    Every new graph structure (factor types, stack sizes, variable indices)
    is a new program for XLA, and compiling it dominates the first answer;
    later solves of the same structure take milliseconds. With the cache, a
    second process that solves a graph of a structure solved before reads
    the compiled program from disk instead (measurements on the performance
    page). Call it once, before the first JAX computation (the flags are
    read when JAX starts its backend); it changes nothing else, and nothing
    is cached unless you call it.

    **Arguments:**

    - `cache_dir`: where to keep the compiled programs (created if needed);
        by default `$XDG_CACHE_HOME/eqsmooth/jax` (`~/.cache/eqsmooth/jax`).
    - `fast_compile`: also call
        [`eqsmooth.set_xla_cpu_flags`][]`(fast_compile=True)` (XLA's
        earlier fusion emitters: about a third less compile time), leaving
        out quietly any flag this jaxlib does not know.

    **Returns:** the cache folder.
    """
    path = Path(cache_dir) if cache_dir is not None else default_cache_dir()
    path.mkdir(parents=True, exist_ok=True)
    if fast_compile:
        # As set_xla_cpu_flags(fast_compile=True), without its warning for a
        # flag this jaxlib lacks: the cache works the same without it.
        add_xla_flags([SCHEDULER_FLAG, FAST_COMPILE_FLAG], warn=False)
    jax.config.update("jax_compilation_cache_dir", str(path))
    # Cache every program: eqsmooth's small solves compile in well under the
    # default one-second threshold, and are exactly the ones worth keeping.
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)
    jax.config.update("jax_persistent_cache_min_entry_size_bytes", 0)
    return path
