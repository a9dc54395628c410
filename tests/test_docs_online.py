"""The online-smoothing snippets of the docs run: every ```python block of
docs/tutorial/online-smoothing.md, in order, in one namespace (the page's
first block is its setup: a 12-pose planar robot), and the online blocks of
docs/coming-from-gtsam.md (those under its "Porting an online smoother"
heading).

Hidden setup: the GTSAM page's online block uses the robot of the online
page (`eqs`, `eqx`, `T`, `odo`, `odo_noise`, `gps_xy`, `gps_noise`,
`mean0`, `cov0`), as its text says; the test runs the online page's first
block before it. Nothing else is added to what the pages show."""

import pathlib
import re

import jax
import jax.numpy as jnp
import numpy as np
import pytest


DOCS = pathlib.Path(__file__).resolve().parent.parent / "docs"
ONLINE = DOCS / "tutorial" / "online-smoothing.md"
GTSAM = DOCS / "coming-from-gtsam.md"

_FENCE = re.compile(r"^```python\n(.*?)^```$", re.S | re.M)


def python_blocks(path: pathlib.Path) -> list[tuple[str, int, str]]:
    """`(heading, line, code)` of every fenced ```python block of a page: the
    `##` heading it sits under, the line its code starts on, its code."""
    text = path.read_text()
    out = []
    for m in _FENCE.finditer(text):
        before = text[: m.start()]
        headings = re.findall(r"^#+ (.*)$", before, re.M)
        line = before.count("\n") + 2
        out.append((headings[-1] if headings else "", line, m.group(1)))
    return out


def _run(blocks, path: pathlib.Path, namespace: dict) -> None:
    for _, line, code in blocks:
        # The file name and line of the block, so a failure points at the page.
        exec(compile("\n" * (line - 1) + code, str(path), "exec"), namespace)


def test_the_parser_finds_the_blocks():
    blocks = python_blocks(ONLINE)
    assert len(blocks) >= 5
    assert "T = 12" in blocks[0][2]  # the setup comes first
    assert all(code.strip() for _, _, code in blocks)


def test_online_page_runs():
    ns: dict = {}
    _run(python_blocks(ONLINE), ONLINE, ns)
    eqs, T = ns["eqs"], ns["T"]
    # The scan (the last block: with closures) and the updates answered
    # every state, near the truth.
    sol = ns["sol"]
    assert ns["lag"] == 10
    err = eqs.local(sol.mean, ns["poses"], batch_ndim=1)
    assert np.isfinite(np.asarray(err)).all() and float(np.abs(err).max()) < 0.5
    state = ns["state"]
    assert int(state.t) == T - 1 and int(state.window_start) == T - 10
    assert np.isfinite(np.asarray(ns["x_now"].parameters())).all()
    # The growing graph (noiseless odometry and closures, the prior at the
    # truth): every pose, at the truth.
    grown = eqs.SE2(jnp.asarray(ns["estimate"].unit_complex_xy))
    assert grown.unit_complex_xy.shape == (T, 4)
    assert float(jnp.abs(eqs.local(grown, ns["poses"], batch_ndim=1)).max()) < 1e-6


def test_gtsam_page_online_blocks_run():
    blocks = [b for b in python_blocks(GTSAM) if "online" in b[0].lower()]
    assert len(blocks) == 1
    ns: dict = {}
    _run(python_blocks(ONLINE)[:1], ONLINE, ns)  # the hidden setup
    _run(blocks, GTSAM, ns)
    state, T = ns["state"], ns["T"]
    assert int(state.t) == T - 1
    assert jax.tree_util.tree_leaves(ns["window"])[0].shape[0] == 10


if __name__ == "__main__":
    pytest.main([__file__, "-q", "-n0"])
