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
