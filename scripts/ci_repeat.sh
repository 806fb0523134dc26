#!/usr/bin/env bash
# Repeat CI from fresh clones: does the suite pass every time, also with the other core busy?
#
#   scripts/ci_repeat.sh [RUNS] [LOADED]      # default 10 runs, the last 5 of them loaded
#
# Each run clones the current commit into a temporary directory beside this checkout (so that
# ../shared is found as in CI), runs `CI=true bash .ci/run` there and records pass/fail and time.
# A loaded run starts one CPU-bound process (a busy loop) for the whole run. The virtualenv is
# reused between runs through a symlink to this checkout's .venv (installing is not what is tested;
# `make test` still checks it is complete). Results go to stdout and to ci_repeat.log.
# CI_REPEAT_LOAD=CMD makes the load a command of your own (e.g. a benchmark that resumes), run in
# its own process group and stopped at the end of each loaded run; a busy loop follows it if it
# ends early. ../shared is linked beside each clone when it is beside this checkout, as in CI.
set -uo pipefail
cd "$(dirname "$0")/.."
RUNS=${1:-10}
LOADED=${2:-5}
HERE=$(pwd)
COMMIT=$(git rev-parse HEAD)
LOG="$HERE/ci_repeat.log"
echo "commit $COMMIT, $RUNS runs, the last $LOADED with a CPU-bound process on another core" | tee "$LOG"
# CI_REPEAT_NOTE: what else ran on the machine meanwhile (e.g. benchmarks), recorded with the results
[ -n "${CI_REPEAT_NOTE:-}" ] && echo "note: $CI_REPEAT_NOTE" | tee -a "$LOG"
pass=0
for i in $(seq 1 "$RUNS"); do
  dir=$(mktemp -d "$(dirname "$HERE")/ci-repeat-XXXX")
  git clone -q "$HERE" "$dir/repo" && git -C "$dir/repo" checkout -q "$COMMIT"
  # as in CI, ../shared beside the clone: the tests that need the dataset run instead of skipping
  [ -d "$(dirname "$HERE")/shared" ] && ln -s "$(dirname "$HERE")/shared" "$dir/shared"
  if [ -d "$HERE/.venv" ]; then
    ln -s "$HERE/.venv" "$dir/repo/.venv"
    # older than the install stamp: the shared venv is not reinstalled (editable) from a clone
    # that is deleted after the run
    touch -d '2000-01-01' "$dir/repo/pyproject.toml" "$dir/repo/Makefile"
  fi
  hog=""
  if [ "$i" -gt $((RUNS - LOADED)) ]; then
    setsid bash -c "${CI_REPEAT_LOAD:-true}; exec python3 -c 'while True: pass'" & hog=$!
  fi
  start=$(date +%s)
  if (cd "$dir/repo" && CI=true bash .ci/run > "$dir/out.txt" 2>&1); then
    result=pass; pass=$((pass + 1))
  else
    result=FAIL; cp "$dir/out.txt" "$HERE/ci_repeat.fail.$i.txt"
  fi
  [ -n "$hog" ] && kill -- -"$hog"
  echo "run $i: $result in $(( $(date +%s) - start )) s, started $(date -d "@$start" +%H:%M)$([ -n "$hog" ] && echo ' (loaded)')" | tee -a "$LOG"
  rm -rf "$dir"
done
echo "$pass/$RUNS passed" | tee -a "$LOG"
[ "$pass" -eq "$RUNS" ]
