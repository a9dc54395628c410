#!/usr/bin/env bash
# Run the disk tracking protocol fold by fold and commit each finished fold.
#
#   bash experiments/disk_tracking/run_protocol.sh [FOLD ...]    # default: 0..9
#
# Each fold is one call of experiments/disk_tracking/__main__.py (resumable: a killed
# fold continues where its checkpoints left it when this script is started
# again; finished folds are skipped). After a fold finishes, its results
# (results/disk/fold_K.json, fold_K.log, sensor_foldK.eqx), the summary, the
# figures and the docs table are committed on the current branch.
set -euo pipefail
cd "$(dirname "$0")/.."
folds=("$@")
if [ ${#folds[@]} -eq 0 ]; then folds=(0 1 2 3 4 5 6 7 8 9); fi
python=${PYTHON:-python}
for k in "${folds[@]}"; do
  if [ -f "results/disk/fold_${k}.json" ]; then
    echo "fold ${k}: already committed or finished, skipped"
    continue
  fi
  "$python" experiments/disk_tracking/__main__.py --folds "$k" --out results/disk \
      --docs docs/tutorial/disk-tracking.md
  git add results/disk docs/tutorial/disk-tracking.md
  minutes=$("$python" -c "import json; print(round(json.load(open('results/disk/fold_${k}.json'))['timings']['total_s'] / 60, 1))")
  git commit -q -m "disk tracking: fold ${k} of the full protocol (${minutes} min on this machine)" \
      -- results/disk docs/tutorial/disk-tracking.md
  echo "fold ${k}: committed"
done
