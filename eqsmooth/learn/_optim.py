"""The optimiser most training runs need: clipping + Adam with warm-up."""

import jax
import optax


def standard_promotion(
    optimizer: optax.GradientTransformation,
) -> optax.GradientTransformation:
    """Run an optax optimiser's `init`/`update` under standard dtype promotion.

    optax mixes Python floats with integer step counts (Adam's bias
    correction `b1 ** count`), which `jax_numpy_dtype_promotion="strict"`
    rejects. Wrapping keeps it usable from strictly typed code; the result
    dtypes are unchanged (updates take the dtype of the gradients).

    **Arguments:**

    - `optimizer`: an `optax.GradientTransformation`.

    **Returns:** the wrapped `optax.GradientTransformation`.
    """

    def init(params):
        with jax.numpy_dtype_promotion("standard"):
            return optimizer.init(params)

    def update(updates, state, params=None):
        with jax.numpy_dtype_promotion("standard"):
            return optimizer.update(updates, state, params)

    return optax.GradientTransformation(init, update)


def make_optimizer(
    learning_rate: float,
    *,
    warmup_steps: int = 0,
    decay_steps: int | None = None,
    final_learning_rate: float = 0.0,
    clip_norm: float | None = 1.0,
    b1: float = 0.9,
    b2: float = 0.999,
    eps: float = 1e-8,
    weight_decay: float = 0.0,
) -> optax.GradientTransformation:
    """Gradient clipping by global norm, then Adam with linear warm-up.

    The learning rate rises linearly from 0 to `learning_rate` over
    `warmup_steps` updates, then stays constant, or, with `decay_steps`,
    follows a cosine from `learning_rate` down to `final_learning_rate`,
    reached after `decay_steps` updates in total (warm-up included).

    **Arguments:**

    - `learning_rate`: peak learning rate.
    - `warmup_steps`: length of the linear warm-up (0: none).
    - `decay_steps`: total number of steps of the warm-up + cosine schedule;
        `None` keeps the rate constant after warm-up.
    - `final_learning_rate`: the rate at the end of the cosine decay.
    - `clip_norm`: clip gradients to this global norm first (`None`: no
        clipping).
    - `b1`, `b2`, `eps`: Adam's parameters.
    - `weight_decay`: decoupled weight decay (AdamW) if positive.

    **Returns:** an `optax.GradientTransformation`.
    """
    if learning_rate <= 0:
        raise ValueError(
            f"make_optimizer: learning_rate must be > 0, got {learning_rate}"
        )
    if warmup_steps < 0:
        raise ValueError(
            f"make_optimizer: warmup_steps must be >= 0, got {warmup_steps}"
        )
    if clip_norm is not None and clip_norm <= 0:
        raise ValueError(f"make_optimizer: clip_norm must be > 0, got {clip_norm}")
    if decay_steps is not None:
        if decay_steps <= warmup_steps:
            raise ValueError(
                f"make_optimizer: decay_steps ({decay_steps}) must exceed "
                f"warmup_steps ({warmup_steps})"
            )
        schedule = optax.warmup_cosine_decay_schedule(
            init_value=0.0,
            peak_value=learning_rate,
            warmup_steps=warmup_steps,
            decay_steps=decay_steps,
            end_value=final_learning_rate,
        )
    elif warmup_steps > 0:
        schedule = optax.linear_schedule(0.0, learning_rate, warmup_steps)
    else:
        schedule = optax.constant_schedule(learning_rate)
    if weight_decay > 0:
        adam = optax.adamw(schedule, b1=b1, b2=b2, eps=eps, weight_decay=weight_decay)
    else:
        adam = optax.adam(schedule, b1=b1, b2=b2, eps=eps)
    parts = [] if clip_norm is None else [optax.clip_by_global_norm(clip_norm)]
    return standard_promotion(optax.chain(*parts, adam))
