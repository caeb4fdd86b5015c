#!/usr/bin/env bash
# convert (50 pods) -> merge -> render (50 pods), each waited for; see convert-job.yaml.
set -euo pipefail
here=$(cd "$(dirname "$0")" && pwd)
for job in convert merge render; do
  kubectl apply -f "$here/$job-job.yaml"
  kubectl wait --for=condition=complete --timeout=24h "job/arkit-$job"
done
