"""Damaged checkpoints, each with fallback to the previous one: a truncated
file and a corrupted (one flipped byte) file. Both are named as such and
`train` resumes from `ckpt.eqx.prev` and still ends bitwise where an
uninterrupted run ends. (tests/test_train.py checks the same detection on
`load_checkpoint` directly and the case where both files are damaged.)"""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optax
import pytest


class _Line(eqx.Module):
    w: jax.Array
    b: jax.Array


def _loss(model, batch):
    return jnp.mean((model.w * batch["x"] + model.b - batch["y"]) ** 2)


def _data():
    rng = np.random.default_rng(0)
    x = rng.normal(size=32)
    return {"x": x, "y": 2.0 * x + 0.5}


def _same(a, b):
    la, lb = jax.tree_util.tree_leaves(a), jax.tree_util.tree_leaves(b)
    return all(np.array_equal(np.asarray(x), np.asarray(y)) for x, y in zip(la, lb))


@pytest.mark.parametrize("damage", ["truncated", "corrupted"])
def test_damaged_checkpoint_falls_back(damage, tmp_path):
    from eqsmooth.learn import Checkpoints, Logging, train

    model0 = _Line(jnp.asarray(0.0), jnp.asarray(0.0))
    kw = dict(
        optimizer=optax.sgd(0.05),
        num_steps=12,
        batch_size=8,
        logging=Logging(progress=False),
    )
    full = train(model0, _loss, _data(), **kw)
    ckpt = tmp_path / "ckpt.eqx"
    train(
        model0,
        _loss,
        _data(),
        checkpoints=Checkpoints(ckpt, every=5),
        **{**kw, "num_steps": 10},
    )
    good = ckpt.read_bytes()
    if damage == "truncated":
        ckpt.write_bytes(good[: len(good) // 2])
    else:
        flipped = bytearray(good)
        flipped[-5] ^= 0x01
        ckpt.write_bytes(bytes(flipped))
    with pytest.warns(UserWarning, match=f"{damage}.*previous checkpoint.*step 5"):
        res = train(
            model0, _loss, _data(), checkpoints=Checkpoints(ckpt, every=5), **kw
        )
    assert res.step == 12 and _same(res.model, full.model)
