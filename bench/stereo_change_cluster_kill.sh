#!/bin/bash
# Stereo -> change -> products on a generated scene three ways, with 256-cell tiles:
#   1. LocalCluster (the default scheduler): the reference;
#   2. the same command against a `dask scheduler` + 2 `dask worker` processes on loopback;
#   3. SIGKILL of the whole process tree once KILL_AT tile results are journalled, then the same command again.
# Then compare the products of 2 and 3 with 1 (bench_big_stereo_change.py same).
#
#   bash bench/stereo_change_cluster_kill.sh SCENE MODEL OUT [KILL_AT]
#   e.g. bash bench/stereo_change_cluster_kill.sh /work/big/st1250 /work/big/calib1k_model/model.json /work/big/sched 30
# (1 250² cells: 2 pairs × 25 stereo tiles; 30 = inside the second pair's stereo.)
set -u
SCENE=$1; MODEL=$2; D=$3; KILL_AT=${4:-30}
cd "$(dirname "$0")/.."
PY=${PY:-.venv/bin/python}; DASK=${DASK:-$(dirname "$PY")/dask}
B="bench/bench_big_stereo_change.py"; ARGS="--model $MODEL --tile-size 256"
mkdir -p "$D"; L="$D/log.txt"
echo "local $(date +%T)" >> "$L"
[ -f "$D/local.json" ] || $PY $B run "$SCENE" "$D/local" $ARGS --json "$D/local.json" > "$D/local.out" 2>&1
echo "address $(date +%T)" >> "$L"
if [ ! -f "$D/addr.json" ]; then
  $DASK scheduler --host 127.0.0.1 --port 8799 --no-dashboard > "$D/sched.log" 2>&1 & S=$!
  sleep 5
  for i in 1 2; do
    $DASK worker tcp://127.0.0.1:8799 --nworkers 1 --nthreads 1 --memory-limit 4GB --no-dashboard > "$D/worker$i.log" 2>&1 &
  done
  sleep 8
  $PY $B run "$SCENE" "$D/addr" $ARGS --scheduler tcp://127.0.0.1:8799 --json "$D/addr.json" > "$D/addr.out" 2>&1
  pkill -f "dask worker tcp://127.0.0.1:8799"; kill $S
fi
echo "kill $(date +%T)" >> "$L"
if [ ! -f "$D/killed.json" ]; then
  setsid $PY $B run "$SCENE" "$D/killed" $ARGS --json "$D/killed.json" > "$D/killed1.out" 2>&1 & P=$!
  while kill -0 $P 2>/dev/null; do
    n=$(find "$D/killed" -name '*.done.pkl' 2>/dev/null | wc -l)
    if [ "$n" -ge "$KILL_AT" ]; then echo "SIGKILL at $n journalled tiles $(date +%T)" >> "$L"; kill -9 -- -$P; break; fi
    sleep 0.5
  done
  sleep 3
  echo "after the kill: products visible: $(find "$D/killed" -name '*.tif' -not -path '*/.geocd-work/*' | tr '\n' ' ');" \
       "partial files outside the work folder: $(find "$D/killed" -name '*.part*' -not -path '*/.geocd-work/*' | wc -l)" >> "$L"
  $PY $B run "$SCENE" "$D/killed" $ARGS --json "$D/killed.json" > "$D/killed2.out" 2>&1
fi
echo "done $(date +%T)" >> "$L"
for r in addr killed; do $PY $B same "$D/local" "$D/$r" --json "$D/same_$r.json" | head -2; done
