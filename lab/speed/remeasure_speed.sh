#!/usr/bin/env bash
# Re-measure the speed figures of docs/benchmarks.md "Issue 16" side by side with a baseline
# commit, on whatever machine this runs (quiet is best: note the load it prints).
#
#   lab/scripts/remeasure_speed.sh [BASE_COMMIT] [SIZES] [RUNS]
#   lab/scripts/remeasure_speed.sh 4383dd1 1,2,4,8,12 7,5,3,1,1
#
# 1. a git worktree of BASE_COMMIT (default 4383dd1, the main before issue 16) in a temp folder;
# 2. `python -m lab.bench scale`: every size's survey once, then `graphslam survey` alternating
#    between this checkout and the baseline (baseline only up to size 4: it needs ~1 min there
#    and ~3 min at size 12), stage medians, peak RSS, growth exponent, the markdown table;
# 3. `python -m lab.bench accuracy paper --seeds 0-2` for both (landmark errors: same minimum?);
# 4. lab/scripts/bench_linear_solvers.py at sizes 1 and 4 (the solver comparison).
# Bytecode of both trees is compiled before the runs (see below).
# Long runs are niced. Output: stdout (JSON lines and tables) and OUT_DIR (default a temp folder).
set -euo pipefail
BASE=${1:-4383dd1}
SIZES=${2:-1,2,4,8,12}
RUNS=${3:-7,5,3,1,1}
HERE=$(cd "$(dirname "$0")/../.." && pwd)
PY=${PYTHON:-"$HERE/.venv/bin/python"}
OUT_DIR=${OUT_DIR:-$(mktemp -d /tmp/graphslam-remeasure-XXXX)}
WT="$OUT_DIR/base"
git -C "$HERE" worktree add --detach "$WT" "$BASE" >/dev/null
trap 'git -C "$HERE" worktree remove --force "$WT"' EXIT
# Both trees' bytecode compiled first, as `pip install` does (an editable install writes it on
# the first import, unless PYTHONDONTWRITEBYTECODE is set: then every run would compile every
# graphslam module again, ~0.1 s, a cost no installed user pays).
"$PY" -m compileall -q "$HERE/graphslam" "$WT/graphslam" >/dev/null
echo "load before: $(cat /proc/loadavg)"
nice -n 10 "$PY" -m python -m lab.bench scale paper --sizes "$SIZES" --runs "$RUNS" --baseline "$WT" \
    --baseline-max-size 4 | tee "$OUT_DIR/scale.txt"
echo "accuracy (this checkout):"
nice -n 10 "$PY" -m python -m lab.bench accuracy paper --seeds 0-2 | tee "$OUT_DIR/accuracy-new.txt"
echo "accuracy (baseline $BASE):"
PYTHONPATH="$WT" nice -n 10 "$PY" -P -m python -m lab.bench accuracy paper --seeds 0-2 | tee "$OUT_DIR/accuracy-base.txt"
nice -n 10 "$PY" "$HERE/scripts/bench_linear_solvers.py" --sizes 1,4 | tee "$OUT_DIR/linear.txt"
echo "load after: $(cat /proc/loadavg)"
echo "outputs in $OUT_DIR"
