"""Models for visual disk tracking: virtual sensor, noise heads, smoother, LSTMs.

Architectures follow Yi et al. 2021 (Sec. V-A, and the issue that specifies
this reproduction):

- virtual sensor (default, ours): `HeatmapSensor`, a heat map at half
  resolution read out by a soft-argmax with a learned "not visible" outcome;
  about 2 ms per image for a forward and backward pass on 2 CPU cores, where
  the paper's CNN (`VirtualSensor`: 3 x [conv 3x3, 32 ch, ReLU], conv 3x3 32
  ch; max over channels; row and column means; 3 x [dense 32, ReLU]; dense 2)
  takes about 120 ms (measured with `benchmarks/disk_sensor.py`, removed in
  983df42: `git show 7c30f80:benchmarks/disk_sensor.py`);
- noise heads giving the square-root precision of the position measurement:
  constant (one learned scalar) or heteroscedastic (an MLP, 4 x 64 ReLU, on
  the normalised visible-pixel count);
- smoother: known dynamics factor with fixed noise (state `[px, py, vx, vy]`)
  and one position factor per frame whose noise comes from the noise head; no
  prior on the first state (the paper's graph has none);
- LSTM baselines: an LSTM (hidden 64), uni- or bidirectional, reading the
  frozen sensor's per-frame features (cached once per fold), carry initialised
  from the ground-truth first state.
"""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float, PRNGKeyArray

import eqsmooth as eqs
import eqsmooth.learn as L

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
# σ of the prior on the first state: the EKF baseline's initial covariance is
# 1e-4 I (it starts at the ground-truth first state, as in the paper).
INITIAL_STATE_SIGMA = 1e-2


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


class HeatmapSensor(eqx.Module):
    """A fast virtual sensor: a heat map read out by a soft-argmax.

    Image `(120, 120, 3)` uint8 -> position `(2,)` in pixels. Two 3 x 3
    convolutions (the first with stride 2) make a `channels`-deep map at half
    resolution, a third makes one heat logit `h_ij` per 2 x 2 cell. The
    position is the softmax-weighted mean of the cell centres, with one more
    outcome, "not visible", whose logit `b` and position `p_b` are learned:

    `p = (Σ_ij e^{h_ij} c_ij + e^b p_b) / (Σ_ij e^{h_ij} + e^b)`.

    When the target is hidden or outside the image, the heat map has nothing
    to point at and the learned outcome takes the weight. `visibility(image)`
    returns `logsumexp(h) - b`, the sensor's own evidence that it sees the
    target; the LSTM baselines read it as a feature.
    """

    conv1: eqx.nn.Conv2d
    conv2: eqx.nn.Conv2d
    heat: eqx.nn.Conv2d
    background: Float[Array, " 3"]  # logit, x, y of the "not visible" outcome

    def __init__(self, key: PRNGKeyArray, channels: int = 16):
        k = jax.random.split(key, 3)
        self.conv1 = _normal_init(
            eqx.nn.Conv2d(3, channels, 3, stride=2, padding=1, key=k[0]), k[0], 2.0
        )
        self.conv2 = _normal_init(
            eqx.nn.Conv2d(channels, channels, 3, padding=1, key=k[1]), k[1], 2.0
        )
        self.heat = _normal_init(
            eqx.nn.Conv2d(channels, 1, 3, padding=1, key=k[2]), k[2], 1.0
        )
        cells = (D.IMAGE_SIZE // 2) ** 2
        # Start with the "not visible" outcome as heavy as the whole map.
        self.background = jnp.array([float(np.log(cells)), 0.0, 0.0])

    def _logits(self, image: Array) -> Float[Array, "60 60"]:
        dtype = self.conv1.weight.dtype
        mean = jnp.asarray(D.IMAGE_MEAN, dtype)[None, None, :]
        std = jnp.asarray(D.IMAGE_STD, dtype)[None, None, :]
        x = jnp.transpose((image.astype(dtype) - mean) / std, (2, 0, 1))
        x = jax.nn.relu(self.conv1(x))
        x = jax.nn.relu(self.conv2(x))
        return self.heat(x)[0]

    def outputs(self, image: Array) -> tuple[Float[Array, " 2"], Float[Array, ""]]:
        """Position `(2,)` in pixels and the visibility logit of one image."""
        h = self._logits(image)
        n = h.shape[0]
        # Cell (i, j) is centred on pixel (2i, 2j); pixel k sits at k - 60.
        centres = jnp.arange(n, dtype=h.dtype) * 2.0 - D.IMAGE_SIZE // 2
        logits = jnp.concatenate([h.ravel(), self.background[:1].astype(h.dtype)])
        w = jax.nn.softmax(logits)
        bg = self.background.astype(h.dtype)
        xs = jnp.concatenate([jnp.tile(centres, n), bg[1:2]])
        ys = jnp.concatenate([jnp.repeat(centres, n), bg[2:3]])
        position = jnp.stack([w @ xs, w @ ys])
        visibility = jax.nn.logsumexp(h) - bg[0]
        return position, visibility

    def __call__(self, image: Array) -> Float[Array, " 2"]:
        return self.outputs(image)[0]

    def features(self, image: Array) -> Float[Array, " 3"]:
        """Per-frame features for the LSTM baselines: scaled position, visibility."""
        position, visibility = self.outputs(image)
        return jnp.concatenate(
            [position / D.POSITION_STD, jnp.clip(visibility, -20, 20)[None] / 10]
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


def constant_noise(sigma: float, dtype=jnp.float32) -> L.ConstantNoiseHead:
    """One learned square-root precision shared by every frame, starting at
    `1/sigma` (never below `SQRT_PRECISION_FLOOR`)."""
    return L.ConstantNoiseHead(sigma, floor=SQRT_PRECISION_FLOOR, dtype=dtype)


def heteroscedastic_noise(
    sigma: float, key: PRNGKeyArray, dtype=jnp.float32
) -> L.HeteroscedasticNoiseHead:
    """The square-root precision of each frame from its visible-pixel count
    (the head's one feature, normalised with the training statistics): an
    MLP of 4 hidden layers of 64 ReLU units, starting at the constant
    `1/sigma` (the inverse of the virtual sensor's validation RMSE).
    Called as `head(visible_pixels[:, None])`."""
    return L.HeteroscedasticNoiseHead(
        sigma,
        1,
        width=64,
        depth=4,
        key=key,
        floor=SQRT_PRECISION_FLOOR,
        shift=D.VISIBLE_PIXELS_MEAN,
        scale=D.VISIBLE_PIXELS_STD,
        dtype=dtype,
    )


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


# The target (radius 7, centre `round(p) + 60` in a 120-pixel image) has no
# pixel in the image once `|p|` exceeds about 67 in x or y.
VIEW_HALF_WIDTH = float(D.IMAGE_SIZE // 2 + D.TARGET_RADIUS)
VIEW_SOFTNESS = 2.0  # px: width of the smooth hinge of the out-of-view factor


def out_of_view_residual(x, data, params):
    """How far inside the image window a hidden target's position is (px).

    `s·softplus((L − max(|px|, |py|)) / s)`: about zero once the target is
    out of the window `[−L, L]²`, `L = VIEW_HALF_WIDTH`, and about the depth
    `L − max|p|` inside it; `data` is 1 for frames with no visible target
    pixel and 0 otherwise.
    """
    depth = VIEW_HALF_WIDTH - jnp.max(jnp.abs(x[:2]))
    return (data * VIEW_SOFTNESS * jax.nn.softplus(depth / VIEW_SOFTNESS))[None]


def build_smoother_graph(
    measurements: Float[Array, "T 2"],
    sqrt_precision: Float[Array, " T"],
    dynamics_sqrt_precision: Float[Array, " 4"],
    initial_state: Float[Array, " 4"] | None = None,
    out_of_view: tuple[Float[Array, ""], Float[Array, " T"]] | None = None,
    out_of_view_robust_scale: float | None = None,
) -> eqs.FactorGraph:
    """The smoother for one sequence.

    **Arguments:**

    - `measurements`: virtual-sensor positions (pixels), one per frame.
    - `sqrt_precision`: per-frame square-root precision of those positions.
    - `dynamics_sqrt_precision`: `1/σ` of the dynamics noise, `(4,)` (fixed at
        `1/[0.1, 0.1, 2, 2]` in the paper; learnable as an extension).
    - `initial_state`: the ground-truth first state, given to every method of
        the protocol (the EKF and LSTM baselines start from it, as in the
        paper): a prior factor with `σ = INITIAL_STATE_SIGMA`, the EKF's
        initial standard deviation. `None`: no prior (the paper's graph).
    - `out_of_view`: `(sqrt_precision, hidden)`, beyond the paper: one factor
        per frame with residual [`out_of_view_residual`][], active where
        `hidden` is 1 (no visible target pixel). An unseen target is most
        often outside the image (74 % of such frames in fold 1), which a
        Gaussian position factor cannot say. `None`: no such factor.
    - `out_of_view_robust_scale`: `k` of a Geman-McClure kernel on the
        out-of-view factor (whitened units), or `None` for a plain quadratic.
        The hinge is wrong for a target occluded inside the image (26 % of
        the hidden frames in fold 1); with the kernel, an estimate that the
        dynamics and the other frames place deep inside the window pays at
        most `k²/2` and is left there, while one near the edge is pushed out.

    **Returns:** an [`eqsmooth.FactorGraph`][] over the group `"x"` of `T`
    states `[px, py, vx, vy]`.
    """
    T = measurements.shape[0]
    t = np.arange(T)
    dyn = eqs.FunctionFactor(
        dynamics_residual,
        (eqs.Var("x", t[:-1]), eqs.Var("x", t[1:])),
        eqs.DiagonalNoise(sqrt_precision=dynamics_sqrt_precision),
    )
    obs = eqs.FunctionFactor(
        position_residual,
        (eqs.Var("x", t),),
        eqs.IsotropicNoise(sqrt_precision=sqrt_precision),
        data=measurements,
    )
    factors: list[eqs.AbstractFactor] = [dyn, obs]
    if initial_state is not None:
        factors.append(
            eqs.PriorFactor(
                eqs.Var("x", np.zeros(1, dtype=int)),
                initial_state[None],
                eqs.IsotropicNoise.from_sigma(INITIAL_STATE_SIGMA),
            )
        )
    if out_of_view is not None:
        view_sqrt_precision, hidden = out_of_view
        noise: eqs.AbstractNoiseModel = eqs.IsotropicNoise(
            sqrt_precision=jnp.broadcast_to(view_sqrt_precision, (T,))
        )
        if out_of_view_robust_scale is not None:
            noise = eqs.GemanMcClureNoise(
                noise, jnp.full((T,), out_of_view_robust_scale, hidden.dtype)
            )
        factors.append(
            eqs.FunctionFactor(
                out_of_view_residual, (eqs.Var("x", t),), noise, data=hidden
            )
        )
    return eqs.FactorGraph(factors)


def initial_guess(
    measurements: Float[Array, "T 2"], initial_state: Float[Array, " 4"] | None = None
) -> Float[Array, "T 4"]:
    """Solver start: the measured positions with finite-difference velocities
    (and the known first state, when given)."""
    v = jnp.diff(measurements, axis=0)
    v = jnp.concatenate([v, v[-1:]], axis=0)
    x = jnp.concatenate([measurements, v], axis=1)
    if initial_state is not None:
        x = x.at[0].set(initial_state.astype(x.dtype))
    return x


# ---------------------------------------------------------------------------
# LSTM baselines
# ---------------------------------------------------------------------------


class LstmTracker(eqx.Module):
    """LSTM + MLP head on cached per-frame sensor features -> positions (px).

    The features are the frozen virtual sensor's (`sensor.features`, plus the
    normalised visible-pixel count the heteroscedastic noise heads read), so
    the LSTM sees what the smoothers see. The carry is initialised from the
    ground-truth first state through a small MLP (the paper's LSTM baselines
    are given it).
    """

    carry_init: eqx.nn.MLP
    encoder: eqx.nn.MLP
    forward_cell: eqx.nn.LSTMCell
    backward_cell: eqx.nn.LSTMCell | None
    head: eqx.nn.MLP
    hidden: int = eqx.field(static=True)

    def __init__(
        self,
        key: PRNGKeyArray,
        bidirectional: bool,
        num_features: int,
        hidden: int = 64,
    ):
        k = jax.random.split(key, 5)
        dirs = 2 if bidirectional else 1
        self.carry_init = eqx.nn.MLP(
            4, 2 * hidden * dirs, 32, 1, activation=jax.nn.relu, key=k[0]
        )
        self.encoder = eqx.nn.MLP(
            num_features, 32, 64, 1, activation=jax.nn.relu, key=k[1]
        )
        self.forward_cell = eqx.nn.LSTMCell(32, hidden, key=k[2])
        self.backward_cell = (
            eqx.nn.LSTMCell(32, hidden, key=k[3]) if bidirectional else None
        )
        self.head = eqx.nn.MLP(
            hidden * dirs, 2, 64, 1, activation=jax.nn.relu, key=k[4]
        )
        self.hidden = hidden

    def __call__(
        self, features: Float[Array, "T F"], initial_state: Float[Array, " 4"]
    ) -> Float[Array, "T 2"]:
        x = jax.vmap(self.encoder)(features)  # (T, 32)
        dtype = x.dtype
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

        out = run(self.forward_cell, (c0[:h], c0[h : 2 * h]), x)
        if self.backward_cell is not None:
            back = run(self.backward_cell, (c0[2 * h : 3 * h], c0[3 * h :]), x[::-1])
            out = jnp.concatenate([out, back[::-1]], axis=1)
        return jax.vmap(self.head)(out) * D.POSITION_STD
