import gc
import os
import random
import warnings

import jax
import pytest

import eqsmooth as eqs


# XLA:CPU's MLIR fusion emitters compile about a third slower than its
# earlier emitters, and compilation is most of this suite's time (the whole
# suite with 2 workers: 858 s with them, 509 s without; docs/performance.md,
# "The test suite"). XLA reads XLA_FLAGS when JAX starts its backend (not
# when it is imported), which no test has done yet; pytest-xdist's workers
# set it the same way. (The jaxtyping hook is installed before conftest
# files load, so importing eqsmooth here keeps its runtime type checks.)
# A jaxlib that lacks the flag (XLA retires flags between releases) runs the
# suite without it: the warning is kept for the report header, not raised.
with warnings.catch_warnings(record=True) as _xla_flag_warnings:
    warnings.simplefilter("always")
    eqs.set_xla_cpu_flags(serial_scheduler=False, fast_compile=True)


def pytest_report_header(config):
    """The JAX this run tests, its backend and the XLA flags it runs with."""
    import jaxlib

    lines = [
        f"jax {jax.__version__}, jaxlib {jaxlib.__version__}, default backend "
        f"{jax.default_backend()} ({jax.devices()[0].device_kind})",
        f"XLA_FLAGS={os.environ.get('XLA_FLAGS', '')!r}",
    ]
    return lines + [f"note: {w.message}" for w in _xla_flag_warnings]


def pytest_collection_modifyitems(config, items):
    """Skip tests marked `cpu_only` (they check what XLA:CPU compiles, such as
    its LAPACK calls) when the default backend is another."""
    backend = jax.default_backend()
    if backend == "cpu":
        return
    skip = pytest.mark.skip(
        reason=f"checks XLA:CPU's compiled program; the default backend is {backend}"
    )
    for item in items:
        if item.get_closest_marker("cpu_only") is not None:
            item.add_marker(skip)


jax.config.update("jax_enable_x64", True)
jax.config.update("jax_numpy_rank_promotion", "raise")
jax.config.update("jax_numpy_dtype_promotion", "strict")


@pytest.fixture(autouse=True, scope="module")
def _unoptimised_code_generation(request):
    """Compile with LLVM's optimisation passes off, unless the module is
    marked `optimised_code`.

    Compilation is most of this suite's time and LLVM's passes about a fifth
    of it (tests/test_filters.py alone on one core: 126 s with them, 93 s
    without), while the tests' shapes are too small for optimised code to
    pay that back. This changes code generation only, not the HLO program or
    its numerics. Modules that run their compiled programs many times
    (test_discover.py alone on one core: 252 s without, 181 s with) are marked
    `optimised_code`; the examples, which CI runs, cover optimised code too.
    """
    optimise = request.node.get_closest_marker("optimised_code") is not None
    jax.config.update("jax_disable_most_optimizations", not optimise)
    yield
    jax.config.update("jax_disable_most_optimizations", False)


@pytest.fixture
def getkey():
    """Return a function producing fresh PRNG keys (deterministic per test)."""
    seed = random.Random(0)

    def _getkey():
        return jax.random.key(seed.randint(0, 2**31 - 1))

    return _getkey


@pytest.fixture(autouse=True, scope="module")
def _release_compiled_code():
    """Drop JAX's compiled executables after every test module.

    Each XLA:CPU executable holds about three memory mappings until it is
    freed. The whole suite compiles enough of them to pass the kernel's
    `vm.max_map_count` (65530 by default) in one process, and the next
    compilation then crashed inside XLA (a segfault or abort in
    `backend_compile_and_load`, at the same test every run). Modules do
    not share compiled functions, so clearing between them costs nothing.
    """
    yield
    gc.collect()
    jax.clear_caches()
    gc.collect()
