#!/usr/bin/env bash
# CPU-seconds of `cosim learn train` per 1,000 steps and per 1,000 training samples, before (the pipeline of
# BEFORE_REF: every step reads its samples from MCAP, batch 2) and after (samples from a `cosim learn cache`
# folder, batch 8, in the training process and with WORKERS worker processes), on the same data, in one run.
# User + system CPU of the whole process tree (/usr/bin/time), for STEPS steps with no validation.
#
#   benchmarks/learn_speed.sh out/learn16 [FUSION AGENTS]       # e.g. early all (default none ego)
#
# Env: STEPS (default 40), EVERY (training ticks 0, EVERY, ...: default 2), WORKERS (default 2), BEFORE_REF (default 73e7c94, main before issue 35),
# CACHE (default out/learn_speed/cache: made first if missing, its CPU reported), OUT (default out/learn_speed).
set -euo pipefail
DATA=${1:?usage: benchmarks/learn_speed.sh BATCH_FOLDER [FUSION AGENTS]}
FUSION=${2:-none}
AGENTS=${3:-ego}
STEPS=${STEPS:-40}
WORKERS=${WORKERS:-2}
EVERY=${EVERY:-2}
BEFORE_REF=${BEFORE_REF:-73e7c94}
OUT=${OUT:-out/learn_speed}
CACHE=${CACHE:-$OUT/cache}
REPO=$(cd "$(dirname "$0")/.." && pwd)
PY=${PY:-$REPO/.venv/bin/python}
mkdir -p "$OUT"
OUT=$(cd "$OUT" && pwd)
DATA=$(cd "$DATA" && pwd)
case $CACHE in /*) ;; *) CACHE=$PWD/$CACHE ;; esac
BEFORE=$OUT/before_src
if [ ! -d "$BEFORE" ]; then
  mkdir -p "$BEFORE"
  git -C "$REPO" archive "$BEFORE_REF" cosim | tar -x -C "$BEFORE"
fi

cpu() {  # label, then the command: prints "label CPU-s wall-s"
  local label=$1; shift
  /usr/bin/time -f "%U %S %e" -o "$OUT/time.txt" "$@" > "$OUT/$label.log" 2>&1
  read -r user sys wall < "$OUT/time.txt"
  echo "$label $(echo "$user + $sys" | bc) $wall"
}

if [ ! -f "$CACHE/cache.json" ]; then
  cpu cache "$PY" -m cosim.cli learn cache "$DATA" --out "$CACHE" --every "$EVERY" -q
fi
rm -rf "$OUT/run_before" "$OUT/run_after0" "$OUT/run_afterw"
# the old tree's cosim.learn shadows the installed one (the rest of cosim is the same package)
before=$(cd "$BEFORE" && PYTHONPATH="$BEFORE" cpu before "$PY" -c "
import sys, cosim.learn.train as t
assert t.__file__.startswith('$BEFORE'), t.__file__
from cosim.cli import main
sys.exit(main(['learn', 'train', '$DATA', '--out', '$OUT/run_before', '--fusion', '$FUSION',
               '--agents', '$AGENTS', '--steps', '$STEPS', '--every', '$EVERY', '--batch-size', '2', '--threads', '1', '--no-val', '-q']))")
after0=$(cpu after0 "$PY" -m cosim.cli learn train "$DATA" --out "$OUT/run_after0" --fusion "$FUSION" --agents "$AGENTS" \
  --steps "$STEPS" --every "$EVERY" --batch-size 8 --threads 1 --no-val --cache "$CACHE" -q)
afterw=$(cpu afterw "$PY" -m cosim.cli learn train "$DATA" --out "$OUT/run_afterw" --fusion "$FUSION" --agents "$AGENTS" \
  --steps "$STEPS" --every "$EVERY" --batch-size 8 --threads 1 --no-val --cache "$CACHE" --workers "$WORKERS" -q)
echo "fusion $FUSION, agents $AGENTS, $STEPS steps each"
printf '%-34s %10s %10s %14s %16s\n' run CPU-s wall-s "CPU-s/1k steps" "CPU-s/1k samples"
for row in "before(batch-2,MCAP) $before 2" "after(batch-8,cache) $after0 8" "after(batch-8,cache,$WORKERS-workers) $afterw 8"; do
  set -- $row
  printf '%-34s %10s %10s %14.0f %16.0f\n' "$1" "$3" "$4" "$(echo "$3 * 1000 / $STEPS" | bc -l)" \
    "$(echo "$3 * 1000 / ($STEPS * $5)" | bc -l)"
done
