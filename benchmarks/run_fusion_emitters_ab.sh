#!/usr/bin/env bash
# Run times under XLA's default and earlier fusion emitters, alternating processes.
cd "$(dirname "$0")/.."
out=${1:-benchmarks/results}
for r in 1 2; do
  for label in default fast; do
    fl=""; [ "$label" = fast ] && fl="--xla_cpu_use_fusion_emitters=false"
    echo "== round $r $label XLA_FLAGS=[$fl]"
    XLA_FLAGS="$fl" python benchmarks/chain.py --solvers BlockTridiagonal --problems se2vel --sizes 10000 \
      --json "$out/fusion_emitters_s19_chain_${label}_${r}.json" | grep -v "^|"
    XLA_FLAGS="$fl" python benchmarks/small_graph.py --repeats 300 \
      --json "$out/fusion_emitters_s19_small_graph_${label}_${r}.json" | grep -E "^\| (api|jit|gtsam)"
  done
done
