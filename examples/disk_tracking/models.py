"""Models for visual disk tracking: virtual sensor, noise heads, smoother, LSTMs.

Architectures follow Yi et al. 2021 (Sec. V-A, and the issue that specifies
this reproduction):

- virtual sensor: 3 x [conv 3x3, 32 ch, ReLU], conv 3x3 32 ch; max over
  channels; row means and column means concatenated (240 features);
  3 x [dense 32, ReLU]; dense 2 (the position, in pixels);
- noise heads giving the square-root precision of the position measurement:
  constant (one learned scalar) or heteroscedastic (an MLP, 4 x 64 ReLU, on
  the normalised visible-pixel count);
- smoother: known dynamics factor with fixed noise (state `[px, py, vx, vy]`)
  and one position factor per frame whose noise comes from the noise head; no
  prior on the first state (the paper's graph has none);
- LSTM baselines: the CNN with 32 outputs as encoder, an LSTM (hidden 64),
  uni- or bidirectional, carry initialised from the ground-truth first state.
"""

import abc

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float, PRNGKeyArray

import eqsmooth as eqs

from . import data as D


DYNAMICS_SIGMAS = np.array(
    [D.POSITION_NOISE_STD, D.POSITION_NOISE_STD]
    + [D.VELOCITY_NOISE_STD, D.VELOCITY_NOISE_STD]
)
VELOCITY_STD = 6.6  # scale of the velocities (pixels / frame), for the LSTM input
# Smallest square-root precision a noise head returns (σ ≤ 100 px, nearly the
# image size). Without it a head can drive the precision to zero, and the
# smoother's normal equations (no prior on the first state) become singular
# in float32: their condition number grows like 20 / s².
SQRT_PRECISION_FLOOR = 1e-2


# ---------------------------------------------------------------------------
# Virtual sensor
# ---------------------------------------------------------------------------


class VirtualSensor(eqx.Module):
    """The paper's disk CNN: image `(120, 120, 3)` uint8 -> `output_dim` features.

    With `output_dim=2` (the virtual sensor) the output is the position in
    pixels (the network's normalised output times `output_scale`).
    """

    convs: tuple[eqx.nn.Conv2d, ...]
    mlp: eqx.nn.MLP
    output_scale: float = eqx.field(static=True)

    def __init__(
        self,
        key: PRNGKeyArray,
        output_dim: int = 2,
        output_scale: float = D.POSITION_STD,
        channels: int = 32,
    ):
        keys = jax.random.split(key, 5)
        convs = []
        in_ch = 3
        for k in keys[:4]:
            convs.append(eqx.nn.Conv2d(in_ch, channels, 3, padding=1, key=k))
            in_ch = channels
        self.convs = tuple(convs)
        self.mlp = eqx.nn.MLP(
            2 * D.IMAGE_SIZE,
            output_dim,
            width_size=32,
            depth=3,
            activation=jax.nn.relu,
            key=keys[4],
        )
        self.output_scale = float(output_scale)
        # He-normal weights before ReLUs, LeCun-normal before linear outputs,
        # zero biases (equinox's default uniform init shrinks the signal
        # through the four convolutions and slows training badly).
        k_init = jax.random.split(keys[4], 8)
        new_convs = tuple(
            _normal_init(c, k, gain=2.0 if i < 3 else 1.0)
            for i, (c, k) in enumerate(zip(self.convs, k_init[:4]))
        )
        self.convs = new_convs
        layers = tuple(
            _normal_init(lin, k, gain=2.0 if i < len(self.mlp.layers) - 1 else 1.0)
            for i, (lin, k) in enumerate(zip(self.mlp.layers, k_init[4:]))
        )
        self.mlp = eqx.tree_at(lambda m: m.layers, self.mlp, layers)

    def features(self, image: Array) -> Float[Array, " 240"]:
        """The 240 pooled features of one image."""
        dtype = self.convs[0].weight.dtype
        mean = jnp.asarray(D.IMAGE_MEAN, dtype)[None, None, :]
        std = jnp.asarray(D.IMAGE_STD, dtype)[None, None, :]
        x = (image.astype(dtype) - mean) / std
        x = jnp.transpose(x, (2, 0, 1))  # (3, H, W)
        for conv in self.convs[:-1]:
            x = jax.nn.relu(conv(x))
        x = self.convs[-1](x)
        x = jnp.max(x, axis=0)  # (H, W): max over channels
        # Row means (one per row, i.e. along y) and column means (along x).
        return jnp.concatenate([jnp.mean(x, axis=1), jnp.mean(x, axis=0)])

    def __call__(self, image: Array) -> Float[Array, " out"]:
        return self.mlp(self.features(image)) * self.output_scale


def target_colour_init(
    sensor: VirtualSensor, noise_scale: float = 0.1
) -> VirtualSensor:
    """Start every first-layer filter as a detector of the target's colour.

    A quick-mode aid, **not the paper's protocol** (the full protocol trains
    the sensor from a random initialisation, 85,000 steps of 32 images). On a
    CPU budget of about a thousand images the randomly initialised sensor
    stays at the "predict the mean" plateau (31 px); from this start it
    reaches about 15 px in 100 steps of 8 images (docs/tutorial/disk-tracking.md).

    Each filter of `sensor.convs[0]` becomes `noise_scale` times its random
    weights plus, at its centre tap, the colour direction `sign(t̂) / √3`
    (`t̂` the normalised target colour: `(+1, −1, −1) / √3` for red), with a
    bias half-way between the target's projection on that direction and the
    largest projection of any other colour (the distractors and the black
    background). After the ReLU it fires on target pixels only. Everything
    stays trainable.
    """
    conv = sensor.convs[0]

    def normalised(colours):
        return (np.asarray(colours, np.float64) - D.IMAGE_MEAN) / D.IMAGE_STD

    target = normalised(D.TARGET_COLOUR)
    direction = np.sign(target) / np.sqrt(3.0)
    others = normalised(np.concatenate([D.DISTRACTOR_COLOURS, [[0, 0, 0]]]))
    threshold = 0.5 * (target @ direction + np.max(others @ direction))
    weight = noise_scale * np.asarray(conv.weight, np.float64)
    weight[:, :, 1, 1] += direction
    bias = np.full(conv.bias.shape, -threshold)
    dtype = conv.weight.dtype
    return eqx.tree_at(
        lambda s: (s.convs[0].weight, s.convs[0].bias),
        sensor,
        (jnp.asarray(weight, dtype), jnp.asarray(bias, dtype)),
    )


def _normal_init(layer, key, gain: float):
    """Weights `N(0, gain / fan_in)` and zero bias for a Linear or Conv layer."""
    w = layer.weight
    fan_in = int(np.prod(w.shape[1:]))
    new_w = jax.random.normal(key, w.shape, w.dtype) * np.sqrt(gain / fan_in)
    return eqx.tree_at(
        lambda lay: (lay.weight, lay.bias),
        layer,
        (new_w, jnp.zeros_like(layer.bias)),
    )


def predict_positions(sensor: VirtualSensor, images: Array) -> Float[Array, "*b 2"]:
    """Apply the sensor to images of any leading shape `(*b, 120, 120, 3)`."""
    lead = images.shape[:-3]
    flat = images.reshape((-1,) + images.shape[-3:])
    out = jax.vmap(sensor)(flat)
    return out.reshape(lead + out.shape[-1:])


# ---------------------------------------------------------------------------
# Noise heads: visible pixels -> square-root precision of the position factor
# ---------------------------------------------------------------------------


class AbstractNoiseHead(eqx.Module):
    """Maps visible-pixel counts `(T,)` to square-root precisions `(T,)` (1/px)."""

    @abc.abstractmethod
    def __call__(self, visible_pixels: Float[Array, " T"]) -> Float[Array, " T"]:
        """Square-root precision for each frame."""


def _above_floor(sigma: float) -> float:
    return max(1.0 / sigma - SQRT_PRECISION_FLOOR, 1e-3)


class ConstantNoise(AbstractNoiseHead):
    """One learned square-root precision shared by every frame.

    `σ⁻¹ = floor + exp(θ)`, starting at `σ⁻¹ = 1/sigma`.
    """

    log_sqrt_precision: Float[Array, ""]

    def __init__(self, sigma: float, dtype=jnp.float32):
        self.log_sqrt_precision = jnp.asarray(np.log(_above_floor(sigma)), dtype=dtype)

    def __call__(self, visible_pixels):
        s = SQRT_PRECISION_FLOOR + jnp.exp(self.log_sqrt_precision)
        return jnp.broadcast_to(s, visible_pixels.shape)


class HeteroscedasticNoise(AbstractNoiseHead):
    """`σ⁻¹(c) = floor + s₀ softplus(MLP(ĉ) + softplus⁻¹(1))`, `ĉ` the normalised count.

    The MLP has 4 hidden layers of 64 ReLU units; its last layer starts at
    zero, so training starts from the constant `σ⁻¹ = 1/sigma` (the inverse
    of the virtual sensor's validation RMSE).
    """

    mlp: eqx.nn.MLP
    base: float = eqx.field(static=True)

    def __init__(self, sigma: float, key: PRNGKeyArray, dtype=jnp.float32):
        mlp = eqx.nn.MLP(
            1, 1, width_size=64, depth=4, activation=jax.nn.relu, key=key, dtype=dtype
        )
        last = mlp.layers[-1]
        last = eqx.tree_at(
            lambda lin: (lin.weight, lin.bias),
            last,
            (jnp.zeros_like(last.weight), jnp.zeros_like(last.bias)),
        )
        self.mlp = eqx.tree_at(lambda m: m.layers[-1], mlp, last)
        self.base = _above_floor(sigma)

    def __call__(self, visible_pixels):
        dtype = self.mlp.layers[0].weight.dtype
        c = (visible_pixels.astype(dtype) - D.VISIBLE_PIXELS_MEAN) / (
            D.VISIBLE_PIXELS_STD
        )
        out = jax.vmap(self.mlp)(c[:, None])[:, 0]
        shift = float(np.log(np.expm1(1.0)))  # softplus(shift) = 1
        return SQRT_PRECISION_FLOOR + self.base * jax.nn.softplus(out + shift)


# ---------------------------------------------------------------------------
# Smoother factor graph
# ---------------------------------------------------------------------------


def disk_dynamics(x: Float[Array, " 4"]) -> Float[Array, " 4"]:
    """Noise-free disk dynamics on `[px, py, vx, vy]` (both from the old state)."""
    p, v = x[:2], x[2:]
    return jnp.concatenate([p + v, v - D.SPRING * p - D.DRAG * jnp.sign(v) * v * v])


def dynamics_residual(x_prev, x_next, data, params):
    return x_next - disk_dynamics(x_prev)


def position_residual(x, data, params):
    return x[:2] - data


def build_smoother_graph(
    measurements: Float[Array, "T 2"],
    sqrt_precision: Float[Array, " T"],
    dynamics_sqrt_precision: Float[Array, " 4"],
) -> eqs.FactorGraph:
    """The smoother for one sequence.

    **Arguments:**

    - `measurements`: virtual-sensor positions (pixels), one per frame.
    - `sqrt_precision`: per-frame square-root precision of those positions.
    - `dynamics_sqrt_precision`: `1/σ` of the dynamics noise, `(4,)` (fixed at
        `1/[0.1, 0.1, 2, 2]` in the paper; learnable as an extension).

    **Returns:** an [`eqsmooth.FactorGraph`][] over the group `"x"` of `T`
    states `[px, py, vx, vy]`.
    """
    T = measurements.shape[0]
    t = np.arange(T)
    dyn = eqs.FunctionFactor(
        dynamics_residual,
        (eqs.Var("x", t[:-1]), eqs.Var("x", t[1:])),
        eqs.DiagonalNoise(dynamics_sqrt_precision),
    )
    obs = eqs.FunctionFactor(
        position_residual,
        (eqs.Var("x", t),),
        eqs.IsotropicNoise(sqrt_precision),
        data=measurements,
    )
    return eqs.FactorGraph([dyn, obs])


def initial_guess(measurements: Float[Array, "T 2"]) -> Float[Array, "T 4"]:
    """Solver start: the measured positions with finite-difference velocities."""
    v = jnp.diff(measurements, axis=0)
    v = jnp.concatenate([v, v[-1:]], axis=0)
    return jnp.concatenate([measurements, v], axis=1)


# ---------------------------------------------------------------------------
# LSTM baselines
# ---------------------------------------------------------------------------


class LstmTracker(eqx.Module):
    """CNN encoder (32 features per frame) + LSTM + MLP head -> positions (px).

    The carry is initialised from the ground-truth first state through a small
    MLP (the paper's LSTM baselines are given it).
    """

    encoder: VirtualSensor
    carry_init: eqx.nn.MLP
    forward_cell: eqx.nn.LSTMCell
    backward_cell: eqx.nn.LSTMCell | None
    head: eqx.nn.MLP
    hidden: int = eqx.field(static=True)

    def __init__(self, key: PRNGKeyArray, bidirectional: bool, hidden: int = 64):
        k = jax.random.split(key, 5)
        dirs = 2 if bidirectional else 1
        self.encoder = VirtualSensor(k[0], output_dim=32, output_scale=1.0)
        self.carry_init = eqx.nn.MLP(
            4, 2 * hidden * dirs, 32, 1, activation=jax.nn.relu, key=k[1]
        )
        self.forward_cell = eqx.nn.LSTMCell(32, hidden, key=k[2])
        self.backward_cell = (
            eqx.nn.LSTMCell(32, hidden, key=k[3]) if bidirectional else None
        )
        self.head = eqx.nn.MLP(
            hidden * dirs, 2, 32, 1, activation=jax.nn.relu, key=k[4]
        )
        self.hidden = hidden

    def __call__(
        self, images: Array, initial_state: Float[Array, " 4"]
    ) -> Float[Array, "T 2"]:
        feats = jax.vmap(self.encoder)(images)  # (T, 32)
        dtype = feats.dtype
        scale = jnp.asarray(
            [D.POSITION_STD, D.POSITION_STD, VELOCITY_STD, VELOCITY_STD], dtype
        )
        c0 = self.carry_init(initial_state.astype(dtype) / scale)
        h = self.hidden

        def run(cell, carry, xs):
            def step(carry, x):
                carry = cell(x, carry)
                return carry, carry[0]

            _, hs = jax.lax.scan(step, carry, xs)
            return hs

        out = run(self.forward_cell, (c0[:h], c0[h : 2 * h]), feats)
        if self.backward_cell is not None:
            back = run(
                self.backward_cell, (c0[2 * h : 3 * h], c0[3 * h :]), feats[::-1]
            )
            out = jnp.concatenate([out, back[::-1]], axis=1)
        return jax.vmap(self.head)(out) * D.POSITION_STD
