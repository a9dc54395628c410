"""One fold of the KITTI-10 visual odometry experiment, resumable step by step.

A fold: (1) pretrain the virtual sensor on the training trajectories minus
their last 205 frames (checkpoint selection on the validation sequence);
(2) run the frozen sensor once over every frame pair that later stages need
and cache its outputs; (3) train every smoother / EKF / LSTM variant on
windows of the last 200 frames of each training trajectory with
`eqs.learn.train` (resumable checkpoints, selection on disjoint windows of
the whole validation sequence, which no stage trains on); (4) score every
method on disjoint length-100 windows of the test sequence. `fold_K.json` is
rewritten after every method, so a killed run started again with the same
command skips what is done and resumes the rest from its checkpoints.
"""

import dataclasses
import functools
import json
import platform
import time
from pathlib import Path

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from tqdm.auto import tqdm

import eqsmooth as eqs

from .._data import leading_axes, load_cache
from .._provenance import git_hash
from . import data as D, models as M


LABEL = "rendered views on real KITTI trajectories"
METHODS = (
    "smoother_hetero_e2e",
    "smoother_hetero_nll",
    "smoother_const_e2e",
    "smoother_const_nll",
    "ekf_hetero",
    "ekf_const",
    "lstm",
    # Added on 2026-11-27 (issue 33): the end-to-end smoothers trained with
    # the surrogate loss on the velocities instead of the positions, and the
    # bidirectional LSTM.
    "smoother_hetero_e2e_vel",
    "smoother_const_e2e_vel",
    "lstm_bi",
)
# Rows scored from the trained models of other rows, without training:
# row -> (how it estimates, the trained method whose model it uses).
# `ekf_*_one_frame_late` scores the EKF as the paper's code release does
# (`models.ekf_one_frame_late`); the `*_noise_from_*` rows transfer the
# learned noise (head and dynamics noise) between filter and smoother (the
# paper's Table II).
DERIVED = {
    "ekf_hetero_one_frame_late": ("ekf_one_frame_late", "ekf_hetero"),
    "ekf_const_one_frame_late": ("ekf_one_frame_late", "ekf_const"),
    "smoother_hetero_noise_from_ekf": ("smoother", "ekf_hetero"),
    "ekf_hetero_noise_from_smoother": ("ekf", "smoother_hetero_e2e"),
    "smoother_const_noise_from_ekf": ("smoother", "ekf_const"),
    "ekf_const_noise_from_smoother": ("ekf", "smoother_const_e2e"),
}


@dataclasses.dataclass
class Config:
    data_seed: int = 0
    variant: str | None = None  # a pre-declared data variant (D.VARIANTS)
    model_seed: int = 0
    poses_dir: str = str(D.DEFAULT_POSES_DIR)
    real_data_dir: str | None = None  # the preprocessed KITTI-10 release, if any
    cameras: tuple[str, ...] = D.CAMERAS
    mirror: bool = True
    max_train_sequences: int | None = None  # keep only the k shortest ones
    # Sensor pretraining.
    sensor_stride: int = 1  # use every k-th pretraining frame pair
    sensor_valid_stride: int = 10
    sensor_steps: int = 10000
    sensor_batch: int = 32
    sensor_lr: float = 1e-3
    sensor_weight_decay: float = 0.05
    sensor_augment: bool = True  # photometric augmentation (augment_pairs)
    # Smoother / EKF / LSTM training on windows of the last 200 frames.
    window: int = 50
    window_stride: int = 10
    steps: int = 4000
    lstm_steps: int = 6000
    batch: int = 8
    lr: float = 3e-3
    eval_every: int = 100
    gn_steps: int = 5  # K of the surrogate loss (5 in the paper's KITTI runs)
    # The surrogate's solve starts at dead reckoning (False) or at the truth
    # (True, the paper's start); no measurable difference with K = 5 (see
    # models.surrogate_loss).
    surrogate_from_truth: bool = False
    methods: tuple[str, ...] = METHODS
    eval_window: int = D.EVAL_WINDOW
    eval_copies: int | None = None  # score only the first k test trajectories
    validate: bool = True  # checkpoint selection on the validation sequence
    quick: bool = False


def quick_config() -> Config:
    return Config(
        cameras=("image_2",),
        max_train_sequences=2,
        sensor_stride=5,
        gn_steps=3,
        sensor_valid_stride=60,
        sensor_steps=150,
        sensor_batch=16,
        window=20,
        window_stride=20,
        steps=40,
        lstm_steps=60,
        batch=4,
        eval_every=20,
        # The key comparison only; compile time dominates a quick run.
        methods=("smoother_hetero_e2e", "smoother_const_e2e", "ekf_hetero", "lstm"),
        validate=False,
        quick=True,
    )


def label(cfg: Config) -> str:
    return LABEL + (f", data variant {cfg.variant!r}" if cfg.variant else "")


def train_sequences(cfg: Config, spec: D.FoldSpec) -> tuple[int, ...]:
    if cfg.max_train_sequences is None:
        return spec.train
    shortest = sorted(spec.train, key=lambda s: D.FRAME_COUNTS[s])
    return tuple(sorted(shortest[: cfg.max_train_sequences]))


def _machine() -> dict:
    import os

    return {
        "cpus": os.cpu_count(),
        "platform": platform.platform(),
        "processor": platform.processor(),
        "jax": jax.__version__,
        "devices": [str(d) for d in jax.devices()],
    }


# ---------------------------------------------------------------------------
# Trajectories of a fold
# ---------------------------------------------------------------------------


def load_trajectories(cfg: Config, seq: int) -> list[D.Trajectory]:
    if cfg.real_data_dir is not None:
        trajs = D.load_kitti10_sequence(cfg.real_data_dir, seq)
    else:
        trajs = D.rendered_sequence(seq, cfg.data_seed, cfg.poses_dir, cfg.variant)
    trajs = [t for t in trajs if t.camera in cfg.cameras]
    return D.with_mirrors(trajs) if cfg.mirror else trajs


# ---------------------------------------------------------------------------
# Sensor
# ---------------------------------------------------------------------------


def pair_dataset(trajs, frames_of, stride: int) -> dict:
    """Frame pairs (t, t+1) of un-mirrored trajectories (mirrored by batch parity)."""
    pairs, vels = [], []
    for tr in trajs:
        if tr.mirrored:
            continue
        frames = frames_of(tr.num_frames)
        frames = frames[frames < tr.num_frames - 1][::stride]
        imgs = tr.images(np.concatenate([frames, frames + 1]))
        n = frames.size
        pairs.append(np.stack([imgs[:n], imgs[n:]], axis=1))
        vels.append(D.velocities(tr.poses)[frames])
    return {
        "pairs": np.concatenate(pairs),
        "velocity": np.concatenate(vels).astype(np.float32),
    }


def _parity_mirror(batch: dict) -> dict:
    # Odd batch positions see the mirrored copy: flipped images, negated ω.
    B = batch["pairs"].shape[0]
    mirrored = jnp.arange(B) % 2 == 1
    vel = batch["velocity"] * jnp.where(mirrored[:, None], jnp.array([1.0, -1.0]), 1.0)
    return {"pairs": batch["pairs"], "mirrored": mirrored, "velocity": vel}


def augment_pairs(batch: dict, key) -> dict:
    """Photometric augmentation of a batch of frame pairs (the same for both
    frames of a pair, so the motion between them is unchanged): contrast
    0.6-1.4 about the pair's mean, per-channel gains 0.85-1.15, an offset of
    ±30 grey levels and pixel noise of std 0-10, clipped to 0-255."""
    p = batch["pairs"]
    B = p.shape[0]
    k1, k2, k3, k4, k5 = jax.random.split(key, 5)
    shape = (B, 1, 1, 1, 1)
    gain = jax.random.uniform(k1, shape, minval=0.6, maxval=1.4)
    chan = jax.random.uniform(k2, (B, 1, 1, 1, 3), minval=0.85, maxval=1.15)
    offset = jax.random.uniform(k3, shape, minval=-30.0, maxval=30.0)
    sigma = jax.random.uniform(k4, shape, maxval=10.0)
    x = p.astype(jnp.float32)
    mean = jnp.mean(x, axis=(1, 2, 3, 4), keepdims=True)
    x = (x - mean) * gain * chan + mean + offset
    x = x + sigma * jax.random.normal(k5, p.shape, jnp.float32)
    return {**batch, "pairs": jnp.clip(x, 0.0, 255.0)}


def sensor_train_loss(sensor, batch):
    return M.sensor_loss(sensor, _parity_mirror(batch))


def sensor_valid_loss(sensor, batch):
    return M.sensor_loss(sensor, _parity_mirror(batch))[1]["mse"]


@eqx.filter_jit
def _sensor_forward(sensor, pairs, mirrored):
    return jax.vmap(sensor)(M.prepare_pairs(pairs, mirrored))


def sensor_outputs(sensor, tr: D.Trajectory, frames: np.ndarray, batch: int = 64):
    """Cached outputs for pairs (t, t+1), t in `frames`: z, log σ, features."""
    outs = []
    for i in range(0, frames.size, batch):
        f = frames[i : i + batch]
        n = f.size
        pad = np.concatenate([f, np.repeat(f[-1:], batch - n)])
        imgs = tr.images(np.concatenate([pad, pad + 1]))
        pairs = np.stack([imgs[:batch], imgs[batch:]], axis=1)
        # Trajectory.images already flipped mirrored views.
        z, ls, h = _sensor_forward(sensor, jnp.asarray(pairs), jnp.zeros(batch, bool))
        outs.append([np.asarray(a)[:n] for a in (z, ls, h)])
    z, ls, h = (np.concatenate([o[k] for o in outs]) for k in range(3))
    return {"z": z, "log_sigma": ls, "features": h}


# ---------------------------------------------------------------------------
# Windows
# ---------------------------------------------------------------------------


def trajectory_cache(sensor, tr: D.Trajectory, first: int) -> dict:
    frames = np.arange(first, tr.num_frames - 1)
    out = sensor_outputs(sensor, tr, frames)
    out["first"] = np.asarray(first)
    return out


def _relative_params(xyt: np.ndarray) -> np.ndarray:
    # Poses relative to the first one (keeps float32 coordinates small).
    x0, y0, t0 = xyt[0]
    c, s = np.cos(t0), np.sin(t0)
    dx, dy = xyt[:, 0] - x0, xyt[:, 1] - y0
    th = xyt[:, 2] - t0
    return np.stack([np.cos(th), np.sin(th), c * dx + s * dy, -s * dx + c * dy], 1)


def make_windows(tr: D.Trajectory, cache: dict, starts: np.ndarray, length: int):
    f0 = int(cache["first"])
    vel = D.velocities(tr.poses)
    out = {k: [] for k in ("z", "log_sigma", "features", "pose", "velocity")}
    for s in starts:
        sl = slice(s - f0, s - f0 + length)
        for k in ("z", "log_sigma", "features"):
            out[k].append(cache[k][sl])
        out["pose"].append(_relative_params(tr.poses[s : s + length]))
        out["velocity"].append(vel[s : s + length])
    return {k: np.stack(v).astype(np.float32) for k, v in out.items()}


def concat(ws: list[dict]) -> dict:
    return {k: np.concatenate([w[k] for w in ws]) for k in ws[0]}


# ---------------------------------------------------------------------------
# Methods
# ---------------------------------------------------------------------------


def method_key(fold_key, method: str):
    """The initialisation key of a trained method: fixed by the method's place
    in `METHODS`, so that a run with `--methods` (any subset, any order)
    trains the same model as the full protocol. (Before commit 01cf627 the key
    followed the place in the run's own list; the full protocol's order is
    `METHODS`, so its rows are unchanged.)"""
    return jax.random.fold_in(fold_key, 10 + METHODS.index(method))


def build_model(method: str, sigmas, key):
    if estimator_kind(method) == "lstm":
        return M.LstmOdometry(key, bidirectional=method == "lstm_bi")
    if "hetero" in method:
        noise = M.heteroscedastic_noise(sigmas, key)
    else:
        noise = M.constant_noise(sigmas)
    return M.Estimator(noise)


def losses(method: str, cfg: Config):
    """(training loss, validation loss) of a method. Every smoother is
    selected on the position error of its test-time solve, whatever it is
    trained on."""
    kind = estimator_kind(method)
    if kind == "lstm":
        return M.lstm_loss, M.lstm_loss
    if kind == "ekf":
        return M.ekf_loss, M.ekf_loss
    target = "velocity" if method.endswith("_e2e_vel") else "position"

    def e2e(model, batch):
        return M.surrogate_loss(
            model, batch, cfg.gn_steps, cfg.surrogate_from_truth, target
        )

    train = M.nll_loss if method.endswith("_nll") else e2e
    return train, M.smoother_valid_loss


def estimator_kind(method: str) -> str:
    """How a method (or a `DERIVED` row's first entry) estimates: `"lstm"`,
    `"ekf"`, `"ekf_one_frame_late"`, `"dead_reckoning"` or `"smoother"`."""
    if method in ("lstm", "lstm_bi"):
        return "lstm"
    if method in ("ekf_one_frame_late", "dead_reckoning"):
        return method
    return "ekf" if method.startswith("ekf") else "smoother"


def estimate(method: str, model, window: dict) -> eqs.factors.VehicleState:
    """The estimate of a method (see `estimator_kind`) for one window."""
    kind = estimator_kind(method)
    if kind == "lstm":
        return model(window)
    if kind == "ekf_one_frame_late":
        return M.ekf_one_frame_late(model, window)
    if kind == "ekf":
        return M.run_ekf(model, window).mean
    if kind == "dead_reckoning":
        return M.dead_reckoning(window)
    return M.smooth(model, window)


def _planar(state) -> np.ndarray:
    p = np.asarray(state.pose.unit_complex_xy)
    return np.stack([p[..., 2], p[..., 3], np.arctan2(p[..., 1], p[..., 0])], -1)


@functools.cache
def _batched_estimator(kind: str):
    """One jitted batched estimator per way of estimating, so that scoring a
    method again (the figures do), or another model of the same structure
    (the `DERIVED` rows), reuses its compiled program."""
    return eqx.filter_jit(lambda m, w: jax.vmap(lambda x: estimate(kind, m, x))(w))


def evaluate(method: str, model, windows: dict, batch: int = 8):
    """Per-window (m/m, deg/m; final step, then whole window) and estimated
    planar poses."""
    fn = _batched_estimator(estimator_kind(method))
    n = windows["z"].shape[0]
    est = []
    for i in range(0, n, batch):
        idx = np.arange(i, min(i + batch, n))
        idx = np.concatenate([idx, np.repeat(idx[-1:], batch - idx.size)])
        w = {k: jnp.asarray(v[idx]) for k, v in windows.items()}
        est.append(_planar(fn(model, w))[: min(batch, n - i)])
    est = np.concatenate(est)
    truth = _planar(
        eqs.factors.VehicleState(eqs.SE2(windows["pose"]), windows["velocity"])
    )
    metrics = np.array(
        [
            D.window_metrics(e, t) + D.whole_window_metrics(e, t)
            for e, t in zip(est, truth)
        ]
    )
    return metrics, est


# ---------------------------------------------------------------------------
# A fold
# ---------------------------------------------------------------------------


def _write_json(path: Path, obj) -> None:
    tmp = path.with_suffix(".tmp")
    tmp.write_text(json.dumps(obj, indent=1))
    tmp.replace(path)


def _train_stage(
    path: Path,
    model,
    loss,
    data,
    validation,
    *,
    lr: float,
    steps: int,
    warmup: int,
    checkpoint_every: int,
    optimizer_options: dict | None = None,
    **options,
):
    """[`eqsmooth.learn.train`][] for `steps` steps, warming up for
    `min(warmup, steps // 10)` of them, with the checkpoints `<path>.ckpt` and
    the log `<path>.jsonl`; `options` go to `train` as they are."""
    optimizer = eqs.learn.make_optimizer(
        lr,
        warmup_steps=min(warmup, steps // 10),
        decay_steps=steps,
        **(optimizer_options or {}),
    )
    return eqs.learn.train(
        model,
        loss,
        data,
        optimizer=optimizer,
        num_steps=steps,
        validation=validation,
        checkpoints=eqs.learn.Checkpoints(
            path.with_name(path.name + ".ckpt"), every=checkpoint_every
        ),
        logging=eqs.learn.Logging(path.with_name(path.name + ".jsonl")),
        **options,
    )


def _fold_record(cfg: Config, fold: int, result_path: Path) -> dict:
    """The fold's results file (resumed when it exists), with this run's
    configuration and machine."""
    spec = D.fold_spec(fold)
    result = json.loads(result_path.read_text()) if result_path.exists() else {}
    result.update(
        label=label(cfg),
        fold=fold,
        test_sequence=spec.test,
        valid_sequence=spec.valid,
        train_sequences=list(train_sequences(cfg, spec)),
        config=dataclasses.asdict(cfg),
        git=git_hash(),
        machine=_machine(),
    )
    result.setdefault("rows", {})
    result.setdefault("timings", {})
    return result


def _pretrain_sensor(cfg, key, train_trajs, valid_trajs, sensor_path, work, timings):
    """Stage 1: the velocity sensor, pretrained on image pairs (or loaded)."""
    sensor = M.VelocitySensor(jax.random.fold_in(key, 0))
    if sensor_path.exists():
        return eqx.tree_deserialise_leaves(sensor_path, sensor)
    t1 = time.perf_counter()
    train_pairs = pair_dataset(train_trajs, D.pretrain_frames, cfg.sensor_stride)
    valid_pairs = pair_dataset(valid_trajs, D.pretrain_frames, cfg.sensor_valid_stride)
    timings["sensor_data_s"] = time.perf_counter() - t1
    print(
        f"sensor: {len(train_pairs['pairs'])} training pairs, "
        f"{len(valid_pairs['pairs'])} validation pairs"
    )
    t1 = time.perf_counter()
    res = _train_stage(
        work / "sensor",
        sensor,
        sensor_train_loss,
        train_pairs,
        eqs.learn.Validation(
            valid_pairs, sensor_valid_loss, every=max(cfg.sensor_steps // 10, 1)
        ),
        lr=cfg.sensor_lr,
        steps=cfg.sensor_steps,
        warmup=200,
        checkpoint_every=200,
        optimizer_options=dict(weight_decay=cfg.sensor_weight_decay),
        augment=augment_pairs if cfg.sensor_augment else None,
        batch_size=cfg.sensor_batch,
        seed=cfg.model_seed,
        has_aux=True,
    )
    timings["sensor_train_s"] = time.perf_counter() - t1
    timings["sensor_best_step"] = res.best_step
    timings["sensor_valid_mse_normalised"] = res.best_valid_loss
    eqx.tree_serialise_leaves(sensor_path, res.best_model)
    return res.best_model


def _read_sensor_cache(path: Path, first: int, frames: int) -> dict | None:
    """A trajectory's cached sensor outputs, or None (absent, or damaged: not
    an `.npz`, another first frame, or arrays of another length; see
    `experiments._data.load_cache`)."""

    def check(cached):
        if int(cached["first"]) != first:
            raise ValueError(f"it starts at frame {int(cached['first'])}, not {first}")
        leading_axes({k: (frames,) for k in _SENSOR_KEYS})(cached)

    return load_cache(path, ("first", *_SENSOR_KEYS), check)


_SENSOR_KEYS = ("z", "log_sigma", "features")


def _sensor_caches(sensor, trajs_by_role, cache_dir: Path) -> dict:
    """Stage 2: the frozen sensor's outputs per trajectory, cached on disk."""
    caches = {}
    cache_dir.mkdir(exist_ok=True)
    all_trajs = [(t, role) for role, trajs in trajs_by_role for t in trajs]
    for tr, role in tqdm(all_trajs, desc="sensor cache"):
        path = cache_dir / (tr.name.replace("/", "_") + ".npz")
        # Training trajectories: only their last frames (the smoother split).
        # The validation and test sequences are used whole.
        first = 0 if role != "train" else int(D.smoother_frames(tr.num_frames)[0])
        cached = _read_sensor_cache(path, first, tr.num_frames - 1 - first)
        if cached is not None:
            caches[tr.name] = cached
            continue
        caches[tr.name] = trajectory_cache(sensor, tr, first)
        np.savez(path, **caches[tr.name])
    return caches


def _windows_of(caches, trajs, length, stride, role):
    ws = []
    for tr in trajs:
        c = caches[tr.name]
        frames = (
            np.arange(tr.num_frames)
            if role != "train"
            else D.smoother_frames(tr.num_frames)
        )
        starts = D.windows(frames, length, stride)
        if starts.size:
            ws.append(make_windows(tr, c, starts, length))
    return concat(ws)


def _sensor_summary(train_w, valid_w, test_w) -> tuple[np.ndarray, dict]:
    """The sensor's RMSE on the smoother-training windows (the noise heads'
    start) and the window counts."""
    err = train_w["z"] - train_w["velocity"]
    sigmas = np.sqrt(np.mean(err.reshape(-1, 2) ** 2, 0))
    summary = {
        "train_window_rmse": sigmas.tolist(),
        "test_rmse": np.sqrt(
            np.mean((test_w["z"] - test_w["velocity"]).reshape(-1, 2) ** 2, 0)
        ).tolist(),
        "num_train_windows": int(train_w["z"].shape[0]),
        "num_valid_windows": int(valid_w["z"].shape[0]),
        "num_test_windows": int(test_w["z"].shape[0]),
    }
    return sigmas, summary


def train_method(
    cfg, key, method, sigmas, train_w, valid_w, work, model=None, loss_pair=None
):
    """Stage 3 for one method: train it (resumable, checkpoints under `work`)
    from `build_model(method, sigmas, method_key(key, method))` with
    `losses(method, cfg)` (or the given `model` and `(train, validation)`
    `loss_pair`: a row outside `METHODS`); return the `eqs.learn.train`
    result and the training seconds."""
    if model is None:
        model = build_model(method, sigmas, method_key(key, method))
    train_loss, valid_loss = loss_pair or losses(method, cfg)
    steps = cfg.lstm_steps if method == "lstm" else cfg.steps
    t1 = time.perf_counter()
    valid = None
    if cfg.validate:
        valid = eqs.learn.Validation(valid_w, valid_loss, every=cfg.eval_every)
    res = _train_stage(
        work / method,
        model,
        train_loss,
        train_w,
        valid,
        lr=cfg.lr,
        steps=steps,
        warmup=50,
        checkpoint_every=100,
        batch_size=min(cfg.batch, train_w["z"].shape[0]),
        seed=cfg.model_seed,
        on_nonfinite="skip",
    )
    return res, time.perf_counter() - t1


def _train_and_score(cfg, key, sigmas, train_w, valid_w, test_w, work, result, save):
    """Stages 3 and 4: train each method (resumable) and score it once."""
    models = {}
    for method in cfg.methods:
        res, train_s = train_method(cfg, key, method, sigmas, train_w, valid_w, work)
        models[method] = res.best_model
        old = result["rows"].get(method)
        if old is not None and "trans_m_per_m_whole" in old:
            continue
        t1 = time.perf_counter()
        m, _ = evaluate(method, res.best_model, test_w)
        eval_s = time.perf_counter() - t1
        new = _row(m, train_s, eval_s, res.best_step)
        result["rows"][method] = new if old is None else _rescored(old, new, result)
        print(
            f"{method}: {result['rows'][method]['trans_m_per_m']:.4f} m/m, "
            f"{result['rows'][method]['rot_deg_per_m']:.4f} deg/m"
        )
        save()
    return models


def _rescored(old: dict, new: dict, result: dict) -> dict:
    """A row scored by an earlier run before the whole-window metric existed,
    with that metric added from `new`, the same method trained again.

    The final-step fields of record stay the earlier run's (the published
    table and the paired comparisons built on it do not move); the retrained
    model's own final-step scores are kept in `whole_window_from`, so a
    reader sees how far the retraining moved and can pair whole-window
    metrics, which all come from retrained models, among themselves."""
    row = dict(old)
    for k, v in new.items():
        if "_whole" in k:
            row[k] = v
    row["whole_window_from"] = {
        "git": result["git"],
        "best_step": new["best_step"],
        "train_s": new["train_s"],
        **{k: new[k] for k in ("trans_m_per_m", "rot_deg_per_m")},
    }
    return row


def _score_derived(models: dict, test_w: dict, result: dict, save) -> None:
    """Stage 5: the `DERIVED` rows whose source model this run trained.

    Each also records `source_now`, its source model scored the usual way in
    this run: where the source row was scored by an earlier run whose
    checkpoints are gone, the model was trained again, and a derived row is
    compared with what its own model scores (equal to the source row when
    the retraining reproduced it)."""
    now = {}
    for row, (how, source) in DERIVED.items():
        if row in result["rows"] or source not in models:
            continue
        if source not in now:
            m, _ = evaluate(source, models[source], test_w)
            now[source] = {
                k: v
                for k, v in _row(m, 0.0, 0.0, None).items()
                if not k.endswith("_windows") and k.startswith(("trans", "rot"))
            }
        t1 = time.perf_counter()
        m, _ = evaluate(how, models[source], test_w)
        result["rows"][row] = _row(m, 0.0, time.perf_counter() - t1, None)
        result["rows"][row]["derived_from"] = source
        result["rows"][row]["source_now"] = now[source]
        print(
            f"{row}: {result['rows'][row]['trans_m_per_m']:.4f} m/m, "
            f"{result['rows'][row]['rot_deg_per_m']:.4f} deg/m"
        )
        save()


def prepare_fold(
    cfg: Config, fold: int, out: Path, timings: dict, save=None, train_sensor=True
) -> dict:
    """Stages 1 and 2 of fold `fold`: load its trajectories, pretrain the
    sensor (or load `out/sensor_foldK.eqx`; with `train_sensor=False` a
    missing sensor raises `FileNotFoundError`), cache its outputs under
    `out/work/fold_K/cache` and cut the windows. Adds to `timings`; calls
    `save()` once the sensor is ready. Returns the windows (`train`, `valid`,
    `test`), the sensor's training-window RMSE `sigmas` (the noise heads'
    start), `sensor_summary`, the scored `test_trajs` and the `caches`."""
    spec = D.fold_spec(fold)
    work = out / "work" / f"fold_{fold}"
    work.mkdir(parents=True, exist_ok=True)
    train_seqs = train_sequences(cfg, spec)
    key = jax.random.key(cfg.model_seed + 1000 * fold)
    sensor_path = out / f"sensor_fold{fold}.eqx"
    if not train_sensor and not sensor_path.exists():
        raise FileNotFoundError(
            f"fold {fold}: no sensor at {sensor_path} (this mode loads the "
            "committed sensor and never trains one)"
        )
    t0 = time.perf_counter()
    print(
        f"fold {fold}: test {spec.test:02d}, valid {spec.valid:02d}, train {train_seqs}"
    )
    train_trajs = [t for s in train_seqs for t in load_trajectories(cfg, s)]
    valid_trajs = load_trajectories(cfg, spec.valid)
    test_trajs = load_trajectories(cfg, spec.test)
    timings["load_s"] = timings.get("load_s", 0.0) + time.perf_counter() - t0
    if cfg.real_data_dir is None:
        r = test_trajs[0]
        frames = np.arange(min(200, r.num_frames))
        t1 = time.perf_counter()
        r.images(frames)
        timings["render_ms_per_frame"] = (time.perf_counter() - t1) / frames.size * 1e3

    sensor = _pretrain_sensor(
        cfg, key, train_trajs, valid_trajs, sensor_path, work, timings
    )
    if save is not None:
        save()

    t1 = time.perf_counter()
    roles = (("train", train_trajs), ("valid", valid_trajs), ("test", test_trajs))
    caches = _sensor_caches(sensor, roles, work / "cache")
    timings["cache_s"] = timings.get("cache_s", 0.0) + time.perf_counter() - t1
    train_w = _windows_of(caches, train_trajs, cfg.window, cfg.window_stride, "train")
    valid_w = _windows_of(caches, valid_trajs, cfg.window, cfg.window, "valid")
    scored = test_trajs[: cfg.eval_copies] if cfg.eval_copies else test_trajs
    test_w = _windows_of(caches, scored, cfg.eval_window, None, "test")
    sigmas, summary = _sensor_summary(train_w, valid_w, test_w)
    print(
        f"windows: {train_w['z'].shape[0]} train, {valid_w['z'].shape[0]} valid, "
        f"{test_w['z'].shape[0]} test; sensor RMSE (v, ω) {sigmas}"
    )
    return {
        "train": train_w,
        "valid": valid_w,
        "test": test_w,
        "sigmas": sigmas,
        "sensor_summary": summary,
        "test_trajs": scored,
        "caches": caches,
    }


def run_fold(cfg: Config, fold: int, out: Path) -> dict:
    """Run (or resume) every stage of fold `fold`; write `fold_K.json` under
    `out` after each; return the result, the models and the test data."""
    out.mkdir(parents=True, exist_ok=True)
    work = out / "work" / f"fold_{fold}"
    work.mkdir(parents=True, exist_ok=True)
    result_path = out / f"fold_{fold}.json"
    result = _fold_record(cfg, fold, result_path)
    timings = result["timings"]
    key = jax.random.key(cfg.model_seed + 1000 * fold)

    t0 = time.perf_counter()
    # Every run of this fold (a first one and any resumed ones) records its
    # wall time; the fold's total is their sum, work later redone included.
    run = {
        "started": time.strftime("%Y-%m-%dT%H:%M:%S"),
        "git": result["git"],
        "methods": list(cfg.methods),
    }
    result.setdefault("runs", []).append(run)

    def save():
        run["wall_s"] = time.perf_counter() - t0
        timings["total_s"] = sum(r["wall_s"] for r in result["runs"])
        _write_json(result_path, result)

    data = prepare_fold(cfg, fold, out, timings, save)
    train_w, valid_w, test_w = data["train"], data["valid"], data["test"]
    sigmas, result["sensor"] = data["sigmas"], data["sensor_summary"]
    scored, caches = data["test_trajs"], data["caches"]

    # Dead reckoning from the sensor: a reference row, no training (scored
    # again, whole, where an earlier run lacks the whole-window metric).
    if "trans_m_per_m_whole" not in result["rows"].get("dead_reckoning", {}):
        m, _ = evaluate("dead_reckoning", None, test_w)
        old = result["rows"].get("dead_reckoning")
        new = _row(m, 0.0, 0.0, None)
        result["rows"]["dead_reckoning"] = (
            new if old is None else _rescored(old, new, result)
        )
    save()
    models = _train_and_score(
        cfg, key, sigmas, train_w, valid_w, test_w, work, result, save
    )
    _score_derived(models, test_w, result, save)
    save()
    return {
        "result": result,
        "models": models,
        "test_trajs": scored,
        "test_windows": test_w,
        "caches": caches,
    }


def _row(metrics: np.ndarray, train_s: float, eval_s: float, best_step) -> dict:
    return {
        "trans_m_per_m": float(np.mean(metrics[:, 0])),
        "rot_deg_per_m": float(np.mean(metrics[:, 1])),
        "trans_m_per_m_windows": metrics[:, 0].tolist(),
        "rot_deg_per_m_windows": metrics[:, 1].tolist(),
        "trans_m_per_m_whole": float(np.mean(metrics[:, 2])),
        "rot_deg_per_m_whole": float(np.mean(metrics[:, 3])),
        "trans_m_per_m_whole_windows": metrics[:, 2].tolist(),
        "rot_deg_per_m_whole_windows": metrics[:, 3].tolist(),
        "train_s": train_s,
        "eval_s": eval_s,
        "best_step": best_step,
    }
