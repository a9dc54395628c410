"""Synthetic visual disk tracking data (the system of Yi et al. 2021, Sec. V-A).

A red target disk and 25 coloured distractor disks move with the same
damped-spring dynamics inside 120 x 120 RGB images. The target is drawn first,
the distractors over it, so they occlude it.

Memory: a fold stores only the disk states (positions of all 26 disks per
frame, radii, colours) and the per-frame visible-pixel counts, a few MB.
Images are rendered on demand from those states (`DiskFold.images`), which is
deterministic and fast (vectorised over images, one loop over the 26 disks).
So the whole 10-fold data set never sits in memory, yet every image is
available at any time.

Determinism: sequence `i` of fold `k` depends only on `(seed, k, i)` (one
`numpy` generator per sequence, spawned from a `SeedSequence`), so a quick
run's first sequences are exactly those of the full protocol.
"""

import dataclasses
import time
from pathlib import Path

import numpy as np

from .._data import leading_axes, load_cache


IMAGE_SIZE = 120
NUM_DISTRACTORS = 25
TARGET_RADIUS = 7
DISTRACTOR_RADII = (3, 9)  # inclusive range of integer radii
TARGET_COLOUR = (255, 0, 0)
DISTRACTOR_COLOURS = np.array(
    [
        [0, 255, 0],  # green
        [0, 0, 255],  # blue
        [0, 255, 255],  # cyan
        [255, 0, 255],  # magenta
        [255, 255, 0],  # yellow
        [255, 255, 255],  # white
    ],
    dtype=np.uint8,
)
SPRING = 0.05
DRAG = 0.0075
POSITION_NOISE_STD = 0.1
VELOCITY_NOISE_STD = 2.0
INITIAL_POSITION_RANGE = 60.0
INITIAL_VELOCITY_STD = 3.0

NUM_FOLDS = 10
SEQUENCES_PER_FOLD = 505
FRAMES_PER_SEQUENCE = 20

# Normalisation constants (0-255 image scale, pixels). Measured on our
# generator: 200 sequences x 20 frames of fold 0, seed 0 (see the tests,
# which re-measure them on fresh sequences). They only set input/output
# scales of the networks, so small differences between folds do not matter.
IMAGE_MEAN = np.array([24.7, 30.3, 29.6], dtype=np.float32)
IMAGE_STD = np.array([75.4, 82.5, 81.7], dtype=np.float32)
POSITION_STD = 31.0
VISIBLE_PIXELS_MEAN = 102.0
VISIBLE_PIXELS_STD = 49.0


def dynamics_step(p: np.ndarray, v: np.ndarray, wp: np.ndarray, wv: np.ndarray):
    """One step of the disk dynamics, both updates from the pre-update state."""
    p_next = p + v + wp
    v_next = v - SPRING * p - DRAG * np.sign(v) * v * v + wv
    return p_next, v_next


@dataclasses.dataclass(frozen=True)
class DiskFold:
    """One fold of disk tracking sequences (states only; images on demand).

    Disk 0 is the red target; disks 1..25 are distractors drawn in order
    after it. Coordinates: origin at the image centre, x to the right, y down,
    in pixels.

    **Fields:**

    - `disk_positions`: `(N, T, 26, 2)` float32 positions of every disk.
    - `disk_velocities`: `(N, T, 26, 2)` float32 velocities.
    - `radii`: `(N, 26)` int32 radii (the target's is 7).
    - `colours`: `(N, 26, 3)` uint8 colours (the target's is red).
    - `visible_pixels`: `(N, T)` int32 count of pixels exactly (255, 0, 0).
    - `seed`, `fold`: what generated it.
    """

    disk_positions: np.ndarray
    disk_velocities: np.ndarray
    radii: np.ndarray
    colours: np.ndarray
    visible_pixels: np.ndarray
    seed: int
    fold: int

    @property
    def num_sequences(self) -> int:
        return self.disk_positions.shape[0]

    @property
    def num_frames(self) -> int:
        return self.disk_positions.shape[1]

    @property
    def positions(self) -> np.ndarray:
        """`(N, T, 2)` target positions."""
        return self.disk_positions[:, :, 0]

    @property
    def velocities(self) -> np.ndarray:
        """`(N, T, 2)` target velocities."""
        return self.disk_velocities[:, :, 0]

    @property
    def states(self) -> np.ndarray:
        """`(N, T, 4)` target states `[px, py, vx, vy]`."""
        return np.concatenate([self.positions, self.velocities], axis=-1)

    def images(self, seqs, frames=None) -> np.ndarray:
        """Render images (uint8) for sequence indices `seqs`.

        With `frames=None`: shape `(len(seqs), T, 120, 120, 3)`; with an index
        array `frames` of the same length as `seqs`: one image per pair,
        shape `(len(seqs), 120, 120, 3)`.
        """
        seqs = np.asarray(seqs)
        if frames is None:
            n, t = seqs.shape[0], self.num_frames
            pos = self.disk_positions[seqs].reshape(n * t, -1, 2)
            radii = np.repeat(self.radii[seqs], t, axis=0)
            colours = np.repeat(self.colours[seqs], t, axis=0)
            return render(pos, radii, colours).reshape(n, t, IMAGE_SIZE, IMAGE_SIZE, 3)
        frames = np.asarray(frames)
        if frames.shape != seqs.shape:
            raise ValueError(
                f"frames {frames.shape} must have the shape of seqs {seqs.shape}"
            )
        return render(
            self.disk_positions[seqs, frames], self.radii[seqs], self.colours[seqs]
        )

    def subset(self, seqs) -> "DiskFold":
        """The sequences `seqs` of this fold, as a new `DiskFold`."""
        seqs = np.asarray(seqs)
        return dataclasses.replace(
            self,
            disk_positions=self.disk_positions[seqs],
            disk_velocities=self.disk_velocities[seqs],
            radii=self.radii[seqs],
            colours=self.colours[seqs],
            visible_pixels=self.visible_pixels[seqs],
        )


def _disk_offsets(radius: int) -> tuple[np.ndarray, np.ndarray]:
    r = np.arange(-radius, radius + 1)
    dy, dx = np.meshgrid(r, r, indexing="ij")
    inside = dx * dx + dy * dy <= radius * radius
    return dy[inside], dx[inside]


_OFFSETS = {
    r: _disk_offsets(r) for r in range(min(DISTRACTOR_RADII[0], TARGET_RADIUS), 10)
}


def render(positions: np.ndarray, radii: np.ndarray, colours: np.ndarray) -> np.ndarray:
    """Draw filled disks on black 120 x 120 images, in disk order.

    A pixel (row i, column j) belongs to a disk with integer centre
    `(cx, cy) = round(p) + 60` when `(j − cx)² + (i − cy)² ≤ r²`.

    **Arguments:**

    - `positions`: `(B, K, 2)` disk positions (x right, y down, origin at the
        image centre).
    - `radii`: `(B, K)` integer radii.
    - `colours`: `(B, K, 3)` uint8 colours.

    **Returns:** `(B, 120, 120, 3)` uint8 images.
    """
    b, k, _ = positions.shape
    images = np.zeros((b, IMAGE_SIZE, IMAGE_SIZE, 3), dtype=np.uint8)
    centres = np.rint(positions).astype(np.int64) + IMAGE_SIZE // 2
    batch = np.arange(b)
    for d in range(k):
        # Group images by this disk's radius, so each group is one scatter.
        for r in np.unique(radii[:, d]):
            sel = batch[radii[:, d] == r]
            dy, dx = _OFFSETS[int(r)]
            rows = centres[sel, d, 1][:, None] + dy[None]
            cols = centres[sel, d, 0][:, None] + dx[None]
            ok = (rows >= 0) & (rows < IMAGE_SIZE) & (cols >= 0) & (cols < IMAGE_SIZE)
            img_idx = np.broadcast_to(sel[:, None], rows.shape)[ok]
            images[img_idx, rows[ok], cols[ok]] = colours[img_idx, d]
    return images


def count_visible(images: np.ndarray) -> np.ndarray:
    """Number of pixels exactly equal to (255, 0, 0) in each image `(..., H, W, 3)`."""
    red = (images[..., 0] == 255) & (images[..., 1] == 0) & (images[..., 2] == 0)
    return red.sum(axis=(-1, -2)).astype(np.int32)


def _simulate_sequence(rng: np.random.Generator, num_frames: int):
    k = NUM_DISTRACTORS + 1
    p = rng.uniform(-INITIAL_POSITION_RANGE, INITIAL_POSITION_RANGE, size=(k, 2))
    v = rng.normal(0.0, INITIAL_VELOCITY_STD, size=(k, 2))
    radii = np.empty(k, dtype=np.int32)
    radii[0] = TARGET_RADIUS
    radii[1:] = rng.integers(
        DISTRACTOR_RADII[0], DISTRACTOR_RADII[1] + 1, size=NUM_DISTRACTORS
    )
    colours = np.empty((k, 3), dtype=np.uint8)
    colours[0] = TARGET_COLOUR
    colours[1:] = DISTRACTOR_COLOURS[
        rng.integers(0, len(DISTRACTOR_COLOURS), size=NUM_DISTRACTORS)
    ]
    wp = rng.normal(0.0, POSITION_NOISE_STD, size=(num_frames - 1, k, 2))
    wv = rng.normal(0.0, VELOCITY_NOISE_STD, size=(num_frames - 1, k, 2))
    return p, v, radii, colours, wp, wv


def generate_fold(
    seed: int,
    fold: int,
    num_sequences: int = SEQUENCES_PER_FOLD,
    num_frames: int = FRAMES_PER_SEQUENCE,
    render_chunk: int = 2048,
) -> DiskFold:
    """Generate fold `fold` of the data set (deterministic in `seed`, `fold`).

    **Arguments:**

    - `seed`: data-set seed.
    - `fold`: fold index (any non-negative integer).
    - `num_sequences`: sequences to generate; sequence `i` is the same for
        every `num_sequences > i`.
    - `num_frames`: frames per sequence (20 in the paper).
    - `render_chunk`: images rendered at once to count visible pixels
        (bounds memory to `render_chunk × 43 kB`).

    **Returns:** a [`DiskFold`][experiments.disk_tracking.data.DiskFold].
    """
    if num_sequences < 1 or num_frames < 1:
        raise ValueError(
            f"need num_sequences >= 1 and num_frames >= 1, got {num_sequences}, "
            f"{num_frames}"
        )
    root = np.random.SeedSequence([seed, fold])
    children = root.spawn(num_sequences)
    parts = [_simulate_sequence(np.random.default_rng(c), num_frames) for c in children]
    p, v, radii, colours, wp, wv = (np.stack(x) for x in zip(*parts))
    # p, v: (N, K, 2); wp, wv: (N, T-1, K, 2). Simulate all sequences at once.
    pos = np.empty((num_sequences, num_frames) + p.shape[1:], dtype=np.float64)
    vel = np.empty_like(pos)
    pos[:, 0], vel[:, 0] = p, v
    for t in range(num_frames - 1):
        pos[:, t + 1], vel[:, t + 1] = dynamics_step(
            pos[:, t], vel[:, t], wp[:, t], wv[:, t]
        )
    fold_data = DiskFold(
        disk_positions=pos.astype(np.float32),
        disk_velocities=vel.astype(np.float32),
        radii=radii,
        colours=colours,
        visible_pixels=np.zeros((num_sequences, num_frames), dtype=np.int32),
        seed=seed,
        fold=fold,
    )
    # Visible pixels: render (bounded chunks) and count exact red.
    flat_seq, flat_frame = np.divmod(np.arange(num_sequences * num_frames), num_frames)
    counts = np.empty(num_sequences * num_frames, dtype=np.int32)
    for start in range(0, counts.shape[0], render_chunk):
        sl = slice(start, start + render_chunk)
        counts[sl] = count_visible(fold_data.images(flat_seq[sl], flat_frame[sl]))
    return dataclasses.replace(
        fold_data, visible_pixels=counts.reshape(num_sequences, num_frames)
    )


def load_fold(
    seed: int,
    fold: int,
    num_sequences: int = SEQUENCES_PER_FOLD,
    num_frames: int = FRAMES_PER_SEQUENCE,
    cache_dir: Path | None = None,
    verbose: bool = False,
) -> DiskFold:
    """[`generate_fold`][experiments.disk_tracking.data.generate_fold],
    optionally cached as `.npz` under `cache_dir`.

    The cache holds states and counts only (a few MB per fold); images are
    always rendered on demand. Never point `cache_dir` into the repository.
    """
    path = None
    if cache_dir is not None:
        cache_dir = Path(cache_dir)
        path = cache_dir / (
            f"disk_seed{seed}_fold{fold}_n{num_sequences}_t{num_frames}.npz"
        )
        n, t = num_sequences, num_frames
        shapes = {"disk_positions": (n, t), "disk_velocities": (n, t)}
        shapes |= {"radii": (n,), "colours": (n,), "visible_pixels": (n, t)}
        z = load_cache(path, _FOLD_KEYS, leading_axes(shapes))
        if z is not None:
            return DiskFold(**z, seed=seed, fold=fold)
    t0 = time.perf_counter()
    data = generate_fold(seed, fold, num_sequences, num_frames)
    if verbose:
        print(
            f"generated fold {fold} ({num_sequences} sequences x {num_frames} "
            f"frames) in {time.perf_counter() - t0:.1f} s"
        )
    if path is not None:
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_suffix(".tmp.npz")
        np.savez(
            tmp,
            disk_positions=data.disk_positions,
            disk_velocities=data.disk_velocities,
            radii=data.radii,
            colours=data.colours,
            visible_pixels=data.visible_pixels,
        )
        tmp.replace(path)
    return data


_FOLD_KEYS = ("disk_positions", "disk_velocities", "radii", "colours", "visible_pixels")


def fold_images(fold: DiskFold, cache_dir: Path | None = None) -> np.ndarray:
    """Every image of `fold`, `(N, T, 120, 120, 3)` uint8, rendered once.

    With `cache_dir`, the images are rendered into a raw file there on the
    first call (written to a temporary name, then renamed, so a killed run
    never leaves a partial cache) and memory-mapped read-only afterwards; a
    fold of 505 sequences is 436 MB. Without it they are rendered in memory.
    """
    shape = (fold.num_sequences, fold.num_frames, IMAGE_SIZE, IMAGE_SIZE, 3)
    path = None
    if cache_dir is not None:
        path = Path(cache_dir) / (
            f"disk_seed{fold.seed}_fold{fold.fold}_n{shape[0]}_t{shape[1]}.u8"
        )
        if path.exists() and path.stat().st_size == int(np.prod(shape)):
            return np.memmap(path, dtype=np.uint8, mode="r", shape=shape)
    images = np.empty(shape, dtype=np.uint8)
    for start in range(0, shape[0], 64):
        seqs = np.arange(start, min(start + 64, shape[0]))
        images[seqs] = fold.images(seqs)
    if path is not None:
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_suffix(".tmp")
        images.tofile(tmp)
        tmp.replace(path)
        return np.memmap(path, dtype=np.uint8, mode="r", shape=shape)
    return images


def concatenate(folds: list[DiskFold]) -> DiskFold:
    """Concatenate folds along the sequence axis (`seed`/`fold` of the first)."""
    if not folds:
        raise ValueError("concatenate needs at least one fold")
    return dataclasses.replace(
        folds[0],
        disk_positions=np.concatenate([f.disk_positions for f in folds]),
        disk_velocities=np.concatenate([f.disk_velocities for f in folds]),
        radii=np.concatenate([f.radii for f in folds]),
        colours=np.concatenate([f.colours for f in folds]),
        visible_pixels=np.concatenate([f.visible_pixels for f in folds]),
    )
