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


class _OtherLine(eqx.Module):
    """Another model whose leaves have `_Line`'s shapes and dtypes."""

    w: jax.Array
    b: jax.Array


class _Scaled(eqx.Module):
    """`_Line`'s leaves under other field names."""

    scale: jax.Array
    offset: jax.Array


def _other_loss(model, batch):
    leaves = jax.tree_util.tree_leaves(model)
    return jnp.mean((leaves[0] * batch["x"] + leaves[1] - batch["y"]) ** 2)


@pytest.mark.parametrize(
    "change, pattern",
    [
        ("model class", "_Line.*_OtherLine|_OtherLine.*_Line"),
        ("field names", "has `_Line\\(` where this run has `_Scaled\\(`"),
        ("optimiser", "ScaleByAdamState|EmptyState|TraceState"),
        ("batch size", "batch_size"),
    ],
)
def test_a_checkpoint_resumes_only_its_own_run(change, pattern, tmp_path):
    """A checkpoint written by one run is refused by another: another model
    with leaves of the same shapes, the same leaves under other names, an
    SGD run reading an Adam checkpoint (which used to fill the best model,
    metric and step from Adam's moments, the step count and the seed), or
    another batch size. The error names the first difference and is raised
    at once, not treated as damage."""
    from eqsmooth.learn import CheckpointError, Checkpoints, Logging, train

    ckpt = tmp_path / "ckpt.eqx"
    model0 = _Line(jnp.asarray(0.0), jnp.asarray(0.0))
    kw = dict(num_steps=6, batch_size=8, logging=Logging(progress=False))
    train(
        model0,
        _loss,
        _data(),
        optimizer=optax.adam(0.05),
        checkpoints=Checkpoints(ckpt, every=3),
        **kw,
    )
    model, loss, optimizer = model0, _loss, optax.adam(0.05)
    if change == "model class":
        model, loss = _OtherLine(jnp.asarray(0.0), jnp.asarray(0.0)), _other_loss
    elif change == "field names":
        model, loss = _Scaled(jnp.asarray(0.0), jnp.asarray(0.0)), _other_loss
    elif change == "optimiser":
        optimizer = optax.sgd(0.05)
    else:
        kw["batch_size"] = 4
    error = CheckpointError if change != "batch size" else ValueError
    with pytest.raises(error, match=pattern) as info:
        train(
            model,
            loss,
            _data(),
            optimizer=optimizer,
            checkpoints=Checkpoints(ckpt, every=3),
            **{**kw, "num_steps": 9},
        )
    assert str(ckpt) in str(info.value)
    # The run that wrote it still resumes.
    res = train(
        model0,
        _loss,
        _data(),
        optimizer=optax.adam(0.05),
        checkpoints=Checkpoints(ckpt, every=3),
        **{**kw, "batch_size": 8, "num_steps": 9},
    )
    assert res.step == 9
