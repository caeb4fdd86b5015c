#!/usr/bin/env bash
# One task of a job array: `convert` or `render` part I of N of the ARKitFace release.
# Slurm and Kubernetes both run this; so does tests/shard_processes.rs, with the
# variables set by hand.
#
#   shard-task.sh convert RELEASE_DIR OUTPUT_DIR [more convert options]
#   shard-task.sh render DATASET_DIR [more render options]
#
# I and N come from Slurm (SLURM_ARRAY_TASK_ID, and SHARD_COUNT or else
# SLURM_ARRAY_TASK_COUNT), from a
# Kubernetes Indexed Job (JOB_COMPLETION_INDEX, with SHARD_COUNT set in the manifest),
# or from SHARD_INDEX and SHARD_COUNT. All tasks write into the same OUTPUT_DIR; their
# files are disjoint. After the convert tasks, run `arkit-tool merge --dataset
# OUTPUT_DIR` once; render parts need no merge. ARKIT_TOOL names the binary.
set -euo pipefail
bin=${ARKIT_TOOL:-arkit-tool}
i=${SLURM_ARRAY_TASK_ID:-${JOB_COMPLETION_INDEX:-${SHARD_INDEX:-}}}
# SHARD_COUNT first: a task resubmitted alone (sbatch --array=I) is an array of one task,
# whose SLURM_ARRAY_TASK_COUNT is 1, not N (submit.sh exports SHARD_COUNT=N).
n=${SHARD_COUNT:-${SLURM_ARRAY_TASK_COUNT:-}}
if [ -z "$i" ] || [ -z "$n" ]; then
  echo "shard-task: no task index and count (set SLURM_ARRAY_TASK_ID/SLURM_ARRAY_TASK_COUNT, JOB_COMPLETION_INDEX/SHARD_COUNT, or SHARD_INDEX/SHARD_COUNT)" >&2
  exit 2
fi
stage=${1:-}
shift || true
case "$stage" in
  convert)
    [ $# -ge 2 ] || { echo "usage: shard-task.sh convert RELEASE_DIR OUTPUT_DIR [options]" >&2; exit 2; }
    input=$1 output=$2
    shift 2
    exec "$bin" convert --input "$input" --output "$output" --shard "$i/$n" "$@"
    ;;
  render)
    [ $# -ge 1 ] || { echo "usage: shard-task.sh render DATASET_DIR [options]" >&2; exit 2; }
    dataset=$1
    shift
    exec "$bin" render --dataset "$dataset" --shard "$i/$n" "$@"
    ;;
  *)
    echo "shard-task: unknown stage '$stage' (convert or render)" >&2
    exit 2
    ;;
esac
