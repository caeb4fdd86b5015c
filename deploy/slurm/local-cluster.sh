#!/usr/bin/env bash
# Runs the Slurm recipe (deploy/slurm/submit.sh) for real on a one-node Slurm cluster
# started on this machine, and checks what it wrote against a single-machine run.
#
#   deploy/slurm/local-cluster.sh [WORK_DIR]
#
# Needs Debian's `slurm-wlm` and `munge` (apt-get install slurm-wlm munge) and root (the
# daemons run as root here; a real cluster's are already running). It
#   1. writes a munge key and a slurm.conf for one node (this host, all its CPUs) into
#      WORK_DIR (default: a new temporary folder), starts munged, slurmctld and slurmd
#      on them (nothing in /etc is touched: SLURM_CONF points the clients at that file);
#   2. makes a small synthetic release with `arkit-tool synth`;
#   3. submits deploy/slurm/submit.sh with sbatch: a convert array of N tasks, the merge
#      job, a render array of N tasks, chained with afterok; waits for all three;
#   4. converts and renders the same release on this machine in one process each, and
#      checks that every Parquet file and the manifest's samples agree byte for byte;
#   5. stops the daemons (also on failure) and prints `slurm: ok` on success.
# With SLURM_FAULTS=1, step 3 submits the recipe held and runs it through faults: a
# convert task cancelled (merge must refuse, naming the missing part; the task is
# resubmitted alone), a render task killed with SIGKILL mid-way (resubmitted alone), a
# render task re-queued; step 4 then checks the result as above.
# ARKIT_TOOL names the binary (default target/release/arkit-tool of this checkout);
# ARKIT_RESOURCES the release's resource folder (default ../shared/arkitface-resources
# beside the checkout: the recipe converts with the real topology); ARRAY_SIZE the
# number of tasks per array (3).
# Exit status: 0 when everything matched, 1 on a difference or a failed job, 2 when a
# prerequisite is missing (the message says which).
set -euo pipefail
here=$(cd "$(dirname "$0")/../.." && pwd)
bin=${ARKIT_TOOL:-$here/target/release/arkit-tool}
n=${ARRAY_SIZE:-3}
for tool in sbatch squeue sacct slurmctld slurmd munged mungekey; do
  command -v "$tool" >/dev/null 2>&1 || { echo "slurm: '$tool' not found (apt-get install slurm-wlm munge)" >&2; exit 2; }
done
[ -x "$bin" ] || { echo "slurm: no arkit-tool binary at $bin (cargo build --release, or set ARKIT_TOOL)" >&2; exit 2; }
[ "$(id -u)" = 0 ] || { echo "slurm: starting slurmd needs root" >&2; exit 2; }
resources=${ARKIT_RESOURCES:-$here/../shared/arkitface-resources}
[ -d "$resources" ] || { echo "slurm: no resource folder at $resources (set ARKIT_RESOURCES)" >&2; exit 2; }
resources=$(cd "$resources" && pwd)

work=${1:-$(mktemp -d)}
mkdir -p "$work"
work=$(cd "$work" && pwd)
state="$work/state"
mkdir -p "$state/ctld" "$state/d" "$state/munge" "$state/log"
chmod 700 "$state/munge"
pids=()
stop() {
  for p in ${pids[@]+"${pids[@]}"}; do kill "$p" 2>/dev/null || true; done
  # slurmd and slurmctld fork their own children (job steps): end what is left of them.
  pkill -f "$state/slurm.conf" 2>/dev/null || true
}
trap stop EXIT

# 1. munge and a one-node Slurm.
mungekey --create --keyfile="$state/munge/munge.key" --force >/dev/null
chmod 400 "$state/munge/munge.key"
socket="$state/munge/munge.socket"
munged --force --key-file="$state/munge/munge.key" --socket="$socket" \
  --pid-file="$state/munge/munged.pid" --log-file="$state/log/munged.log" \
  --seed-file="$state/munge/munged.seed"
pids+=("$(cat "$state/munge/munged.pid")")
host=$(hostname -s)
cpus=$(nproc)
mem_mb=$(( $(awk '/MemTotal/ {print $2}' /proc/meminfo) / 1024 - 512 ))
# With faults: a re-queued job waits cred_expire seconds (120 by default) before it
# starts again; 10 here.
cred_expire=
[ "${SLURM_FAULTS:-0}" = 1 ] && cred_expire=,cred_expire=10
# The first free pair of ports from 16817 on (unless SLURMCTLD_PORT and SLURMD_PORT
# are given), so that two of these clusters on one machine (two test runs side by
# side) do not fight over one port.
listening() { # PORT
  if command -v ss >/dev/null 2>&1; then
    ss -ltnH 2>/dev/null | awk '{print $4}' | grep -q ":$1\$"
  else
    (echo >"/dev/tcp/127.0.0.1/$1") 2>/dev/null
  fi
}
ctld_port=${SLURMCTLD_PORT:-}
slurmd_port=${SLURMD_PORT:-}
if [ -z "$ctld_port" ] || [ -z "$slurmd_port" ]; then
  p=16817
  while listening "$p" || listening $((p + 1)); do p=$((p + 2)); done
  ctld_port=${ctld_port:-$p}
  slurmd_port=${slurmd_port:-$((p + 1))}
fi
cat >"$state/slurm.conf" <<EOF
# One node, written by deploy/slurm/local-cluster.sh.
ClusterName=arkit-local
SlurmctldHost=$host
SlurmctldPort=$ctld_port
SlurmdPort=$slurmd_port
AuthType=auth/munge
CredType=cred/munge
AuthInfo=socket=$socket$cred_expire
SlurmUser=root
SlurmdUser=root
StateSaveLocation=$state/ctld
SlurmdSpoolDir=$state/d
SlurmctldPidFile=$state/slurmctld.pid
SlurmdPidFile=$state/slurmd.pid
SlurmctldLogFile=$state/log/slurmctld.log
SlurmdLogFile=$state/log/slurmd.log
ProctrackType=proctrack/pgid
TaskPlugin=task/none
SelectType=select/cons_tres
SelectTypeParameters=CR_Core_Memory
SchedulerType=sched/backfill
JobCompType=jobcomp/none
JobAcctGatherType=jobacct_gather/none
AccountingStorageType=accounting_storage/none
MpiDefault=none
ReturnToService=2
MaxArraySize=1001
NodeName=$host CPUs=$cpus RealMemory=$mem_mb State=UNKNOWN
PartitionName=local Nodes=$host Default=YES MaxTime=INFINITE State=UP
EOF
export SLURM_CONF="$state/slurm.conf"
slurmctld -f "$SLURM_CONF"
slurmd -f "$SLURM_CONF"
for _ in $(seq 1 60); do
  if sinfo -h -o '%t' 2>/dev/null | grep -qE '^(idle|mix|alloc)'; then break; fi
  sleep 1
done
sinfo -h -o '%t' | grep -qE '^(idle|mix|alloc)' || {
  echo "slurm: the node did not come up; logs in $state/log" >&2
  tail -n 20 "$state/log/slurmctld.log" "$state/log/slurmd.log" >&2 || true
  exit 1
}
echo "slurm: one-node cluster up ($host, $cpus CPUs, ${mem_mb} MB)"

# 2. A small release.
release="$work/release"
"$bin" synth --output "$release" --subjects 6 --images-per-subject 8 --size 256x256 \
  --seed 3 --resources "$resources" >/dev/null
# Small shards, so that each of the N tasks has several to do.
convert_options="--rows-per-shard 6"
render_options="--size 48 --points 64 --uv-size 16"
# With faults, shards of two rows and larger targets, so that a render task has eight
# shards to write and is caught between two of them.
if [ "${SLURM_FAULTS:-0}" = 1 ]; then
  convert_options="--rows-per-shard 2"
  render_options="--size 96 --points 256 --uv-size 32"
fi

# 3. The recipe, submitted as a user would (smaller tasks for one small node); with
# SLURM_FAULTS=1, held, then run through the faults of step 3b.
out="$work/slurm-out"
faults=${SLURM_FAULTS:-0}
hold=()
[ "$faults" = 1 ] && hold=(SBATCH_HOLD=1)
task_bin=$bin
if [ "$faults" = 1 ]; then
  # Render task 1's first run stops for good just before it renames its second shard
  # (1 + N) into place (ARKIT_PAUSE_BEFORE_RENAME, the kill harness's hook), so that
  # step 3b kills it between two shards whatever the machine's speed.
  task_bin="$work/tool-pausing-render-1"
  second=$(printf 'targets/part-%05d.parquet' $((1 + n)))
  cat >"$task_bin" <<TOOL
#!/usr/bin/env bash
if [ "\${SLURM_ARRAY_TASK_ID:-}" = 1 ] && [ "\$1" = render ] && mkdir "$work/paused-once" 2>/dev/null; then
  export ARKIT_PAUSE_BEFORE_RENAME="$second"
fi
exec "$bin" "\$@"
TOOL
  chmod +x "$task_bin"
fi
submitted=$(cd "$work" && env ${hold[@]+"${hold[@]}"} CPUS=1 MEM=1G TIME=00:20:00 ARKIT_TOOL="$task_bin" \
  CONVERT_OPTIONS="$convert_options" RENDER_OPTIONS="$render_options" \
  "$here/deploy/slurm/submit.sh" "$release" "$out" "$resources" "$n")
echo "$submitted"
ids=$(echo "$submitted" | sed -n 's/^submitted: convert array \([0-9]*\) -> merge \([0-9]*\) -> render array \([0-9]*\)$/\1 \2 \3/p')
[ -n "$ids" ] || { echo "slurm: could not read the job ids from submit.sh's output" >&2; exit 1; }
read -r convert merge render <<<"$ids"
deadline=$(( $(date +%s) + ${SLURM_WAIT_SECONDS:-600} ))
fail() { echo "slurm: $*" >&2; squeue >&2 || true; tail -n 30 "$work"/slurm-*.out >&2 2>/dev/null || true; exit 1; }
# Waits until no job of the ids given (comma-separated) is queued or running.
wait_jobs() {
  while squeue -h -j "$1" -o '%i' 2>/dev/null | grep -q .; do
    [ "$(date +%s)" -le "$deadline" ] || fail "jobs $1 still queued after ${SLURM_WAIT_SECONDS:-600} s"
    sleep 1
  done
}
# What is resubmitted for one failed task: the same script, an array of that one task,
# with SHARD_COUNT=N (as submit.sh exports it) so that it still does part I of N.
# shellcheck disable=SC2086 # the options are words
resubmit() { # STAGE TASK ARGS...
  local stage=$1 i=$2
  shift 2
  (cd "$work" && sbatch --parsable --cpus-per-task=1 --mem=1G --time=00:20:00 --array="$i" \
    --job-name="arkit-$stage-again" --export=ALL,ARKIT_TOOL="$bin",SHARD_COUNT="$n" \
    "$here/deploy/shard-task.sh" "$stage" "$@")
}
if [ "$faults" = 1 ]; then
  # 3b. Faults. (1) Convert task 1 cancelled before it ran (as a pre-empted or failed
  # task): the others finish; merge refuses, naming the missing part; the merge job
  # waits on a dependency that can no longer be met; task 1 resubmitted alone, the
  # merge job pointed at it.
  t=$(date +%s)
  scancel "${convert}_1"
  scontrol release "$convert"
  scontrol release "$merge"
  wait_jobs "$convert"
  if "$bin" merge --dataset "$out" >/dev/null 2>"$work/merge-refused.txt"; then
    fail "merge accepted a conversion whose part 1 of $n was cancelled"
  fi
  grep -q "part 1 of $n is missing" "$work/merge-refused.txt" \
    || fail "merge's refusal does not name part 1: $(cat "$work/merge-refused.txt")"
  echo "slurm: fault 1: convert task ${convert}_1 cancelled; merge refused: $(tail -n 1 "$work/merge-refused.txt")"
  for _ in $(seq 1 30); do # the scheduler's next pass marks it
    reason=$(squeue -h -j "$merge" -o '%T %r')
    case "$reason" in *DependencyNeverSatisfied*) break ;; esac
    sleep 1
  done
  echo "slurm: fault 1: the merge job waits: $reason"
  # shellcheck disable=SC2086
  again=$(resubmit convert 1 "$release" "$out" --resources "$resources" $convert_options)
  scontrol update JobId="$merge" Dependency="afterok:$again"
  wait_jobs "$again,$merge"
  [ -f "$out/dataset.json" ] || fail "no dataset.json after the resubmitted task and the merge"
  echo "slurm: fault 1: task 1 resubmitted as $again, merged ($(( $(date +%s) - t )) s)"
  # (2) Render task 1 killed (SIGKILL) mid-way, once it has written its first shard
  # (shard 1) of several; (3) render task 2 re-queued (scontrol requeue) once running.
  t=$(date +%s)
  scontrol release "$render"
  # Task 1 holds its second shard, complete, under its temporary name: kill it there
  # (SIGKILL, through Slurm) with shards still to write.
  until grep -q "paused before renaming" "$work/slurm-${render}_1.out" 2>/dev/null; do
    [ "$(date +%s)" -le "$deadline" ] || fail "render task 1 never reached its second shard"
    sleep 0.05
  done
  task1() { for k in $(seq 1 "$n" $((shards - 1))); do [ -e "$out/targets/part-$(printf %05d "$k").parquet" ] && echo "$k"; done; }
  shards=$(grep -c '"samples_file"' "$out/dataset.json")
  scancel --full --signal=KILL "${render}_1"
  # Task 2 starts when task 1's CPU is free; once it has written its first shard
  # (running, or already done: either can be re-queued), it is re-queued.
  while [ ! -e "$out/targets/part-00002.parquet" ]; do
    [ "$(date +%s)" -le "$deadline" ] || fail "render task 2 never started"
    sleep 0.05
  done
  scontrol requeue "${render}_2"
  # (A re-queued job waits cred_expire seconds, 10 here, before it starts again.)
  wait_jobs "$render"
  # Task 1's shards: 1, 1 + N, ... of the dataset's.
  missing=$(for k in $(seq 1 "$n" $((shards - 1))); do [ -e "$out/targets/part-$(printf %05d "$k").parquet" ] || echo "$k"; done | tr '\n' ' ')
  [ -n "$missing" ] || fail "render task 1 was killed but every shard of it is there (it finished first)"
  echo "slurm: fault 2: render task ${render}_1 killed mid-way (before renaming its second shard); its shards written: $(task1 | tr '\n' ' ')missing: $missing"
  if "$bin" train --dataset "$out" --resources "$resources" --split all --steps 1 --batch 1 \
      --output "$work/model" >/dev/null 2>"$work/train-refused.txt"; then
    fail "train accepted targets with render task 1's shards missing"
  fi
  grep -q "targets" "$work/train-refused.txt" \
    || fail "train's refusal does not name the targets: $(cat "$work/train-refused.txt")"
  echo "slurm: fault 2: train refused: $(tail -n 1 "$work/train-refused.txt")"
  # shellcheck disable=SC2086
  again=$(resubmit render 1 "$out" --resources "$resources" $render_options)
  wait_jobs "$again"
  echo "slurm: fault 2: render task 1 resubmitted as $again ($(( $(date +%s) - t )) s)"
  # The re-queued task may leave squeue for a moment between its runs (and waits
  # cred_expire seconds before the second), so its second start is awaited in the log.
  # A start is logged by the main scheduler ("sched: Allocate JobId=...") or by the
  # backfill scheduler ("sched/backfill: _start_job: Started JobId=..."): both count.
  runs_of_task2() {
    grep -cE "(Allocate|Started) JobId=${render}_2\(" "$state/log/slurmctld.log" || true
  }
  while [ "$(runs_of_task2)" -lt 2 ] && [ "$(date +%s)" -le "$deadline" ]; do sleep 1; done
  wait_jobs "$render"
  runs=$(runs_of_task2)
  [ "$runs" -ge 2 ] || fail "render task 2 was re-queued but ran $runs time(s)"
  echo "slurm: fault 3: render task ${render}_2 re-queued and run again ($runs runs)"
fi
while squeue -h -o '%i' | grep -q .; do
  if [ "$(date +%s)" -gt "$deadline" ]; then
    echo "slurm: jobs still queued after ${SLURM_WAIT_SECONDS:-600} s:" >&2
    squeue >&2
    exit 1
  fi
  sleep 2
done
# Without accounting, a job's end state is in slurmctld's log ("done status 0" per task).
# (With faults, the tasks made to fail are expected there; the comparison below judges.)
if [ "$faults" != 1 ]; then
failed=$(grep -E '_job_complete: JobId=[0-9_]+ WEXITSTATUS [1-9]|_job_complete: JobId=.* WTERMSIG' "$state/log/slurmctld.log" || true)
cancelled=$(grep -E 'DependencyNeverSatisfied|cancelled' "$state/log/slurmctld.log" || true)
if [ -n "$failed$cancelled" ]; then
  echo "slurm: a job failed:" >&2
  echo "$failed$cancelled" >&2
  tail -n 30 "$work"/slurm-*.out >&2 2>/dev/null || true
  exit 1
fi
done_tasks=$(grep -cE '_job_complete: JobId=[0-9_]+.* done' "$state/log/slurmctld.log" || true)
echo "slurm: $done_tasks job tasks done ($n convert, 1 merge, $n render expected)"
[ "$done_tasks" -eq $((2 * n + 1)) ] || { echo "slurm: expected $((2 * n + 1)) finished tasks" >&2; exit 1; }
fi

# 4. The same on one machine, and the comparison.
single="$work/single"
# shellcheck disable=SC2086 # the options are words
"$bin" convert --input "$release" --output "$single" --resources "$resources" $convert_options >/dev/null
# shellcheck disable=SC2086
"$bin" render --dataset "$single" --resources "$resources" $render_options >/dev/null
status=0
compare() { # the files under $1 of both outputs, byte for byte
  local a="$single/$1" b="$out/$1" listed_a listed_b
  listed_a=$(cd "$a" && find . -type f -name '*.parquet' | sort)
  listed_b=$(cd "$b" && find . -type f -name '*.parquet' | sort)
  if [ "$listed_a" != "$listed_b" ]; then
    echo "slurm: $1: different files:" >&2
    diff <(echo "$listed_a") <(echo "$listed_b") >&2 || true
    status=1
    return
  fi
  local count=0
  while read -r f; do
    if ! cmp -s "$a/$f" "$b/$f"; then
      echo "slurm: $1/$f differs from the single-machine run" >&2
      status=1
    fi
    count=$((count + 1))
  done <<<"$listed_a"
  echo "slurm: $1: $count Parquet files identical to the single-machine run"
}
compare samples
compare targets
if [ -d "$single/errors" ] || [ -d "$out/errors" ]; then compare errors; fi
"$bin" inspect --dataset "$out" --json >"$work/slurm-inspect.json"
"$bin" inspect --dataset "$single" --json >"$work/single-inspect.json"
if ! cmp -s "$work/slurm-inspect.json" "$work/single-inspect.json"; then
  echo "slurm: inspect differs between the Slurm run and the single-machine run" >&2
  diff "$work/single-inspect.json" "$work/slurm-inspect.json" >&2 || true
  status=1
fi
[ "$status" -eq 0 ] && echo "slurm: ok"
exit "$status"
