#!/usr/bin/env bash
# A/B of `mam run` on the GPU machine: the tree at .old/ (a `git archive` of another commit, carried) against
# this checkout, alternating, each e2e window as in gpu.sh step c. Output: $OUT/ab-<side>-<n>.json.
set -u
ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
SITE=/tmp/ab-site
python3 -m pip install -q --no-index --no-deps --target "$SITE" "$ROOT"/benchmarks/wheels/*.whl || exit 1
SECONDS_WINDOW="${SECONDS_WINDOW:-25}"
n=0
for side in ${SIDES:-old new old new}; do
  n=$((n + 1))
  tree="$ROOT"; [ "$side" = old ] && tree="$ROOT/.old"
  (cd "$tree" && PYTHONPATH="$SITE:$tree" PYTHONUNBUFFERED=1 timeout 150 python3 benchmarks/gpu_steps.py e2e \
    --device cuda --seconds "$SECONDS_WINDOW" --work "/tmp/ab-$n" --workers 3 --lag 2 --tag "$side-$n" \
    --start-steps 1000 --compete-every 5000 --eval-episodes 20 --grace 20 --out "$OUT/ab-$side-$n.json")
  python3 -c "import json,sys; d=json.load(open(sys.argv[1])); print(sys.argv[2], {k: d.get(k) for k in ('env_steps_per_s','updates_per_s','learner_wait_share','train_seconds')})" "$OUT/ab-$side-$n.json" "$side-$n"
done
