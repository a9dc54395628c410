"""Training stages of the disk tracking experiment and its evaluation.

Stages (one test fold at a time):

1. data: training folds (minus a validation split) and the test fold;
2. pretrain the virtual sensor (MSE on positions), select on validation;
3. run the frozen sensor once over every sequence (its positions are all the
   smoothers and EKFs need, so their training costs no CNN passes);
4. smoothers: {constant, heteroscedastic} noise x {surrogate loss (K = 3
   unrolled Gauss-Newton steps from ground truth), joint NLL};
5. EKFs: the same noise heads x {E2E MSE, marginal NLL};
6. LSTMs: uni- and bidirectional, end to end from images;
7. test RMSE (per coordinate, pixels) of every model selected on validation.

Model selection never looks at the test fold.

Losses come from `eqsmooth.learn` (surrogate loss, joint NLL) and the EKF
from `eqsmooth.filters`; the optimiser is `eqsmooth.learn.make_optimizer`.
"""

import dataclasses
import math
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optax

import eqsmooth as eqs

from . import data as D, models as M


try:  # progress bars when tqdm is installed (the `examples` extra)
    from tqdm.auto import tqdm

    _HAVE_TQDM = True
except ImportError:  # pragma: no cover
    _HAVE_TQDM = False

    def tqdm(it, **kwargs):
        return it


# ---------------------------------------------------------------------------
# Configuration
# ---------------------------------------------------------------------------


@dataclasses.dataclass
class Config:
    """Everything that defines a run (saved with the results)."""

    data_seed: int = 0
    model_seed: int = 0
    num_folds: int = D.NUM_FOLDS
    sequences_per_fold: int = D.SEQUENCES_PER_FOLD
    num_frames: int = D.FRAMES_PER_SEQUENCE
    test_folds: tuple[int, ...] = tuple(range(D.NUM_FOLDS))
    # Training folds used with each test fold (None: all the others).
    train_folds: tuple[int, ...] | None = None
    val_fraction: float = 0.1  # of the training sequences, for model selection
    # Sequences actually used per split (None: all); quick mode sets these.
    max_train_sequences: int | None = None
    max_val_sequences: int | None = None
    max_test_sequences: int | None = None
    # Virtual sensor pretraining.
    sensor_steps: int = 85_000  # ~30 epochs of 91k images at batch 32
    sensor_batch: int = 32
    sensor_lr: float = 1e-4
    sensor_warmup: int = 50
    # Quick-mode aid, not the paper's protocol: start the sensor's first conv
    # as a target-colour detector (`models.target_colour_init`).
    sensor_colour_init: bool = False
    # Smoothers and EKFs (noise heads only; the sensor is frozen).
    fg_steps: int = 4_300  # ~30 epochs of 4.5k sequences at batch 32
    fg_batch: int = 32
    fg_lr: float = 1e-4
    surrogate_steps: int = 3  # K unrolled Gauss-Newton steps
    eval_solver_steps: int = 10
    # LSTMs.
    lstm_steps: int = 51_000  # ~60 epochs of 13.6k subsequences at batch 16
    lstm_batch: int = 16
    lstm_lr: float = 1e-4
    lstm_subsequence: int = 10
    lstm_hidden: int = 64
    lstm_init_from_sensor: bool = False  # beyond the paper; quick mode uses it
    # Beyond the paper: fine-tune the sensor through the smoother.
    finetune_steps: int = 2_000
    finetune_batch: int = 8  # sequences (x 20 images) per step
    finetune_lr: float = 1e-5
    # Common.
    warmup: int = 50
    clip_norm: float = 10.0
    eval_every: int = 500
    eval_batch: int = 256  # images per sensor forward pass in evaluation
    images_on_device: bool = False  # pre-render training images (GPU runs)
    methods: tuple[str, ...] = (
        "smoother_const_surrogate",
        "smoother_const_nll",
        "smoother_hetero_surrogate",
        "smoother_hetero_nll",
        "smoother_hetero_implicit",
        "smoother_hetero_surrogate_learndyn",
        "ekf_const_mse",
        "ekf_const_nll",
        "ekf_hetero_mse",
        "ekf_hetero_nll",
        "lstm_uni",
        "lstm_bi",
        "smoother_hetero_finetune",  # needs smoother_hetero_surrogate first
    )
    cache_dir: str | None = None
    sensor_weights_dir: str | None = None  # reuse sensor_fold{k}.eqx from here
    quick: bool = False
    dtype: str = "float32"


# Pretrained virtual sensors committed with the repository (from full-protocol
# runs on a GPU), named sensor_fold{k}.eqx; quick mode uses fold 0's if there.
WEIGHTS_DIR = Path(__file__).resolve().parent / "weights"


def quick_config(pretrain_sensor: bool = False, **overrides) -> Config:
    """A small configuration that runs end to end in minutes on 2 CPU cores.

    The CNN is the cost on a CPU (about 36 ms per image for a forward and
    backward pass on 2 idle cores, several times that on a loaded machine), so
    the sensor sees about a thousand training images. From the paper's random
    initialisation it stays at the "predict the mean" plateau on that budget;
    quick mode therefore starts its first conv as a target-colour detector
    (`sensor_colour_init`, a quick-mode aid, not the paper's protocol).

    Unless `pretrain_sensor` is set, quick mode loads a committed
    full-protocol sensor for test fold 0 instead when one exists
    (`examples/disk_tracking/weights/sensor_fold0.eqx`; trained on folds 1-9
    only, so fold 0 stays unseen).
    """
    committed = WEIGHTS_DIR / "sensor_fold0.eqx"
    if not pretrain_sensor and committed.exists():
        overrides.setdefault("sensor_weights_dir", str(WEIGHTS_DIR))
    cfg = Config(
        test_folds=(0,),
        train_folds=(1, 2),
        sequences_per_fold=60,
        # Every sequence costs 20 CNN passes for the sensor's positions.
        max_train_sequences=48,
        max_val_sequences=6,
        max_test_sequences=24,
        sensor_steps=100,
        sensor_batch=8,
        sensor_lr=2e-3,
        sensor_colour_init=True,
        fg_steps=80,
        fg_batch=16,
        fg_lr=1e-2,
        lstm_steps=8,  # each step: 2 x 10 CNN passes
        lstm_batch=2,
        lstm_lr=2e-3,
        lstm_init_from_sensor=True,
        # Fine-tuning the CNN through the smoother costs 20 CNN passes per
        # sequence: left out of the quick run (pass --methods to add it).
        methods=tuple(m for m in Config.methods if m != "smoother_hetero_finetune"),
        finetune_steps=20,
        finetune_batch=2,
        warmup=10,
        eval_every=40,
        eval_batch=120,  # divides every split's image count: no padded passes
        quick=True,
    )
    return dataclasses.replace(cfg, **overrides)


# ---------------------------------------------------------------------------
# Data splits
# ---------------------------------------------------------------------------


@dataclasses.dataclass
class Split:
    """Sequences of one split plus, once computed, the sensor's positions."""

    fold: D.DiskFold
    images: Any = None  # optional device array (N, T, 120, 120, 3) uint8
    sensor: np.ndarray | None = None  # (N, T, 2) virtual-sensor positions

    @property
    def n(self) -> int:
        return self.fold.num_sequences

    def get_images(self, seqs, frames=None) -> jax.Array:
        if self.images is not None:
            seqs = jnp.asarray(seqs)
            if frames is None:
                return self.images[seqs]
            return self.images[seqs, jnp.asarray(frames)]
        return jnp.asarray(self.fold.images(seqs, frames))


def make_splits(cfg: Config, test_fold: int) -> tuple[Split, Split, Split]:
    """Training, validation (from the training folds) and test splits."""
    load = dict(
        seed=cfg.data_seed,
        num_sequences=cfg.sequences_per_fold,
        num_frames=cfg.num_frames,
        cache_dir=Path(cfg.cache_dir) if cfg.cache_dir else None,
    )
    train_folds = cfg.train_folds
    if train_folds is None:
        train_folds = tuple(k for k in range(cfg.num_folds) if k != test_fold)
    if test_fold in train_folds:
        raise ValueError(f"test fold {test_fold} is also a training fold")
    pool = D.concatenate([D.load_fold(fold=k, **load) for k in train_folds])
    test = D.load_fold(fold=test_fold, **load)
    perm = np.random.default_rng([cfg.data_seed, test_fold, 1]).permutation(
        pool.num_sequences
    )
    n_val = max(1, int(round(cfg.val_fraction * pool.num_sequences)))
    if cfg.max_val_sequences is not None:
        n_val = min(n_val, cfg.max_val_sequences)
    val_idx, train_idx = perm[:n_val], perm[n_val:]
    if cfg.max_train_sequences is not None:
        train_idx = train_idx[: cfg.max_train_sequences]
    test_idx = np.arange(test.num_sequences)
    if cfg.max_test_sequences is not None:
        test_idx = test_idx[: cfg.max_test_sequences]
    splits = (
        Split(pool.subset(np.sort(train_idx))),
        Split(pool.subset(np.sort(val_idx))),
        Split(test.subset(test_idx)),
    )
    if cfg.images_on_device:
        for s in splits[:2]:
            chunks = [
                jnp.asarray(s.fold.images(np.arange(i, min(i + 64, s.n))))
                for i in range(0, s.n, 64)
            ]
            s.images = jnp.concatenate(chunks)
    return splits


# ---------------------------------------------------------------------------
# Generic training loop with validation-based model selection
# ---------------------------------------------------------------------------


def make_optimizer(cfg: Config, lr: float) -> optax.GradientTransformation:
    """Clip by global norm, Adam with linear warm-up (the paper's optimiser)."""
    return eqs.learn.make_optimizer(
        lr, warmup_steps=cfg.warmup, clip_norm=cfg.clip_norm
    )


@dataclasses.dataclass
class FitResult:
    model: Any
    best_val: float
    best_step: int
    history: list[tuple[int, float, float]]  # (step, train loss, val rmse)
    seconds: float
    skipped: int = 0  # batches whose step failed (solver error) and were skipped


def fit(
    name: str,
    model,
    loss_fn: Callable,
    sample_batch: Callable[[np.random.Generator], Any],
    validate: Callable[[Any], float],
    steps: int,
    lr: float,
    cfg: Config,
    seed: int,
) -> FitResult:
    """Adam on `loss_fn(model, batch)`; keep the model with the best validation."""
    opt = make_optimizer(cfg, lr)
    params, static = eqx.partition(model, eqx.is_inexact_array)
    opt_state = opt.init(params)

    @eqx.filter_jit
    def step(params, opt_state, batch):
        def f(p):
            return loss_fn(eqx.combine(p, static), batch)

        loss, grads = jax.value_and_grad(f)(params)
        updates, opt_state = opt.update(grads, opt_state, params)
        return optax.apply_updates(params, updates), opt_state, loss

    rng = np.random.default_rng(seed)
    t0 = time.perf_counter()
    val0 = validate(model)
    best_val = val0 if math.isfinite(val0) else math.inf
    best, best_step = params, 0
    history = [(0, float("nan"), val0)]
    losses = []
    bar = tqdm(range(1, steps + 1), desc=name, leave=False)
    skipped = 0
    for i in bar:
        try:
            new = step(params, opt_state, sample_batch(rng))
            loss = float(new[2])
        except eqx.EquinoxRuntimeError:
            # A solve failed inside the step (e.g. near-singular normal
            # equations for an extreme batch): skip the batch, keep going.
            skipped += 1
            continue
        if not math.isfinite(loss):
            skipped += 1
            continue
        params, opt_state = new[0], new[1]
        losses.append(loss)
        if i % cfg.eval_every == 0 or i == steps:
            val = validate(eqx.combine(params, static))
            mean_loss = float(np.mean(losses)) if losses else float("nan")
            losses = []
            history.append((i, mean_loss, val))
            if math.isfinite(val) and val < best_val:
                best_val, best, best_step = val, params, i
            if _HAVE_TQDM:
                bar.set_postfix(loss=f"{mean_loss:.4g}", val=f"{val:.3f}")
    if skipped:
        print(f"{name}: skipped {skipped} of {steps} batches (solver errors)")
    return FitResult(
        eqx.combine(best, static),
        best_val,
        best_step,
        history,
        time.perf_counter() - t0,
        skipped,
    )


def rmse(pred: np.ndarray, truth: np.ndarray) -> float:
    """Per-coordinate position RMSE in pixels."""
    return float(np.sqrt(np.mean((np.asarray(pred) - np.asarray(truth)) ** 2)))


# ---------------------------------------------------------------------------
# Stage 2-3: virtual sensor
# ---------------------------------------------------------------------------


_predict = eqx.filter_jit(M.predict_positions)


def sensor_positions(sensor: M.VirtualSensor, split: Split, batch: int) -> np.ndarray:
    """The sensor's positions `(N, T, 2)` for every frame of a split."""
    T = split.fold.num_frames
    seq, frame = np.divmod(np.arange(split.n * T), T)
    out = np.empty((split.n * T, 2), dtype=np.float32)
    for i in range(0, out.shape[0], batch):
        sl = slice(i, i + batch)
        ims = split.get_images(seq[sl], frame[sl])
        if ims.shape[0] < batch:  # pad: one compiled shape
            pad = jnp.zeros((batch - ims.shape[0],) + ims.shape[1:], ims.dtype)
            ims = jnp.concatenate([ims, pad])
        out[sl] = np.asarray(_predict(sensor, ims))[: out[sl].shape[0]]
    return out.reshape(split.n, T, 2)


def sensor_loss(sensor, batch):
    images, positions = batch
    pred = M.predict_positions(sensor, images)
    return jnp.mean(((pred - positions) / D.POSITION_STD) ** 2)


def pretrain_sensor(cfg: Config, train: Split, val: Split, key) -> FitResult:
    sensor = M.VirtualSensor(key)
    if cfg.sensor_colour_init:
        sensor = M.target_colour_init(sensor)
    sensor = jax.tree_util.tree_map(
        lambda x: x.astype(cfg.dtype) if eqx.is_inexact_array(x) else x, sensor
    )
    T = train.fold.num_frames

    def sample(rng):
        seqs = rng.integers(0, train.n, cfg.sensor_batch)
        frames = rng.integers(0, T, cfg.sensor_batch)
        pos = train.fold.positions[seqs, frames].astype(cfg.dtype)
        return train.get_images(seqs, frames), jnp.asarray(pos)

    def validate(s):
        pred = sensor_positions(s, val, cfg.eval_batch)
        return rmse(pred, val.fold.positions)

    return fit(
        "virtual sensor",
        sensor,
        sensor_loss,
        sample,
        validate,
        cfg.sensor_steps,
        cfg.sensor_lr,
        cfg,
        seed=cfg.model_seed,
    )


# ---------------------------------------------------------------------------
# Stage 4: smoothers
# ---------------------------------------------------------------------------


class SmootherModel(eqx.Module):
    """A noise head plus the (fixed or learned) dynamics square-root precision."""

    noise: M.AbstractNoiseHead
    log_dynamics_sqrt_precision: jax.Array
    learn_dynamics: bool = eqx.field(static=True, default=False)

    def graph(self, measurements, visible_pixels) -> eqs.FactorGraph:
        # A learned dynamics noise stays within a factor e³ ≈ 20 of the true
        # one, so the normal equations stay well conditioned in float32.
        nominal = jnp.asarray(-np.log(M.DYNAMICS_SIGMAS), measurements.dtype)
        log_dyn = jnp.clip(self.log_dynamics_sqrt_precision, nominal - 3, nominal + 3)
        return M.build_smoother_graph(
            measurements, self.noise(visible_pixels), jnp.exp(log_dyn)
        )


def make_smoother_model(kind: str, sigma: float, key, dtype) -> SmootherModel:
    if kind == "const":
        noise = M.ConstantNoise(sigma, dtype=dtype)
    elif kind == "hetero":
        noise = M.HeteroscedasticNoise(sigma, key, dtype=dtype)
    else:
        raise ValueError(f"unknown noise kind {kind!r}")
    return SmootherModel(noise, jnp.asarray(-np.log(M.DYNAMICS_SIGMAS), dtype=dtype))


def _fixed_dynamics(model: SmootherModel) -> SmootherModel:
    # The paper keeps the dynamics noise fixed: stop its gradient (unless the
    # model learns it, an extension).
    if model.learn_dynamics:
        return model
    return eqx.tree_at(
        lambda m: m.log_dynamics_sqrt_precision,
        model,
        jax.lax.stop_gradient(model.log_dynamics_sqrt_precision),
    )


_POSITION_WEIGHTS = np.array([1.0, 1.0, 0.0, 0.0]) / D.POSITION_STD**2


def surrogate_loss_one(model: SmootherModel, meas, counts, truth, K: int):
    """The paper's surrogate loss: K unrolled Gauss-Newton steps from the truth.

    [`eqsmooth.learn.surrogate_loss`][] scored on positions (normalised by
    their standard deviation), as the paper does.
    """
    graph = _fixed_dynamics(model).graph(meas, counts)
    solver = eqs.FixedStepGaussNewton(eqs.BlockTridiagonal(), num_steps=K)
    weights = {"x": jnp.asarray(_POSITION_WEIGHTS, truth.dtype)}
    return eqs.learn.surrogate_loss(
        graph,
        {"x": truth},
        solver=solver,
        adjoint=eqs.UnrolledAdjoint(),
        weights=weights,
        throw=False,
    )


def implicit_loss_one(model: SmootherModel, meas, counts, truth, max_steps: int):
    """MSE of the converged MAP positions, differentiated implicitly.

    Beyond the paper: Gauss-Newton runs to convergence and the gradient comes
    from the optimality condition ([`eqsmooth.ImplicitAdjoint`][]) instead of
    K unrolled steps.
    """
    graph = _fixed_dynamics(model).graph(meas, counts)
    solver = eqs.GaussNewton(eqs.BlockTridiagonal())
    sol = eqs.least_squares(
        graph,
        {"x": truth},
        solver,
        max_steps=max_steps,
        adjoint=eqs.ImplicitAdjoint(),
        throw=False,
    )
    err = (sol.value["x"][:, :2] - truth[:, :2]) / D.POSITION_STD
    return jnp.mean(err * err)


def joint_nll_one(model: SmootherModel, meas, counts, truth):
    """Joint NLL of the ground truth, per frame ([`eqsmooth.learn.joint_nll`][])."""
    graph = _fixed_dynamics(model).graph(meas, counts)
    return eqs.learn.joint_nll(graph, {"x": truth})


def smooth_one(model: SmootherModel, meas, counts, max_steps: int):
    """MAP trajectory `(T, 4)` by Gauss-Newton from the sensor's positions."""
    graph = model.graph(meas, counts)
    solver = eqs.GaussNewton(eqs.BlockTridiagonal())
    sol = eqs.least_squares(
        graph,
        {"x": M.initial_guess(meas)},
        solver,
        max_steps=max_steps,
        throw=False,
    )
    return sol.value["x"]


@eqx.filter_jit
def _smooth_batch(model, meas, counts, max_steps: int):
    return jax.vmap(smooth_one, in_axes=(None, 0, 0, None))(
        model, meas, counts, max_steps
    )


def _padded_batches(n: int, batch: int):
    """Index arrays of length `batch` covering 0..n-1 (the last one padded).

    One compiled shape for every split size; padded rows repeat the last index
    and are dropped by the caller (`[:count]`).
    """
    for i in range(0, n, batch):
        idx = np.arange(i, min(i + batch, n))
        count = idx.shape[0]
        yield np.concatenate([idx, np.full(batch - count, n - 1)]), count


def smooth_split(model, split: Split, cfg: Config, batch: int = 32) -> np.ndarray:
    out = []
    for idx, count in _padded_batches(split.n, batch):
        meas = jnp.asarray(split.sensor[idx], cfg.dtype)
        counts = jnp.asarray(split.fold.visible_pixels[idx], cfg.dtype)
        res = _smooth_batch(model, meas, counts, cfg.eval_solver_steps)
        out.append(np.asarray(res)[:count])
    return np.concatenate(out)


def _sequence_sampler(split: Split, cfg: Config):
    def sample(rng):
        seqs = rng.integers(0, split.n, cfg.fg_batch)
        return (
            jnp.asarray(split.sensor[seqs], cfg.dtype),
            jnp.asarray(split.fold.visible_pixels[seqs], cfg.dtype),
            jnp.asarray(split.fold.states[seqs], cfg.dtype),
        )

    return sample


def train_smoother(
    cfg: Config,
    kind: str,
    loss: str,
    train: Split,
    val: Split,
    sigma: float,
    key,
    learn_dynamics: bool = False,
) -> FitResult:
    model = make_smoother_model(kind, sigma, key, cfg.dtype)
    if learn_dynamics:
        model = dataclasses.replace(model, learn_dynamics=True)
    K = cfg.surrogate_steps

    def loss_fn(m, batch):
        meas, counts, truth = batch
        if loss == "surrogate":
            per = jax.vmap(surrogate_loss_one, in_axes=(None, 0, 0, 0, None))(
                m, meas, counts, truth, K
            )
        elif loss == "implicit":
            per = jax.vmap(implicit_loss_one, in_axes=(None, 0, 0, 0, None))(
                m, meas, counts, truth, cfg.eval_solver_steps
            )
        else:
            per = jax.vmap(joint_nll_one, in_axes=(None, 0, 0, 0))(
                m, meas, counts, truth
            )
        return jnp.mean(per)

    def validate(m):
        return rmse(smooth_split(m, val, cfg)[..., :2], val.fold.positions)

    return fit(
        f"smoother {kind} {loss}{' +dynamics' if learn_dynamics else ''}",
        model,
        loss_fn,
        _sequence_sampler(train, cfg),
        validate,
        cfg.fg_steps,
        cfg.fg_lr,
        cfg,
        seed=cfg.model_seed + 1,
    )


# ---------------------------------------------------------------------------
# Beyond the paper: fine-tune the CNN end to end through the smoother
# ---------------------------------------------------------------------------


class FinetuneModel(eqx.Module):
    """The virtual sensor and a smoother model, trained together."""

    sensor: M.VirtualSensor
    smoother: SmootherModel


def finetune_loss_one(model: FinetuneModel, images, counts, truth, K: int):
    """The surrogate loss with the sensor's positions computed inside the loss."""
    meas = jax.vmap(model.sensor)(images)
    return surrogate_loss_one(model.smoother, meas, counts, truth, K)


def finetune_eval(model: FinetuneModel, split: Split, cfg: Config) -> np.ndarray:
    """Positions `(N, T, 2)`: the fine-tuned sensor, then the smoother."""
    moved = dataclasses.replace(
        split, sensor=sensor_positions(model.sensor, split, cfg.eval_batch)
    )
    return smooth_split(model.smoother, moved, cfg)[..., :2]


def train_finetune(
    cfg: Config,
    train: Split,
    val: Split,
    sensor: M.VirtualSensor,
    smoother: SmootherModel,
) -> FitResult:
    model = FinetuneModel(sensor, smoother)
    K = cfg.surrogate_steps

    def loss_fn(m, batch):
        images, counts, truth = batch
        per = jax.vmap(finetune_loss_one, in_axes=(None, 0, 0, 0, None))(
            m, images, counts, truth, K
        )
        return jnp.mean(per)

    def sample(rng):
        seqs = rng.integers(0, train.n, cfg.finetune_batch)
        return (
            train.get_images(seqs),
            jnp.asarray(train.fold.visible_pixels[seqs], cfg.dtype),
            jnp.asarray(train.fold.states[seqs], cfg.dtype),
        )

    def validate(m):
        return rmse(finetune_eval(m, val, cfg), val.fold.positions)

    return fit(
        "fine-tune sensor + smoother",
        model,
        loss_fn,
        sample,
        validate,
        cfg.finetune_steps,
        cfg.finetune_lr,
        cfg,
        seed=cfg.model_seed + 4,
    )


# ---------------------------------------------------------------------------
# Stage 5: EKFs
# ---------------------------------------------------------------------------


def ekf_one(model: SmootherModel, meas, counts, x0):
    """EKF means `(T, 4)` and covariances `(T, 4, 4)` from the true first state.

    The filter is [`eqsmooth.filters.ekf`][] built from the smoother's own
    factor stacks (same dynamics and measurement models). As in the paper, it
    starts at the ground-truth first state with a tiny covariance.
    """
    graph = _fixed_dynamics(model).graph(meas, counts)
    dyn, obs = graph.factors
    P0 = 1e-4 * jnp.eye(4, dtype=meas.dtype)
    sol = eqs.filters.ekf(dyn, [obs], x0, P0, throw=False)
    return sol.mean, sol.covariance


def ekf_mse_one(model, meas, counts, truth):
    xs, _ = ekf_one(model, meas, counts, truth[0])
    err = (xs[:, :2] - truth[:, :2]) / D.POSITION_STD
    return jnp.mean(err * err)


def ekf_nll_one(model, meas, counts, truth):
    """The paper's marginal NLL: true positions under the filter's position marginals.

    (`eqsmooth.filters.ekf_marginal_nll` scores the full 4-D state; the paper
    scores positions only, so the 2 x 2 position block is used here.)
    """
    xs, Ps = ekf_one(model, meas, counts, truth[0])
    e = truth[:, :2] - xs[:, :2]
    L = jnp.linalg.cholesky(Ps[:, :2, :2])
    w = jax.scipy.linalg.solve_triangular(L, e[..., None], lower=True)[..., 0]
    logdet = 2 * jnp.sum(jnp.log(jnp.diagonal(L, axis1=1, axis2=2)), axis=1)
    return jnp.mean(0.5 * jnp.sum(w * w, axis=1) + 0.5 * logdet)


@eqx.filter_jit
def _ekf_batch(model, meas, counts, x0):
    return jax.vmap(ekf_one, in_axes=(None, 0, 0, 0))(model, meas, counts, x0)


def ekf_split(model, split: Split, cfg: Config, batch: int = 32) -> np.ndarray:
    out = []
    for idx, count in _padded_batches(split.n, batch):
        meas = jnp.asarray(split.sensor[idx], cfg.dtype)
        counts = jnp.asarray(split.fold.visible_pixels[idx], cfg.dtype)
        x0 = jnp.asarray(split.fold.states[idx, 0], cfg.dtype)
        out.append(np.asarray(_ekf_batch(model, meas, counts, x0)[0])[:count])
    return np.concatenate(out)


def train_ekf(
    cfg: Config, kind: str, loss: str, train: Split, val: Split, sigma: float, key
) -> FitResult:
    model = make_smoother_model(kind, sigma, key, cfg.dtype)
    one = ekf_mse_one if loss == "mse" else ekf_nll_one

    def loss_fn(m, batch):
        meas, counts, truth = batch
        return jnp.mean(jax.vmap(one, in_axes=(None, 0, 0, 0))(m, meas, counts, truth))

    def validate(m):
        return rmse(ekf_split(m, val, cfg)[..., :2], val.fold.positions)

    return fit(
        f"ekf {kind} {loss}",
        model,
        loss_fn,
        _sequence_sampler(train, cfg),
        validate,
        cfg.fg_steps,
        cfg.fg_lr,
        cfg,
        seed=cfg.model_seed + 2,
    )


# ---------------------------------------------------------------------------
# Stage 6: LSTMs
# ---------------------------------------------------------------------------


def lstm_loss(model: M.LstmTracker, batch):
    images, states = batch
    pred = jax.vmap(model)(images, states[:, 0])
    return jnp.mean(((pred - states[..., :2]) / D.POSITION_STD) ** 2)


@eqx.filter_jit
def _lstm_batch(model, images, x0):
    return jax.vmap(model)(images, x0)


def lstm_split(model, split: Split, cfg: Config) -> np.ndarray:
    per = max(1, cfg.eval_batch // split.fold.num_frames)
    out = []
    for idx, count in _padded_batches(split.n, per):
        ims = split.get_images(idx)
        x0 = jnp.asarray(split.fold.states[idx, 0], cfg.dtype)
        out.append(np.asarray(_lstm_batch(model, ims, x0))[:count])
    return np.concatenate(out)


def train_lstm(
    cfg: Config,
    bidirectional: bool,
    train: Split,
    val: Split,
    key,
    sensor: M.VirtualSensor | None,
) -> FitResult:
    model = M.LstmTracker(key, bidirectional, hidden=cfg.lstm_hidden)
    if cfg.lstm_init_from_sensor and sensor is not None:
        # Beyond the paper (quick mode): start the encoder from the pretrained
        # sensor's convolutions and hidden dense layers.
        model = eqx.tree_at(lambda m: m.encoder.convs, model, sensor.convs)
        model = eqx.tree_at(
            lambda m: m.encoder.mlp.layers[:-1], model, sensor.mlp.layers[:-1]
        )
    model = jax.tree_util.tree_map(
        lambda x: x.astype(cfg.dtype) if eqx.is_inexact_array(x) else x, model
    )
    T, L = train.fold.num_frames, cfg.lstm_subsequence

    def sample(rng):
        seqs = rng.integers(0, train.n, cfg.lstm_batch)
        start = rng.integers(0, T - L + 1, cfg.lstm_batch)
        frames = start[:, None] + np.arange(L)[None]
        seq_rep = np.repeat(seqs[:, None], L, axis=1)
        ims = train.get_images(seq_rep.ravel(), frames.ravel())
        ims = ims.reshape((cfg.lstm_batch, L) + ims.shape[1:])
        states = train.fold.states[seq_rep, frames].astype(cfg.dtype)
        return ims, jnp.asarray(states)

    def validate(m):
        return rmse(lstm_split(m, val, cfg), val.fold.positions)

    return fit(
        f"lstm {'bi' if bidirectional else 'uni'}",
        model,
        lstm_loss,
        sample,
        validate,
        cfg.lstm_steps,
        cfg.lstm_lr,
        cfg,
        seed=cfg.model_seed + 3,
    )


# ---------------------------------------------------------------------------
# One fold, end to end
# ---------------------------------------------------------------------------


def run_fold(cfg: Config, test_fold: int, out: Path, log=print) -> dict:
    """Run every stage for one test fold; save weights; return the results."""
    timings: dict[str, float] = {}
    t0 = time.perf_counter()
    train, val, test = make_splits(cfg, test_fold)
    timings["data_s"] = time.perf_counter() - t0
    log(
        f"fold {test_fold}: {train.n} training, {val.n} validation, {test.n} test "
        f"sequences of {cfg.num_frames} frames"
    )
    key = jax.random.key(cfg.model_seed)
    k_sensor, k_noise, k_lstm = jax.random.split(key, 3)
    fold_dir = out / f"fold_{test_fold}"
    fold_dir.mkdir(parents=True, exist_ok=True)
    records: dict[str, dict] = {}

    # Stage 2: virtual sensor.
    t = time.perf_counter()
    sensor_file = None
    if cfg.sensor_weights_dir is not None:
        sensor_file = Path(cfg.sensor_weights_dir) / f"sensor_fold{test_fold}.eqx"
    if sensor_file is not None and sensor_file.exists():
        like = M.VirtualSensor(k_sensor)
        like = jax.tree_util.tree_map(
            lambda x: x.astype(cfg.dtype) if eqx.is_inexact_array(x) else x, like
        )
        sensor = eqx.tree_deserialise_leaves(sensor_file, like)
        log(f"loaded the virtual sensor from {sensor_file}")
        sensor_fit = None
    else:
        if cfg.sensor_colour_init:
            log(
                "virtual sensor: first conv initialised as a target-colour "
                "detector (quick-mode aid, not the paper's protocol)"
            )
        sensor_fit = pretrain_sensor(cfg, train, val, k_sensor)
        sensor = sensor_fit.model
        eqx.tree_serialise_leaves(fold_dir / f"sensor_fold{test_fold}.eqx", sensor)
    timings["sensor_s"] = time.perf_counter() - t

    # Stage 3: sensor positions for every split (frozen sensor).
    t = time.perf_counter()
    for s in (train, val, test):
        s.sensor = sensor_positions(sensor, s, cfg.eval_batch)
    timings["sensor_positions_s"] = time.perf_counter() - t
    val_sensor_rmse = rmse(val.sensor, val.fold.positions)
    records["virtual_sensor"] = dict(
        test_rmse=rmse(test.sensor, test.fold.positions),
        val_rmse=val_sensor_rmse,
        best_step=None if sensor_fit is None else sensor_fit.best_step,
        seconds=timings["sensor_s"],
        history=None if sensor_fit is None else sensor_fit.history,
    )
    log(
        f"virtual sensor: val RMSE {val_sensor_rmse:.3f} px, test RMSE "
        f"{records['virtual_sensor']['test_rmse']:.3f} px"
    )

    models: dict[str, Any] = {}
    test_predictions: dict[str, np.ndarray] = {"virtual_sensor": test.sensor}
    for method in cfg.methods:
        parts = method.split("_")
        t = time.perf_counter()
        if method == "smoother_hetero_finetune":
            start = models.get("smoother_hetero_surrogate")
            if start is None:
                start = make_smoother_model(
                    "hetero", val_sensor_rmse, k_noise, cfg.dtype
                )
            res = train_finetune(cfg, train, val, sensor, start)
            pred = finetune_eval(res.model, test, cfg)
        elif parts[0] == "smoother":
            res = train_smoother(
                cfg,
                parts[1],
                parts[2],
                train,
                val,
                val_sensor_rmse,
                k_noise,
                learn_dynamics=parts[-1] == "learndyn",
            )
            pred = smooth_split(res.model, test, cfg)[..., :2]
        elif parts[0] == "ekf":
            res = train_ekf(
                cfg, parts[1], parts[2], train, val, val_sensor_rmse, k_noise
            )
            pred = ekf_split(res.model, test, cfg)[..., :2]
        elif parts[0] == "lstm":
            res = train_lstm(cfg, parts[1] == "bi", train, val, k_lstm, sensor)
            pred = lstm_split(res.model, test, cfg)
        else:
            raise ValueError(f"unknown method {method!r}")
        models[method] = res.model
        test_predictions[method] = pred
        records[method] = dict(
            test_rmse=rmse(pred, test.fold.positions),
            val_rmse=res.best_val,
            best_step=res.best_step,
            seconds=time.perf_counter() - t,
            skipped_batches=res.skipped,
            history=res.history,
        )
        rec = records[method]
        log(
            f"{method}: val RMSE {res.best_val:.3f} (step {res.best_step}), test "
            f"RMSE {rec['test_rmse']:.3f} px ({rec['seconds']:.0f} s)"
        )
        if parts[0] in ("smoother", "ekf"):
            eqx.tree_serialise_leaves(fold_dir / f"{method}.eqx", res.model)
        if method == "smoother_hetero_finetune":
            test_predictions["sensor_finetuned"] = sensor_positions(
                res.model.sensor, test, cfg.eval_batch
            )
    timings["total_s"] = time.perf_counter() - t0
    return dict(
        fold=test_fold,
        records=records,
        timings=timings,
        models=models,
        test=test,
        val=val,
        test_predictions=test_predictions,
    )
