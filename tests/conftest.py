import gc
import random

import jax
import pytest


jax.config.update("jax_enable_x64", True)
jax.config.update("jax_numpy_rank_promotion", "raise")
jax.config.update("jax_numpy_dtype_promotion", "strict")


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
