"""Data parallelism: a step sharded over 2 (virtual CPU) devices equals one device."""

import json
import socket
import subprocess
import sys
import textwrap

import jax
import jax.numpy as jnp
import numpy as np
import optax
import pytest
from helpers import child_env

from eqsmooth.learn import (
    initialize_distributed,
    make_mesh,
    make_train_step,
    read_checkpoint_header,
    replicate,
    shard_batch,
)


def _loss(model, batch):
    pred = model["w"] * batch["x"] + model["b"]
    return jnp.mean((pred - batch["y"]) ** 2)


def test_one_device_mesh_is_a_no_op():
    mesh = make_mesh(jax.devices()[:1])
    model = {"w": jnp.asarray(0.3), "b": jnp.asarray(-0.1)}
    batch = {"x": jnp.linspace(0.0, 1.0, 6), "y": jnp.linspace(1.0, 2.0, 6)}
    opt = optax.sgd(0.1)
    plain = make_train_step(_loss, opt)(model, opt.init(model), batch)
    meshed = make_train_step(_loss, opt, mesh=mesh)(
        replicate(model, mesh),
        replicate(opt.init(model), mesh),
        shard_batch(batch, mesh),
    )
    for a, b in zip(
        jax.tree_util.tree_leaves(plain), jax.tree_util.tree_leaves(meshed)
    ):
        assert np.array_equal(np.asarray(a), np.asarray(b))


def test_initialize_distributed_without_arguments_does_nothing():
    assert initialize_distributed() is False
    assert jax.process_count() == 1


_SCRIPT = textwrap.dedent(
    """
    import json, sys
    import jax
    jax.config.update("jax_enable_x64", True)
    import jax.numpy as jnp, numpy as np, optax
    import eqsmooth as eqs
    from eqsmooth.learn import (
        make_mesh, make_train_step, replicate, shard_batch, surrogate_loss, train,
        Logging, Validation,
    )

    assert len(jax.devices()) == 2, jax.devices()
    T, B = 5, 4
    t = np.arange(T)

    def walk(a, b, data, params):
        return b - a * params

    def obs(x, data, params):
        return x - data

    def per_example(model, ex):
        graph = eqs.FactorGraph([
            eqs.FunctionFactor(
                walk, (eqs.Var("x", t[:-1]), eqs.Var("x", t[1:])),
                eqs.IsotropicNoise(sqrt_precision=jnp.exp(model["log_q"])),
                params=model["coeff"],
            ),
            eqs.FunctionFactor(
                obs, (eqs.Var("x", t),),
                eqs.DiagonalNoise(sqrt_precision=jnp.exp(model["log_r"])),
                data=ex["meas"],
            ),
        ])
        return surrogate_loss(graph, {"x": ex["truth"]})

    def loss(model, batch):
        return jnp.mean(jax.vmap(lambda ex: per_example(model, ex))(batch))

    rng = np.random.default_rng(0)
    truth = np.cumsum(rng.normal(size=(8, T, 2)), axis=1)
    data = {"truth": truth, "meas": truth + 0.3 * rng.normal(size=truth.shape)}
    model = {
        "log_q": jnp.asarray(0.1), "log_r": jnp.array([0.5, -0.2]),
        "coeff": jnp.asarray(0.9),
    }
    batch = jax.tree_util.tree_map(lambda a: jnp.asarray(a[:B]), data)
    opt = optax.sgd(1.0)  # new = old - grad
    mesh = make_mesh()
    single = make_train_step(loss, opt)
    sharded = make_train_step(loss, opt, mesh=mesh)
    m1, _, met1 = single(model, opt.init(model), batch)
    sb = shard_batch(batch, mesh)
    shard_shapes = sorted(s.data.shape for s in sb["meas"].addressable_shards)
    m2, _, met2 = sharded(replicate(model, mesh), replicate(opt.init(model), mesh), sb)
    g1 = jax.tree_util.tree_map(lambda a, b: a - b, model, m1)
    g2 = jax.tree_util.tree_map(lambda a, b: a - b, model, m2)
    grad_diff = max(
        float(jnp.max(jnp.abs(a - b)))
        for a, b in zip(jax.tree_util.tree_leaves(g1), jax.tree_util.tree_leaves(g2))
    )
    grad_max = max(float(jnp.max(jnp.abs(a))) for a in jax.tree_util.tree_leaves(g1))
    try:
        shard_batch(jax.tree_util.tree_map(lambda a: a[:3], batch), mesh)
        odd_error = ""
    except ValueError as err:
        odd_error = str(err)

    # The training loop (a cheap regression loss): 5 steps with and without mesh.
    def line_loss(m, b):
        return jnp.mean((m["w"] * b["x"] + m["coeff"] - b["y"]) ** 2)

    xs = rng.normal(size=16)
    line_data = {"x": xs, "y": 2.0 * xs + 1.0}
    line0 = {"w": jnp.asarray(0.0), "coeff": model["coeff"]}
    xv = rng.normal(size=5)  # 5 = a full batch of 4 (sharded) + 1 (replicated)
    kw = dict(
        optimizer=optax.adam(1e-2), num_steps=5, batch_size=4,
        logging=Logging(progress=False),
        validation=Validation({"x": xv, "y": 2.0 * xv}, every=2),
    )
    r1 = train(line0, line_loss, line_data, **kw)
    r2 = train(line0, line_loss, line_data, mesh=mesh, **kw)
    train_diff = max(
        float(jnp.max(jnp.abs(a - b)))
        for a, b in zip(
            jax.tree_util.tree_leaves(r1.model), jax.tree_util.tree_leaves(r2.model)
        )
    )
    out_sharding = m2["log_r"].sharding
    print("RESULT", json.dumps({
        "loss1": float(met1["loss"]), "loss2": float(met2["loss"]),
        "grad_diff": grad_diff, "grad_max": grad_max,
        "shard_shapes": [list(s) for s in shard_shapes],
        "replicated_out": bool(out_sharding.is_fully_replicated),
        "out_devices": len(out_sharding.device_set),
        "odd_error": odd_error,
        "train_diff": train_diff,
        "train_moved": float(jnp.abs(r1.model["coeff"] - model["coeff"])),
        "valid": [r1.best_valid_loss, r2.best_valid_loss, r1.best_step, r2.best_step],
    }))
    """
)


@pytest.fixture(scope="module")
def two_device_result(tmp_path_factory):
    path = tmp_path_factory.mktemp("sharding") / "sharded_step.py"
    path.write_text(_SCRIPT)
    env = child_env("--xla_force_host_platform_device_count=2")
    proc = subprocess.run(
        [sys.executable, str(path)],
        env=env,
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert proc.returncode == 0, proc.stderr[-4000:]
    line = [x for x in proc.stdout.splitlines() if x.startswith("RESULT ")][-1]
    return json.loads(line[len("RESULT ") :])


def test_sharded_step_matches_single_device(two_device_result):
    r = two_device_result
    assert abs(r["loss1"] - r["loss2"]) <= 1e-12 * max(1.0, abs(r["loss1"]))
    assert r["grad_max"] > 1e-3  # the comparison is not vacuous
    assert r["grad_diff"] <= 1e-12
    # The batch really was split: two shards of 2 sequences each.
    assert r["shard_shapes"] == [[2, 5, 2], [2, 5, 2]]
    assert r["replicated_out"] and r["out_devices"] == 2


def test_sharded_training_loop_matches_single_device(two_device_result):
    r = two_device_result
    assert r["train_moved"] > 1e-4
    assert r["train_diff"] <= 1e-12
    v1, v2, s1, s2 = r["valid"]
    assert abs(v1 - v2) <= 1e-12 * abs(v1) and s1 == s2


def test_shard_batch_rejects_indivisible_batch(two_device_result):
    assert "multiple of the device count" in two_device_result["odd_error"]


_MULTI = textwrap.dedent(
    """
    import json, sys
    import jax
    jax.config.update("jax_enable_x64", True)
    jax.config.update("jax_cpu_collectives_implementation", "gloo")
    import jax.numpy as jnp, numpy as np, optax
    from eqsmooth.learn import initialize_distributed, make_mesh, train
    from eqsmooth.learn import Checkpoints, Logging, Validation

    nproc, pid, port, out = int(sys.argv[1]), int(sys.argv[2]), sys.argv[3], sys.argv[4]
    if nproc > 1:
        assert initialize_distributed(f"localhost:{port}", nproc, pid)
    assert jax.process_count() == nproc

    def loss(m, b):
        return jnp.mean((m["w"] * b["x"] + m["b"] - b["y"]) ** 2)

    rng = np.random.default_rng(0)
    x, xv = rng.normal(size=16), rng.normal(size=5)
    res = train(
        {"w": jnp.asarray(0.0), "b": jnp.asarray(0.0)}, loss,
        {"x": x, "y": 2 * x + 1}, optimizer=optax.adam(0.1), num_steps=6,
        batch_size=4, validation=Validation({"x": xv, "y": 1.5 * xv}, every=2),
        checkpoints=Checkpoints(out + "/ckpt.eqx", every=2),
        logging=Logging(out + f"/log{pid}.jsonl", progress=False),
        mesh=make_mesh() if nproc > 1 else None,
    )
    final = {k: float(np.asarray(v.addressable_data(0))) for k, v in res.model.items()}
    print("RESULT", json.dumps({"model": final, "best_step": res.best_step,
                                "best": res.best_valid_loss}), flush=True)
    if nproc > 1:
        jax.distributed.shutdown()
    """
)


def _free_port():
    with socket.socket() as sock:
        sock.bind(("localhost", 0))
        return sock.getsockname()[1]


def test_multi_process_training_matches_single_process(tmp_path):
    # Two processes with one CPU device each, joined by jax.distributed (gloo
    # collectives): the multi-host path of shard_batch / replicate / train.
    script = tmp_path / "multi.py"
    script.write_text(_MULTI)
    env = child_env()
    port = str(_free_port())
    dirs = {"multi": tmp_path / "multi", "single": tmp_path / "single"}
    for d in dirs.values():
        d.mkdir()
    runs = [
        (n, pid, dirs["multi" if n == 2 else "single"])
        for n, pid in [(2, 0), (2, 1), (1, 0)]
    ]
    procs = [
        subprocess.Popen(
            [sys.executable, str(script), str(n), str(pid), port, str(d)],
            env=env,
            stdout=subprocess.PIPE,
            stderr=subprocess.STDOUT,
            text=True,
        )
        for n, pid, d in runs
    ]
    results = []
    for p in procs:
        out, _ = p.communicate(timeout=240)
        assert p.returncode == 0, out[-3000:]
        line = [x for x in out.splitlines() if x.startswith("RESULT ")][-1]
        results.append(json.loads(line[len("RESULT ") :]))
    single = results[2]
    for r in results[:2]:
        for k in ("w", "b"):
            assert abs(r["model"][k] - single["model"][k]) <= 1e-12
        assert r["best_step"] == single["best_step"]
        assert abs(r["best"] - single["best"]) <= 1e-12
    assert abs(single["model"]["w"]) > 0.1  # it trained
    # Only process 0 wrote the log and the checkpoints (the current one holds
    # the final step, the previous one is kept as a fallback).
    assert sorted(p.name for p in dirs["multi"].iterdir()) == [
        "ckpt.eqx",
        "ckpt.eqx.prev",
        "log0.jsonl",
    ]
    assert read_checkpoint_header(dirs["multi"] / "ckpt.eqx")["step"] == 6
