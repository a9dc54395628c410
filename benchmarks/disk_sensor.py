"""Cost of the disk-tracking virtual sensors: forward and forward + backward.

The paper's CNN (`models.VirtualSensor`, four 3 x 3 convolutions of 32
channels at 120 x 120) against ours (`models.HeatmapSensor`, a heat map at
half resolution and a soft-argmax), in one process, jitted, float32, on a
batch of rendered disk images; plus the cost of rendering those images. A
training step of the sensor is one forward + backward pass of a batch.

    cd benchmarks && python disk_sensor.py --json results/disk_sensor.json
    cd benchmarks && python disk_sensor.py --quick
"""

import argparse
import sys
import time
from pathlib import Path

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from _common import markdown_table, time_fn, write_json


sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "examples"))
from disk_tracking import data as D, models as M  # noqa: E402


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--batch", type=int, default=32)
    parser.add_argument("--repeats", type=int, default=9)
    parser.add_argument("--quick", action="store_true", help="batch 8, 3 repeats")
    parser.add_argument("--json", default=None)
    args = parser.parse_args(argv)
    if args.quick:
        args.batch, args.repeats = 8, 3
    fold = D.generate_fold(0, 0, num_sequences=max(args.batch // 20, 1) + 1)
    seqs = np.arange(args.batch) % fold.num_sequences
    frames = np.arange(args.batch) % fold.num_frames
    t0 = time.perf_counter()
    for _ in range(args.repeats):
        images = fold.images(seqs, frames)
    render_ms = 1e3 * (time.perf_counter() - t0) / args.repeats / args.batch
    x = jnp.asarray(images)
    y = jnp.asarray(fold.positions[seqs, frames])
    key = jax.random.key(0)
    sensors = {
        "paper CNN (VirtualSensor)": M.VirtualSensor(key),
        "heat map (HeatmapSensor, 16 ch)": M.HeatmapSensor(key, channels=16),
    }

    @eqx.filter_jit
    def forward(sensor, x):
        return jax.vmap(sensor)(x)

    @eqx.filter_jit
    def forward_backward(sensor, x, y):
        return eqx.filter_grad(lambda s: jnp.mean((jax.vmap(s)(x) - y) ** 2))(sensor)

    rows = []
    for name, sensor in sensors.items():
        params = sum(p.size for p in jax.tree.leaves(eqx.filter(sensor, eqx.is_array)))
        row = {"sensor": name, "params": int(params), "batch": args.batch}
        first, med, _ = time_fn(forward, sensor, x, repeats=args.repeats)
        row["forward_ms_per_image"] = 1e3 * med / args.batch
        first_b, med_b, _ = time_fn(
            forward_backward, sensor, x, y, repeats=args.repeats
        )
        row["fwd_bwd_ms_per_image"] = 1e3 * med_b / args.batch
        row["compile_s"] = first_b - med_b
        row["render_ms_per_image"] = render_ms
        rows.append(row)
        print(
            f"{name}: forward {row['forward_ms_per_image']:.2f} ms/image, forward + "
            f"backward {row['fwd_bwd_ms_per_image']:.2f} ms/image",
            flush=True,
        )
    ratio = rows[0]["fwd_bwd_ms_per_image"] / rows[1]["fwd_bwd_ms_per_image"]
    for r in rows:
        r["benchmark"] = "disk_sensor"
        r["median_s"] = r["fwd_bwd_ms_per_image"] * args.batch / 1e3
    print(f"rendering: {render_ms:.3f} ms/image; paper / heat map = {ratio:.1f}x")
    cols = ["sensor", "params", "batch", "forward_ms_per_image"]
    cols += ["fwd_bwd_ms_per_image", "render_ms_per_image", "compile_s"]
    print(markdown_table(rows, cols))
    if args.json:
        write_json(args.json, rows, {"argv": argv or sys.argv[1:]})


if __name__ == "__main__":
    main()
