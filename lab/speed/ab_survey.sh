#!/usr/bin/env bash
# Side-by-side wall time of `graphslam survey` for two variants, alternating run by run (so that the
# machine's drift hits both), medians at the end. A variant is a source tree (run with PYTHONPATH,
# `python -P`) and optional extra survey arguments.
#
#   lab/speed/ab_survey.sh DATA RUNS SRC_A SRC_B ["ARGS_A"] ["ARGS_B"]
#   lab/speed/ab_survey.sh /tmp/p1 15 /work/wt/old /work/main                 # two commits
#   lab/speed/ab_survey.sh /tmp/p4 3 . . "--set optimizer.blas_threads=1" "--set optimizer.blas_threads=0"
#
# DATA: a folder of recordings (e.g. `graphslam simulate paper --seed 0 --out /tmp/p1`).
set -euo pipefail
DATA=$1; RUNS=$2; SRC_A=$(cd "$3" && pwd); SRC_B=$(cd "$4" && pwd); ARGS_A=${5:-}; ARGS_B=${6:-}
HERE=$(cd "$(dirname "$0")/../.." && pwd)
PY=${PYTHON:-"$HERE/.venv/bin/python"}
OUT=$(mktemp -d /tmp/graphslam-ab-XXXX)
trap 'rm -rf "$OUT"' EXIT
echo "load before: $(cat /proc/loadavg)"
for i in $(seq "$RUNS"); do
  for side in A B; do
    src=SRC_$side; args=ARGS_$side
    # shellcheck disable=SC2086
    ( cd /tmp && /usr/bin/time -a -o "$OUT/$side" -f "%e" env PYTHONPATH="${!src}" "$PY" -P -m graphslam survey \
        "$DATA" --out "$OUT/out_$side" --no-progress ${!args} >/dev/null )
  done
done
for side in A B; do
  src=SRC_$side; args=ARGS_$side
  sort -n "$OUT/$side" | awk -v s="$side" -v src="${!src}" -v a="${!args}" \
    '{v[NR]=$1} END {printf "%s (%s %s): median %.2f s of %d runs; sorted:", s, src, a, v[int((NR+1)/2)], NR;
                     for (i=1;i<=NR;i++) printf " %.2f", v[i]; print ""}'
done
echo "load after: $(cat /proc/loadavg)"
