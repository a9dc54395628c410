"""The README's Python snippets run as printed (a pose graph, learning a
smoother's noise through the solve) and do what their comments say."""

import re
from pathlib import Path

import jax
import numpy as np


README = Path(__file__).resolve().parents[1] / "README.md"


def _blocks() -> list[str]:
    return re.findall(r"```python\n(.*?)```", README.read_text(), re.S)


def test_readme_snippets_run(capsys):
    blocks = _blocks()
    assert len(blocks) == 2
    pose, learn = ({}, {})
    exec(compile(blocks[0], "README.md:pose-graph", "exec"), pose)
    positions = np.asarray(pose["sol"].value["x"].translation())
    np.testing.assert_allclose(
        positions, [[0, 0], [2, 0], [4, 0], [4, 2], [2, 2]], atol=1e-6
    )
    # A user's session has JAX's standard dtype promotion (the suite's is
    # strict, which optax's adam does not follow).
    with jax.numpy_dtype_promotion("standard"):
        exec(compile(blocks[1], "README.md:learning", "exec"), learn)
    sigma = float(np.exp(learn["log_sigma"]))
    assert 0.2 < sigma < 0.4  # the true process σ is 0.3, started at 3
    capsys.readouterr()


def test_docs_home_pose_graph_runs():
    home = README.parent / "docs" / "index.md"
    block = re.findall(r"```python\n(.*?)```", home.read_text(), re.S)[0]
    scope = {}
    exec(compile(block, "docs/index.md:pose-graph", "exec"), scope)
    assert scope["covariances"].shape == (5, 3, 3)
    np.testing.assert_allclose(
        np.asarray(scope["sol"].value["x"].translation())[3], [4, 2], atol=1e-6
    )
