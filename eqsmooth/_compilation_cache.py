"""One call for fast first answers: XLA's faster compiler flags, JAX's
persistent compilation cache, and a store of traced programs."""

import dataclasses
import functools
import hashlib
import importlib.metadata
import importlib.resources
import inspect
import logging
import os
import pickle
import re
from collections.abc import Callable
from pathlib import Path

import equinox as eqx
import jax

from ._xla_flags import add_xla_flags, FAST_COMPILE_FLAG, SCHEDULER_FLAG


def default_cache_dir() -> Path:
    """`$XDG_CACHE_HOME/eqsmooth/jax` (by default `~/.cache/eqsmooth/jax`)."""
    root = os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache"
    return Path(root) / "eqsmooth" / "jax"


# Where `stored_program`s keep their traced programs (None: not kept).
_PROGRAM_DIR: Path | None = None
_log = logging.getLogger(__name__)


def enable_compilation_cache(
    cache_dir: str | os.PathLike | None = None,
    *,
    fast_compile: bool = True,
    store_programs: bool = True,
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

    JAX still traces and lowers every program in each new process to find
    it in the cache, and for the large programs of `eqsmooth.discover`
    that took most of a first call (22 of 28 s on a loaded machine). With
    `store_programs`, those programs are also kept as lowered
    (StableHLO) programs, keyed by everything their tracing depends on: the
    installed eqsmooth sources, the JAX version and settings, the shapes,
    dtypes and static settings of the arguments, and the traced model
    functions (a model's transition and measurement functions with its
    candidates, so an edited model function makes a new program). A later
    process calls the stored program without tracing it.

    **Arguments:**

    - `cache_dir`: where to keep the compiled programs (created if needed);
        by default `$XDG_CACHE_HOME/eqsmooth/jax` (`~/.cache/eqsmooth/jax`).
    - `fast_compile`: also call
        [`eqsmooth.set_xla_cpu_flags`][]`(fast_compile=True)` (XLA's
        earlier fusion emitters: about a third less compile time), leaving
        out quietly any flag this jaxlib does not know.
    - `store_programs`: also keep traced programs (in `cache_dir/programs`),
        as described above. They are pickled files: keep the folder as
        private as the compiled programs beside it.

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
    global _PROGRAM_DIR
    _PROGRAM_DIR = path / "programs" if store_programs else None
    if _PROGRAM_DIR is not None:
        _PROGRAM_DIR.mkdir(exist_ok=True)
    return path


# ---------------------------------------------------------------------------
# Stored programs: skip tracing in later processes
# ---------------------------------------------------------------------------

# Bump when the stored format or the key changes.
_FORMAT = 1
_FAILED = object()


def _sources(folder, prefix: str = ""):
    """Every `.py` file under `folder` (an `importlib.resources` traversable,
    so it works for a checkout and an installed wheel alike), as
    `(relative name, bytes)` in a fixed order."""
    for entry in sorted(folder.iterdir(), key=lambda e: e.name):
        name = f"{prefix}{entry.name}"
        if entry.is_dir():
            yield from _sources(entry, f"{name}/")
        elif entry.name.endswith(".py"):
            yield name, entry.read_bytes()


@functools.cache
def _environment() -> str:
    """What every stored program depends on besides its own arguments: the
    eqsmooth sources (any edit makes new keys), JAX's version and the
    settings that change tracing."""
    digest = hashlib.sha256()
    for name, source in _sources(importlib.resources.files("eqsmooth")):
        digest.update(name.encode())
        digest.update(source)
    settings = [
        f"{name}={getattr(jax.config, name, None)}"
        for name in (
            "jax_enable_x64",
            "jax_default_matmul_precision",
            "jax_numpy_dtype_promotion",
            "jax_numpy_rank_promotion",
            "jax_default_prng_impl",
        )
    ]
    versions = [jax.__version__, importlib.metadata.version("jaxlib")]
    backend = [jax.default_backend(), jax.devices()[0].device_kind]
    return "\n".join(
        [f"format {_FORMAT}", digest.hexdigest()] + versions + backend + settings
    )


# Object addresses in reprs (`<function f at 0x7f...>`) differ between
# processes; what such an object does enters the key through `fingerprint`.
_ADDRESS = re.compile(r" at 0x[0-9a-fA-F]+")


def _weak(x) -> bool:
    return bool(getattr(x, "weak_type", False))


@functools.cache
def _device() -> jax.sharding.SingleDeviceSharding:
    return jax.sharding.SingleDeviceSharding(jax.devices()[0])


def _elsewhere(x, device) -> bool:
    """Whether `x` is traced, or placed on another device than the default
    one that stored programs run on."""
    if isinstance(x, jax.core.Tracer):
        return True
    return isinstance(x, jax.Array) and x.committed and x.sharding != device


def stored_program(
    fn: Callable, jitted: Callable, fingerprint: Callable[[dict], str]
) -> Callable:
    """`jitted` (the compiled `fn`), reading and writing traced programs in
    the folder `enable_compilation_cache` set, if it did.

    `fn`'s non-array arguments are static (as for `eqx.filter_jit`).
    `fingerprint(arguments)` (the bound arguments by name) returns text that
    changes whenever a callable among the static arguments would trace to
    another program: the static arguments enter the key by their reprs,
    with object addresses removed. A call under a JAX transformation (traced
    arguments) or a program that cannot be exported runs `jitted` instead.
    """
    signature = inspect.signature(fn)
    programs: dict = {}  # this process's: (structure, static, avals) -> program

    @functools.wraps(fn)
    def call(*args, **kwargs):
        if _PROGRAM_DIR is None:
            return jitted(*args, **kwargs)
        bound = signature.bind(*args, **kwargs)
        bound.apply_defaults()
        full = (bound.args, bound.kwargs)
        dynamic, static = eqx.partition(full, eqx.is_array)
        leaves, structure = jax.tree.flatten(dynamic)
        device = _device()
        if any(_elsewhere(x, device) for x in leaves):
            return jitted(*args, **kwargs)
        static_leaves, static_structure = jax.tree.flatten(static)
        avals = tuple((x.shape, str(x.dtype), _weak(x)) for x in leaves)
        key = (structure, static_structure, tuple(static_leaves), avals)
        program = programs.get(key)
        if program is None:
            program = programs[key] = _load_or_export(
                fn, structure, static, avals, fingerprint(bound.arguments)
            )
        if program is _FAILED:
            return jitted(*args, **kwargs)
        run, out_structure = program
        return jax.tree.unflatten(out_structure, run(*leaves))

    return call


def _load_or_export(fn, structure, static, avals, fingerprint: str):
    """`(callable of the flat arrays, output structure)` of `fn` from the
    program folder, exported there first if missing; `_FAILED` if `fn`
    cannot be exported (it then runs as before)."""
    description = "\n".join(
        [
            _environment(),
            f"{fn.__module__}.{fn.__qualname__}",
            _ADDRESS.sub("", str(structure)),
            _ADDRESS.sub("", str(jax.tree.structure(static))),
            _ADDRESS.sub("", repr(jax.tree.leaves(static))),
            repr(avals),
            fingerprint,
        ]
    )
    digest = hashlib.sha256(description.encode()).hexdigest()[:40]
    path = _PROGRAM_DIR / f"{fn.__name__}-{digest}.pkl"
    try:
        exported, skeleton = pickle.loads(path.read_bytes())
        out_structure = jax.tree.structure(skeleton)
    except Exception:  # noqa: BLE001 - missing, unreadable or stale: export again
        out_structures = []

        def flat(*leaves):
            args, kwargs = eqx.combine(jax.tree.unflatten(structure, leaves), static)
            out_leaves, out_structure = jax.tree.flatten(fn(*args, **kwargs))
            out_structures.append(out_structure)
            return out_leaves

        specs = [jax.ShapeDtypeStruct(s, d, weak_type=w) for s, d, w in avals]
        try:
            exported = jax.export.export(jax.jit(flat))(*specs)
            out_structure = out_structures[-1]
            # Without its derivative rule (a closure): stored programs are
            # called outside transformations only. The output structure as
            # a tree of placeholders: a pickled PyTreeDef of an equinox
            # Module does not unflatten.
            skeleton = jax.tree.unflatten(out_structure, [0] * out_structure.num_leaves)
            blob = pickle.dumps(
                (dataclasses.replace(exported, _get_vjp=None), skeleton)
            )
        except Exception as e:  # noqa: BLE001 - any failure: run as before
            _log.debug("eqsmooth: %s is not stored: %r", fn.__qualname__, e)
            return _FAILED
        temporary = path.with_suffix(f".{os.getpid()}.tmp")
        try:
            temporary.write_bytes(blob)
            os.replace(temporary, path)
        except OSError as e:
            _log.debug("eqsmooth: could not write %s: %r", path, e)
        # Called as a later process will read it back: the program that
        # calls it is then the same, and so is its key in JAX's cache (the
        # exported object before pickling made another key).
        exported = pickle.loads(blob)[0]
    # Placed explicitly: arguments committed to the device (outputs of
    # other programs) and uncommitted ones (NumPy arrays) otherwise lower
    # to two programs, each compiled (the score program twice, 70 s).
    return jax.jit(exported.call, in_shardings=_device()), out_structure
