#!/usr/bin/env bash
# The small-graph benchmark on two source trees, alternating processes:
#   bash benchmarks/run_small_graph_ab.sh BEFORE_TREE AFTER_TREE LABEL [ROUNDS]
# writes benchmarks/results/small_graph_LABEL_{before,after}_{1..ROUNDS}.json.
set -euo pipefail
before=$(cd "$1" && pwd); after=$(cd "$2" && pwd); label=$3; rounds=${4:-2}
out=$(cd "$(dirname "$0")" && pwd)/results
for r in $(seq 1 "$rounds"); do
  for side in before after; do
    tree=$before; [ "$side" = after ] && tree=$after
    echo "== round $r $side ($tree)"
    PYTHONPATH="$tree" python "$tree/benchmarks/small_graph.py" --repeats 300 \
      --json "$out/small_graph_${label}_${side}_${r}.json" | grep -E "^\| (api|jit|gtsam)"
  done
done
