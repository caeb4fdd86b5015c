#!/usr/bin/env bash
# Convert and render the ARKitFace release on a Slurm cluster: an array of N convert
# tasks, one merge, an array of N render tasks, chained with afterok dependencies.
#
#   deploy/slurm/submit.sh RELEASE_DIR OUTPUT_DIR RESOURCES_DIR [N]
#
# RELEASE_DIR is the download as published (ARKitFace_image_*, ARKitFace_info_*,
# ARKitFace_list); OUTPUT_DIR must be on a file system every node sees. N defaults to
# 50. Per-task resources: CPUS (8), MEM (16G), TIME (04:00:00); ARKIT_TOOL names the
# binary on the nodes. Each task uses all the CPUs it is given (rayon). More options for
# every convert task in CONVERT_OPTIONS (e.g. "--rows-per-shard 4096"), for every render
# task in RENDER_OPTIONS (e.g. "--size 192 --points 1024"); PARTITION, if set, is passed
# to every sbatch as --partition. Prints the three job ids. A failed or cancelled task is
# resubmitted alone: docs/cluster.md, "When a task fails".
# deploy/slurm/local-cluster.sh runs this on a one-node cluster and checks the result.
set -euo pipefail
if [ $# -lt 3 ]; then
  sed -n '2,17p' "$0" >&2
  exit 2
fi
here=$(cd "$(dirname "$0")/.." && pwd)
release=$1 output=$2 resources=$3 n=${4:-50}
bin=${ARKIT_TOOL:-arkit-tool}
read -r -a convert_options <<<"${CONVERT_OPTIONS:-}"
read -r -a render_options <<<"${RENDER_OPTIONS:-}"
common=()
[ -n "${PARTITION:-}" ] && common+=(--partition="$PARTITION")
task=("${common[@]}" --cpus-per-task="${CPUS:-8}" --mem="${MEM:-16G}" --time="${TIME:-04:00:00}")
# SHARD_COUNT: a task resubmitted alone (docs/cluster.md) still knows N.
convert=$(sbatch --parsable "${task[@]}" --array="0-$((n - 1))" --job-name=arkit-convert \
  --export=ALL,ARKIT_TOOL="$bin",SHARD_COUNT="$n" \
  "$here/shard-task.sh" convert "$release" "$output" --resources "$resources" \
  "${convert_options[@]}")
merge=$(sbatch --parsable "${common[@]}" --dependency="afterok:$convert" --job-name=arkit-merge \
  --wrap "'$bin' merge --dataset '$output'")
render=$(sbatch --parsable "${task[@]}" --dependency="afterok:$merge" --array="0-$((n - 1))" \
  --job-name=arkit-render --export=ALL,ARKIT_TOOL="$bin",SHARD_COUNT="$n" \
  "$here/shard-task.sh" render "$output" --resources "$resources" "${render_options[@]}")
echo "submitted: convert array $convert -> merge $merge -> render array $render"
echo "watch: squeue -j $convert,$merge,$render; then: $bin inspect --dataset $output"
