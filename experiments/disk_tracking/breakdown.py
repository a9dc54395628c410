"""Where a finished fold's errors come from: hidden frames, off-image, worst sequences.

Reloads the trained smoother and bidirectional LSTM of one fold from their
checkpoints (a finished stage only evaluates) and prints, for each, the test
RMSE split by the number of visible target pixels, the hidden frames split
into "target outside the image" and "target occluded inside it", and the
share of the squared error that the worst 1 % / 5 % of sequences carry.

    python -m experiments.disk_tracking.breakdown --fold 1 --work runs/disk
"""

import argparse
from pathlib import Path

import jax
import numpy as np

from . import models as M, protocol as P, train as T


def breakdown(pred: np.ndarray, truth: np.ndarray, visible: np.ndarray) -> dict:
    """Per-coordinate RMSE of `pred` `(N, T, 2)` by visibility, and tail shares."""
    sq = ((pred - truth) ** 2).sum(-1)  # (N, T), squared Euclidean
    out: dict = dict(rmse=float(np.sqrt(sq.mean() / 2)))
    for lo, hi in ((0, 1), (1, 30), (30, 80), (80, None)):
        m = (visible >= lo) if hi is None else (visible >= lo) & (visible < hi)
        out[f"visible[{lo},{hi or ''})"] = dict(
            frames=float(m.mean()),
            rmse=float(np.sqrt(sq[m].mean() / 2)),
            error_share=float(sq[m].sum() / sq.sum()),
        )
    hidden = visible == 0
    outside = (np.abs(truth) > M.VIEW_HALF_WIDTH).any(-1)
    for name, m in (("outside", hidden & outside), ("occluded", hidden & ~outside)):
        out[f"hidden_{name}"] = dict(
            frames_of_hidden=float(m.sum() / max(hidden.sum(), 1)),
            rmse=float(np.sqrt(sq[m].mean() / 2)),
        )
    per_seq = np.sort(sq.mean(1))[::-1]
    for f in (0.01, 0.05):
        k = max(1, int(len(per_seq) * f))
        out[f"worst_{f:.0%}_share"] = float(per_seq[:k].sum() / per_seq.sum())
    return out


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--fold", type=int, required=True)
    p.add_argument("--work", type=Path, default=Path("runs/disk"))
    p.add_argument("--smoother", default="smoother_hetero_surrogate_learndyn")
    a = p.parse_args(argv)
    cfg = T.Config()
    fold_dir = a.work / f"fold_{a.fold}"
    train, val, test = T.make_splits(cfg, a.fold, a.work / "cache")
    for name, split in (("train", train), ("val", val), ("test", test)):
        P.cached_outputs(None, split, cfg, fold_dir / f"sensor_{name}.npz")
    sigma = T.rmse(val.sensor, val.fold.positions)
    _, k_noise, k_lstm = jax.random.split(jax.random.key(cfg.model_seed), 3)
    res = T.train_factor_graph(cfg, a.smoother, train, val, sigma, k_noise, fold_dir)
    steps = cfg.eval_solver_steps
    smoothed = T.predict_split(
        lambda m, b: T.smoothed_positions(m, b, steps),
        res.best_model,
        test.sequences(cfg.dtype),
    )
    lstm = T.train_lstm(cfg, True, train, val, k_lstm, fold_dir, "lstm_bi")
    lstm_pred = T.predict_split(
        T.lstm_positions, lstm.best_model, T._lstm_data(test, cfg.dtype)
    )
    truth, visible = test.fold.positions, test.fold.visible_pixels
    for name, pred in ((a.smoother, smoothed), ("lstm_bi", lstm_pred)):
        print(name)
        for k, v in breakdown(pred, truth, visible).items():
            print(f"  {k}: {v}")


if __name__ == "__main__":
    main()
