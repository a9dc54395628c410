"""eqsmooth.enable_compilation_cache: a second process reads the first one's
compiled solve from disk instead of compiling it again."""

import json
import subprocess
import sys
import textwrap

from helpers import child_env


_CHILD = textwrap.dedent(
    """
    import json, sys
    import eqsmooth as eqs
    path = eqs.enable_compilation_cache(sys.argv[1])
    import jax, jax.numpy as jnp
    from jax import monitoring
    events = []
    monitoring.register_event_listener(lambda name, **kw: events.append(name))
    graph = eqs.FactorGraph([
        eqs.PriorFactor(eqs.Var("x", [0, 1]), jnp.ones((2, 1)),
                        eqs.IsotropicNoise.from_sigma(1.0)),
        eqs.BetweenFactor(eqs.Var("x", [0]), eqs.Var("x", [1]), jnp.zeros((1, 1)),
                          eqs.IsotropicNoise.from_sigma(1.0)),
    ])
    sol = eqs.least_squares(graph, {"x": jnp.zeros((2, 1))}, eqs.GaussNewton())
    jax.block_until_ready(sol.value)
    print(json.dumps({
        "dir": str(path),
        "hits": sum(e.endswith("cache_hits") for e in events),
        "misses": sum(e.endswith("cache_misses") for e in events),
    }))
    """
)


def _run(cache):
    out = subprocess.run(
        [sys.executable, "-c", _CHILD, str(cache)],
        env=child_env(),
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert out.returncode == 0, out.stderr[-2000:]
    return json.loads(out.stdout.strip().splitlines()[-1])


def test_second_process_reads_the_cache(tmp_path):
    cache = tmp_path / "cache"
    first = _run(cache)
    assert first["dir"] == str(cache) and first["misses"] >= 1 and first["hits"] == 0
    assert any(cache.iterdir())
    second = _run(cache)
    assert second["hits"] >= 1 and second["misses"] == 0, second
