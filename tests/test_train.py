"""Training utilities: optimiser, loop, model selection, checkpoints, resume."""

import json
import signal
import subprocess
import sys
import textwrap
import time

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optax
import pytest
from helpers import child_env

from eqsmooth.learn import (
    atomic_write,
    CheckpointError,
    Checkpoints,
    epoch_order,
    evaluate,
    load_checkpoint,
    Logging,
    make_optimizer,
    previous_checkpoint,
    read_checkpoint_header,
    train,
    TrainState,
    Validation,
)


class Line(eqx.Module):
    w: jax.Array
    b: jax.Array


def _line_loss(model, batch):
    pred = model.w * batch["x"] + model.b
    return jnp.mean((pred - batch["y"]) ** 2)


def _line_data(slope, n=32, seed=0):
    rng = np.random.default_rng(seed)
    x = rng.normal(size=n)
    return {"x": x, "y": slope * x + 0.5 + 0.01 * rng.normal(size=n)}


def _same(a, b):
    la, lb = jax.tree_util.tree_leaves(a), jax.tree_util.tree_leaves(b)
    return len(la) == len(lb) and all(
        np.array_equal(np.asarray(x), np.asarray(y)) for x, y in zip(la, lb)
    )


_LINE0 = Line(jnp.asarray(0.0), jnp.asarray(0.0))


def _like():
    """A `TrainState` shaped like a run of `_LINE0` under `optax.sgd`."""
    return TrainState(
        model=_LINE0,
        opt_state=optax.sgd(0.05).init(_LINE0),
        step=0,
        seed=0,
        best_model=_LINE0,
        best_metric=0.0,
        best_step=0,
    )


def _train_line(**kw):
    """`train` of `_LINE0` on `_line_data(2.0)` with `optax.sgd(0.05)`, 60
    steps of batch 8 and no progress bar, but for what `kw` says."""
    defaults = dict(
        optimizer=optax.sgd(0.05),
        num_steps=60,
        batch_size=8,
        logging=Logging(progress=False),
    )
    return train(_LINE0, _line_loss, _line_data(2.0), **{**defaults, **kw})


def test_make_optimizer_warmup_decay_and_clipping():
    params = {"a": jnp.zeros(3)}
    grads = {"a": jnp.array([3.0, -4.0, 0.0])}  # global norm 5
    opt = make_optimizer(0.1, warmup_steps=4, decay_steps=10, clip_norm=1.0)
    state = opt.init(params)
    ups = []
    for _ in range(11):
        u, state = opt.update(grads, state, params)
        ups.append(np.asarray(u["a"]))
    # Adam with a constant gradient moves each coordinate by -lr(t) * sign(g).
    lr = [0.0, 0.025, 0.05, 0.075, 0.1]
    for t in range(5):
        np.testing.assert_allclose(ups[t][:2], [-lr[t], lr[t]], rtol=1e-6, atol=1e-12)
    assert ups[4][2] == 0.0
    assert 0 < -ups[6][0] < 0.1  # in the cosine decay
    np.testing.assert_allclose(ups[10][:2], 0.0, atol=1e-12)  # decayed to 0
    # Clipping happens before Adam: the clipped gradient reaches Adam's moments.
    clip_only = make_optimizer(0.1, clip_norm=1.0)
    s = clip_only.init(params)
    _, s = clip_only.update(grads, s, params)
    mu = jax.tree_util.tree_leaves(s[1][0].mu)[0]  # chain -> adam -> scale_by_adam
    np.testing.assert_allclose(np.asarray(mu), 0.1 * np.array([0.6, -0.8, 0.0]))
    with pytest.raises(ValueError, match="decay_steps"):
        make_optimizer(0.1, warmup_steps=5, decay_steps=5)


def test_epoch_order_is_a_function_of_seed_and_epoch():
    a = epoch_order(3, 7, 20)
    np.testing.assert_array_equal(a, epoch_order(3, 7, 20))
    assert sorted(a.tolist()) == list(range(20))
    assert not np.array_equal(a, epoch_order(3, 8, 20))
    assert not np.array_equal(a, epoch_order(4, 7, 20))


def test_train_reduces_loss_and_logs(tmp_path):
    data = _line_data(2.0)
    log = tmp_path / "log.jsonl"
    res = train(
        _LINE0,
        _line_loss,
        data,
        optimizer=make_optimizer(0.1, warmup_steps=5),
        num_steps=150,
        batch_size=8,
        logging=Logging(log, every=10, progress=False),
    )
    first = float(_line_loss(_LINE0, data))
    last = float(_line_loss(res.model, data))
    assert last < 1e-2 * first
    np.testing.assert_allclose(float(res.model.w), 2.0, atol=0.05)
    records = [json.loads(line) for line in log.read_text().splitlines()]
    assert [r["step"] for r in records] == list(range(10, 151, 10))
    assert {"step", "epoch", "loss", "grad_norm", "time"} <= set(records[0])
    assert res.history == records
    assert res.step == 150 and res.best_step == 150


def test_nonfinite_batches_raise_or_are_skipped():
    data = _line_data(2.0, n=16)
    data["y"][5] = np.nan  # one bad example
    kw = dict(
        optimizer=make_optimizer(0.1, warmup_steps=2),
        num_steps=20,
        batch_size=4,
        logging=Logging(progress=False),
    )
    order = epoch_order(0, 0, 16)
    bad_step = int(np.nonzero(order == 5)[0][0]) // 4 + 1
    with pytest.raises(FloatingPointError, match=f"step {bad_step} .*examples .*5"):
        train(_LINE0, _line_loss, data, **kw)
    res = train(_LINE0, _line_loss, data, on_nonfinite="skip", **kw)
    assert np.isfinite(float(res.model.w)) and np.isfinite(float(res.model.b))
    # One of the 4 batches of every epoch holds the bad example: 5 epochs.
    assert res.history[-1]["skipped"] == 5
    clean = {k: np.delete(v, 5) for k, v in data.items()}
    assert float(_line_loss(res.model, clean)) < 0.2 * float(_line_loss(_LINE0, clean))
    with pytest.raises(ValueError, match="on_nonfinite"):
        train(_LINE0, _line_loss, data, on_nonfinite="ignore", **kw)
    # Every batch non-finite: skipping them all trains nothing, and says so.
    all_bad = {k: np.where(True, np.nan, v) for k, v in data.items()}
    with pytest.raises(FloatingPointError, match="every one of the 20 steps"):
        train(_LINE0, _line_loss, all_bad, on_nonfinite="skip", **kw)


def test_nonfinite_validation_example_is_named():
    # One NaN validation example made every validation loss NaN, and model
    # selection silently kept the untrained model (NaN never compares lower).
    data = _line_data(2.0, n=16)
    valid = _line_data(2.0, n=12)
    valid["y"][7] = np.nan
    with pytest.raises(FloatingPointError, match="examples 4..7 \\(of 12\\)"):
        train(
            _LINE0,
            _line_loss,
            data,
            validation=Validation(valid),
            optimizer=make_optimizer(0.1),
            num_steps=4,
            batch_size=4,
            logging=Logging(progress=False),
        )


def test_augment_sees_a_key_per_step_and_never_touches_validation():
    data = _line_data(2.0, n=16)

    def augment(batch, key):
        # Shift the targets by 1 plus a little key-dependent noise.
        noise = 0.01 * jax.random.normal(key, batch["y"].shape)
        return {**batch, "y": batch["y"] + 1.0 + noise}

    kw = dict(
        optimizer=make_optimizer(0.1, warmup_steps=2),
        num_steps=60,
        batch_size=4,
        logging=Logging(progress=False),
        validation=Validation(data, every=60),
    )
    res = train(_LINE0, _line_loss, data, augment=augment, **kw)
    # The model learned the augmented targets (intercept 0.5 + 1) ...
    assert abs(float(res.model.b) - 1.5) < 0.1
    # ... and the validation loss was computed on the raw data: about 1.
    assert 0.8 < res.history[-1]["valid_loss"] < 1.2
    # The key depends on (seed, step) only: the same run gives the same bytes,
    # another seed gives another model.
    again = train(_LINE0, _line_loss, data, augment=augment, **kw)
    assert _same(res.model, again.model)
    other = train(_LINE0, _line_loss, data, augment=augment, seed=1, **kw)
    assert not _same(res.model, other.model)


def test_model_selection_keeps_best_validation_model(tmp_path):
    # Training pulls the slope to 2; validation prefers slope 1, which the
    # trajectory passes on its way: the best model is an intermediate one.
    res = _train_line(
        validation=Validation(_line_data(1.0, seed=1), every=5),
        checkpoints=Checkpoints(tmp_path / "ckpt.eqx", every=7),
    )
    valid = {r["step"]: r["valid_loss"] for r in res.history if "valid_loss" in r}
    assert sorted(valid) == list(range(0, 61, 5))
    best_step = min(valid, key=lambda k: valid[k])
    assert 0 < best_step < 60
    assert res.best_step == best_step
    assert res.best_valid_loss == valid[best_step]
    np.testing.assert_allclose(
        float(evaluate(res.best_model, _line_loss, _line_data(1.0, seed=1), 8)),
        res.best_valid_loss,
        rtol=1e-12,
    )
    assert float(_line_loss(res.best_model, _line_data(1.0, seed=1))) < float(
        _line_loss(res.model, _line_data(1.0, seed=1))
    )

    # The final checkpoint holds model, optimiser state, step, seed and the best
    # model, and nothing half-written is left behind.
    ckpt = tmp_path / "ckpt.eqx"
    header = read_checkpoint_header(ckpt)
    assert header["step"] == 60 and header["seed"] == 0
    assert header["best_step"] == best_step
    assert header["best_metric"] == res.best_valid_loss
    assert header["metadata"] == {"num_examples": 32, "batch_size": 8}
    assert sorted(p.name for p in tmp_path.iterdir()) == ["ckpt.eqx", "ckpt.eqx.prev"]
    assert read_checkpoint_header(tmp_path / "ckpt.eqx.prev")["step"] == 56
    like = _like()
    state = load_checkpoint(ckpt, like)
    assert state.step == 60 and state.best_step == best_step
    assert _same(state.model, res.model)
    assert _same(state.best_model, res.best_model)
    assert state.best_metric == res.best_valid_loss

    # Resuming a finished run does nothing; a different seed is refused.
    again = _train_line(
        validation=Validation(_line_data(1.0, seed=1)), checkpoints=Checkpoints(ckpt)
    )
    assert _same(again.model, res.model)
    assert again.best_step == best_step
    with pytest.raises(ValueError, match="seed"):
        _train_line(seed=1, checkpoints=Checkpoints(ckpt))


def test_damaged_checkpoints_are_named_and_the_previous_one_is_used(tmp_path):
    ckpt = tmp_path / "ckpt.eqx"
    full = _train_line(num_steps=12)
    # Stop at step 10 (checkpoints at 5 and 10), then damage the newest file.
    _train_line(checkpoints=Checkpoints(ckpt, every=5), num_steps=10)
    like = _like()
    good = ckpt.read_bytes()
    ckpt.write_bytes(good[:-3])
    with pytest.raises(CheckpointError, match="truncated"):
        load_checkpoint(ckpt, like)
    flipped = bytearray(good)
    flipped[-5] ^= 0x01
    ckpt.write_bytes(bytes(flipped))
    with pytest.raises(CheckpointError, match="corrupted"):
        load_checkpoint(ckpt, like)
    # Resuming falls back to the checkpoint of step 5, says so, and still
    # ends bitwise where an uninterrupted run ends (the data order is fixed).
    with pytest.warns(UserWarning, match="corrupted.*step 5"):
        res = _train_line(checkpoints=Checkpoints(ckpt, every=5), num_steps=12)
    assert res.step == 12 and _same(res.model, full.model)
    # With both files damaged there is nothing to resume from: say why.
    ckpt.write_bytes(good[:-3])
    previous_checkpoint(ckpt).write_bytes(b"garbage\n")
    with pytest.raises(CheckpointError, match="no usable checkpoint.*truncated"):
        _train_line(checkpoints=Checkpoints(ckpt), num_steps=12)


def test_atomic_write_keeps_old_file_on_failure(tmp_path):
    path = tmp_path / "f.bin"
    atomic_write(path, lambda f: f.write(b"old"))

    def broken(f):
        f.write(b"partial")
        raise RuntimeError("disk full")

    with pytest.raises(RuntimeError, match="disk full"):
        atomic_write(path, broken)
    assert path.read_bytes() == b"old"
    assert [p.name for p in tmp_path.iterdir()] == ["f.bin"]


def test_bad_inputs():
    with pytest.raises(ValueError, match="batch_size"):
        train(
            _LINE0,
            _line_loss,
            _line_data(2.0, n=4),
            optimizer=optax.sgd(0.1),
            num_steps=1,
            batch_size=8,
            logging=Logging(progress=False),
        )
    with pytest.raises(ValueError, match="leading"):
        train(
            _LINE0,
            _line_loss,
            {"x": np.zeros(8), "y": np.zeros(9)},
            optimizer=optax.sgd(0.1),
            num_steps=1,
            batch_size=2,
            logging=Logging(progress=False),
        )
    with pytest.raises(ValueError, match="not an eqsmooth checkpoint"):
        read_checkpoint_header(__file__)


# ------------------------------------------------------------------ kill and resume

_SCRIPT = textwrap.dedent(
    """
    import json, sys, time
    import jax
    jax.config.update("jax_enable_x64", True)
    import equinox as eqx, jax.numpy as jnp, numpy as np
    from eqsmooth.learn import Checkpoints, Logging, make_optimizer, train, Validation

    ckpt, log, out, sleep = sys.argv[1], sys.argv[2], sys.argv[3], float(sys.argv[4])
    if len(sys.argv) > 5:
        # Killed in the middle of writing the checkpoint of step argv[5]: the
        # real atomic_write runs, its temporary file gets half the bytes, and
        # the process is SIGKILLed before the rename.
        import os, signal
        import eqsmooth.learn._checkpoint as C
        kill_at, real = int(sys.argv[5]), C.atomic_write

        def dying(path, write):
            import io
            buf = io.BytesIO()
            write(buf)
            data = buf.getvalue()
            if json.loads(data.split(b"\\n", 1)[0])["step"] != kill_at:
                return real(path, write)

            def half(f):
                f.write(data[: len(data) // 2])
                f.flush()
                os.fsync(f.fileno())
                os.kill(os.getpid(), signal.SIGKILL)

            return real(path, half)

        C.atomic_write = dying
    rng = np.random.default_rng(0)
    x = rng.normal(size=(64, 2))
    y = np.sin(x[:, :1]) + x[:, 1:] ** 2
    xv = rng.normal(size=(16, 2))
    yv = np.sin(xv[:, :1]) + xv[:, 1:] ** 2
    model = eqx.nn.MLP(2, 1, 8, 2, key=jax.random.key(0))
    executed = []

    def loss(m, batch):
        pred = jax.vmap(m)(batch["x"])
        err = pred - batch["y"]
        return jnp.mean(err**2), {"max_err": jnp.max(jnp.abs(err))}

    res = train(
        model, loss, {"x": x, "y": y},
        optimizer=make_optimizer(1e-2, warmup_steps=5, decay_steps=60),
        num_steps=45, batch_size=8, seed=3, has_aux=True,
        validation=Validation({"x": xv, "y": yv}, every=4),
        checkpoints=Checkpoints(ckpt, every=3),
        logging=Logging(log, progress=False, callback=lambda step, rec: (
            executed.append(step), time.sleep(sleep))),
        augment=lambda b, k: {**b, "x": b["x"] + 0.01 * jax.random.normal(k, (8, 2))},
    )
    eqx.tree_serialise_leaves(out, (res.model, res.best_model, res.best_step))
    with open(out + ".steps.json", "w") as f:
        json.dump(executed, f)
    """
)


def _run(tmp_path, name, sleep, kill_in_write_at=None):
    script = tmp_path / "train_script.py"
    if not script.exists():
        # Written once: rewriting it while an earlier child is still reading
        # it at start-up gave that child an empty or partial script, which
        # exited 0 having done nothing (a flaky failure under load).
        script.write_text(_SCRIPT)
    d = tmp_path / name
    d.mkdir(exist_ok=True)
    args = [
        sys.executable,
        str(script),
        str(d / "ckpt.eqx"),
        str(d / "log.jsonl"),
        str(d / "out.eqx"),
        str(sleep),
    ] + ([] if kill_in_write_at is None else [str(kill_in_write_at)])
    env = child_env()
    with open(d / "stderr.txt", "ab") as err:
        return subprocess.Popen(args, env=env, stderr=err), d


def _stderr(d):
    return (d / "stderr.txt").read_text()


def test_kill_and_resume_is_bitwise_identical(tmp_path):
    """Killed between steps, and killed while a checkpoint is being written:
    both resume and end with the uninterrupted run's bytes."""
    full, full_dir = _run(tmp_path, "full", 0.0)
    in_write, wdir = _run(tmp_path, "in_write", 0.0, kill_in_write_at=12)
    killed, kdir = _run(tmp_path, "killed", 0.1)
    deadline = time.monotonic() + 120
    while time.monotonic() < deadline:
        ck = kdir / "ckpt.eqx"
        if ck.exists() and read_checkpoint_header(ck)["step"] >= 9:
            break
        assert killed.poll() is None, _stderr(kdir)
        time.sleep(0.02)
    killed.send_signal(signal.SIGKILL)
    killed.wait()
    assert killed.returncode == -signal.SIGKILL
    stopped_at = read_checkpoint_header(kdir / "ckpt.eqx")["step"]
    assert 9 <= stopped_at < 45
    assert not (kdir / "out.eqx").exists()

    resumed, _ = _run(tmp_path, "killed", 0.0)
    assert resumed.wait(timeout=180) == 0, _stderr(kdir)
    assert full.wait(timeout=180) == 0, _stderr(full_dir)
    # The resumed process really started from the checkpoint.
    resumed_steps = json.loads((kdir / "out.eqx.steps.json").read_text())
    assert resumed_steps == list(range(stopped_at + 1, 46))
    full_steps = json.loads((full_dir / "out.eqx.steps.json").read_text())
    assert full_steps == list(range(1, 46))
    # Final model, best model and best step: the same bytes.
    assert (kdir / "out.eqx").read_bytes() == (full_dir / "out.eqx").read_bytes()
    a = (kdir / "ckpt.eqx").read_bytes()
    b = (full_dir / "ckpt.eqx").read_bytes()
    assert a == b
    # The resumed log has every step once, with the uninterrupted run's numbers.
    logs = []
    for d in (kdir, full_dir):
        recs = [json.loads(line) for line in (d / "log.jsonl").read_text().splitlines()]
        for r in recs:
            r.pop("time")
        logs.append(recs)
    assert logs[0] == logs[1]
    assert [r["step"] for r in logs[0] if "loss" in r] == list(range(1, 46))

    # Killed in the middle of writing step 12's checkpoint: the file in place
    # is still step 9's, whole; the half-written temporary file is left over.
    assert in_write.wait(timeout=180) == -signal.SIGKILL, _stderr(wdir)
    assert read_checkpoint_header(wdir / "ckpt.eqx")["step"] == 9
    assert len(list(wdir.glob(".ckpt.eqx.*.tmp"))) == 1
    resumed, _ = _run(tmp_path, "in_write", 0.0)
    assert resumed.wait(timeout=180) == 0, _stderr(wdir)
    assert json.loads((wdir / "out.eqx.steps.json").read_text()) == list(range(10, 46))
    assert (wdir / "out.eqx").read_bytes() == (full_dir / "out.eqx").read_bytes()
    assert (wdir / "ckpt.eqx").read_bytes() == b
    # The resumed run removed the stale temporary file.
    assert not list(wdir.glob(".ckpt.eqx.*.tmp"))
