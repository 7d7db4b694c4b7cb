#!/bin/bash
# The realism cross-check of docs/learnability.md (issue 29, deliverable 5): train the detector on data made by
# one version of cosim's world and evaluate it on data made by another, both ways, and report the gap.
#
#   benchmarks/learn_crosscheck.sh OLD_COMMIT NEW_COMMIT OUT [COUNT]
#
# OLD_COMMIT: the world as it was (e.g. the commit before the procedural assets of issue 28 landed);
# NEW_COMMIT: the world with them (e.g. main). Each commit gets a git worktree and a venv under OUT/trees,
# generates the same sweep (sweeps/learnability.yaml of this checkout, COUNT episodes, default 24) into
# OUT/data/{old,new}, and trains one early-fusion model (all agents) per world with this checkout's
# `cosim learn` (the [learn] extra). The four evaluations (old->old, old->new, new->new, new->old) land in
# OUT/eval/*; their overall tables are printed at the end. Needs a few CPU hours on 2 cores.
set -euo pipefail
OLD=$1; NEW=$2; OUT=$(realpath -m "$3"); COUNT=${4:-24}
HERE=$(cd "$(dirname "$0")/.." && pwd)
COSIM="$HERE/.venv/bin/cosim"
STEPS=${STEPS:-2000}
mkdir -p "$OUT/trees" "$OUT/data" "$OUT/runs" "$OUT/eval"
for side in old new; do
  commit=$OLD; [ "$side" = new ] && commit=$NEW
  tree="$OUT/trees/$side"
  [ -d "$tree" ] || git -C "$HERE" worktree add --detach "$tree" "$commit"
  make -C "$tree" .venv/.cosim-installed
  nice -n 10 "$tree/.venv/bin/cosim" batch "$HERE/sweeps/learnability.yaml" --out "$OUT/data/$side" \
    --count "$COUNT" --workers 2 -q
  nice -n 10 "$COSIM" learn train "$OUT/data/$side" --out "$OUT/runs/$side" --fusion early --agents all \
    --steps "$STEPS" --keep-every 250 --threads 2 -q
done
for model in old new; do
  for data in old new; do
    "$COSIM" learn predict "$OUT/runs/$model" "$OUT/data/$data" --split test --out "$OUT/eval/$model-on-$data.jsonl" -q
    "$COSIM" eval --gt "$OUT/data/$data" --split test --pred "$OUT/eval/$model-on-$data.jsonl" --visible-only \
      --out "$OUT/eval/$model-on-$data" | sed -n '1,6p' | sed "s/^/[$model model on $data data] /"
  done
done
