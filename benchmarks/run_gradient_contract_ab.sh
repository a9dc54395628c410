#!/usr/bin/env bash
# Issue 32's speed check: the SE(2)+velocity chain at T = 1e4, the T = 200
# training step (K = 3, unrolled and truncated) and the 5-pose SE(2) first
# call, on two source trees, alternating processes, and XLA's flop and byte
# counts of the chain solve and the training step (benchmarks/xla_cost.py):
#   bash benchmarks/run_gradient_contract_ab.sh BEFORE_TREE AFTER_TREE [ROUNDS]
# writes benchmarks/results/gradient_contract_ab/*.json and prints the
# after/before tables (benchmarks/before_after.py).
set -euo pipefail
before=$(cd "$1" && pwd); after=$(cd "$2" && pwd); rounds=${3:-2}
here=$(cd "$(dirname "$0")" && pwd)
out=$here/results/gradient_contract_ab
mkdir -p "$out"
for r in $(seq 1 "$rounds"); do
  for side in before after; do
    tree=$before; [ "$side" = after ] && tree=$after
    echo "== round $r $side ($tree)"
    PYTHONPATH="$tree" python "$tree/benchmarks/chain.py" --problems se2vel \
      --sizes 10000 --solvers BlockTridiagonal --json "$out/chain_${side}_$r.json" \
      > /dev/null
    PYTHONPATH="$tree" python "$tree/benchmarks/train_step.py" --sizes 200 \
      --steps 3 --solvers BlockTridiagonal --adjoints unrolled "truncated(k=1)" \
      --no-reference --json "$out/train_step_${side}_$r.json" > /dev/null
  done
done
for side in before after; do
  tree=$before; [ "$side" = after ] && tree=$after
  PYTHONPATH="$tree" python "$here/xla_cost.py" "$tree" --json "$out/xla_cost_$side.json"
done
python "$here/first_call.py" --cases pose2 --trees "before=$before" \
  "after=$after" --repeats "$rounds" --json "$out/first_call.json"
for r in $(seq 1 "$rounds"); do
  for w in chain train_step; do
    python "$here/before_after.py" "$out/${w}_before_$r.json" "$out/${w}_after_$r.json"
  done
done
