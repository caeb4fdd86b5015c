#!/usr/bin/env bash
# The whole pipeline at a chosen size, each stage measured: synth (800x800, the real
# topology), convert, split, render, crops, and one training epoch of ds.loader (batch
# 64, two workers, sparse correspondences, the crop store). Prints one table row per
# stage: wall time, CPU time (user + system, the stage's children included), peak
# memory (the largest resident set of one of the stage's processes: for the loader,
# the main process or a worker, whichever is larger), disk written (the growth
# of the run's folder) and open files (the most descriptors held at once by the
# stage's processes, sampled every 0.5 s).
#
#   deploy/scale-run.sh SAMPLES [WORKDIR]
#
#   SAMPLES        samples to synthesise: 180 images a subject, so 90,000 is 500
#                  subjects (the release's count); a multiple of 180 is exact
#   WORKDIR        where the run's data go (default /tmp/arkit-scale-SAMPLES); every
#                  stage's output stays there until you delete it
#
# Environment:
#   ARKIT_TOOL     the binary (default target/release/arkit-tool)
#   RESOURCES      the release's resource folder (default ../shared/arkitface-resources)
#   PYTHON         a Python with arkit_tool importable and torch (default python3);
#                  the loader stage is skipped, and says so, without them
#   STAGES         the stages to run, in order (default: all six); a later stage reads
#                  what the earlier ones left in WORKDIR, so a run can be resumed
#   TABLE          also append the rows to this file (tab-separated)
#
# Needs GNU time (/usr/bin/time). The table's CPU time over wall time is the stage's
# parallelism; on a machine shared with other work, wall time is the figure to distrust.
set -euo pipefail

N=${1:?usage: deploy/scale-run.sh SAMPLES [WORKDIR]}
WORK=${2:-/tmp/arkit-scale-$N}
HERE=$(cd "$(dirname "$0")/.." && pwd)
BIN=${ARKIT_TOOL:-$HERE/target/release/arkit-tool}
RES=${RESOURCES:-$HERE/../shared/arkitface-resources}
PY=${PYTHON:-python3}
STAGES=${STAGES:-synth convert split render crops loader}
PER=180
SUBJECTS=$(( (N + PER - 1) / PER ))
TEST=$(( SUBJECTS / 10 > 0 ? SUBJECTS / 10 : 1 ))

[ -x /usr/bin/time ] || { echo "scale-run: needs GNU time at /usr/bin/time" >&2; exit 2; }
[ -x "$BIN" ] || { echo "scale-run: no binary at $BIN (cargo build --release, or set ARKIT_TOOL)" >&2; exit 2; }
[ -f "$RES/triangles.npy" ] || { echo "scale-run: no resources at $RES (set RESOURCES)" >&2; exit 2; }
mkdir -p "$WORK"
LOGS=$WORK/logs
mkdir -p "$LOGS"

# The most open descriptors of `$1`'s process tree until it exits.
fd_peak() {
  local root=$1 peak=0 n pids
  while kill -0 "$root" 2>/dev/null; do
    pids=$(ps -o pid= --ppid "$root" 2>/dev/null; echo "$root")
    # Grandchildren (DataLoader workers under python under time).
    for p in $pids; do pids="$pids $(ps -o pid= --ppid "$p" 2>/dev/null)"; done
    n=0
    for p in $(echo "$pids" | tr ' ' '\n' | sort -u); do
      [ -d "/proc/$p/fd" ] && n=$(( n + $(ls "/proc/$p/fd" 2>/dev/null | wc -l) ))
    done
    [ "$n" -gt "$peak" ] && peak=$n
    sleep 0.5
  done
  echo "$peak"
}

LOADER_PY='
import sys, time
import arkit_tool
ds = arkit_tool.ARKitFaceDataset(sys.argv[1], split="train", mode="train", corr="sparse",
                                 resources=sys.argv[2])
assert ds.crop_store is not None, "no crop store: run the crops stage first"
n = 0
t = time.perf_counter()
for batch in ds.loader(64, shuffle=True, num_workers=2):
    n += batch["img"].shape[0]
dt = time.perf_counter() - t
print(f"loader: {n} samples in {dt:.1f} s, {n / dt:.0f} samples/s")
'

printf '%-8s %8s %10s %10s %10s %10s %8s\n' stage samples wall_s cpu_s peak_MiB disk_MiB fds
for stage in $STAGES; do
  case $stage in
    synth) cmd=("$BIN" synth --output "$WORK/release" --subjects "$SUBJECTS" --images-per-subject "$PER"
                --size 800x800 --seed 1 --resources "$RES") ;;
    convert) cmd=("$BIN" convert --input "$WORK/release" --output "$WORK/data" --resources "$RES") ;;
    split) cmd=("$BIN" split --dataset "$WORK/data" --test-subjects "$TEST" --seed 0) ;;
    render) cmd=("$BIN" render --dataset "$WORK/data" --resources "$RES") ;;
    crops) cmd=("$BIN" crops --dataset "$WORK/data" --resources "$RES") ;;
    loader)
      if ! "$PY" -c 'import arkit_tool, torch' 2>/dev/null; then
        echo "loader   SKIPPED: $PY cannot import arkit_tool and torch" >&2
        continue
      fi
      cmd=("$PY" -c "$LOADER_PY" "$WORK/data" "$RES") ;;
    *) echo "scale-run: unknown stage '$stage'" >&2; exit 2 ;;
  esac
  before=$(du -sm "$WORK" | cut -f1)
  /usr/bin/time -v -o "$LOGS/$stage.time" "${cmd[@]}" >"$LOGS/$stage.out" 2>"$LOGS/$stage.err" &
  pid=$!
  fds=$(fd_peak "$pid")
  if ! wait "$pid"; then
    echo "scale-run: $stage failed; see $LOGS/$stage.err and $LOGS/$stage.time" >&2
    exit 1
  fi
  after=$(du -sm "$WORK" | cut -f1)
  t=$LOGS/$stage.time
  wall=$(awk -F': ' '/Elapsed \(wall clock\)/ {n = split($2, p, ":"); s = 0; for (i = 1; i <= n; i++) s = s * 60 + p[i]; print s}' "$t")
  cpu=$(awk -F': ' '/User time/ {u = $2} /System time/ {s = $2} END {printf "%.1f", u + s}' "$t")
  rss=$(awk -F': ' '/Maximum resident set size/ {printf "%.0f", $2 / 1024}' "$t")
  row=$(printf '%-8s %8d %10.1f %10s %10s %10d %8d' "$stage" "$N" "$wall" "$cpu" "$rss" $(( after - before )) "$fds")
  echo "$row"
  if [ -n "${TABLE:-}" ]; then echo "$row" | tr -s ' ' '\t' >>"$TABLE"; fi
done
echo "total on disk: $(du -sh "$WORK" | cut -f1) in $WORK (delete it when done)"
