#!/usr/bin/env bash
# Create volcap's work pools, the GPU concurrency limit and the zombie-run automation on the
# Prefect server PREFECT_API_URL points at. Safe to run again (updates what exists).
#
#   deploy/setup-pool.sh --gpus 8                    # studio / bare-metal: process workers
#   deploy/setup-pool.sh --gpus 64 --type kubernetes # cluster: one Kubernetes Job per GPU run
#
# Pools:   control  (process)              the production orchestrator, no GPU
#          gpu      (process | kubernetes) train-segment runs, one GPU each
# Limits:  work pool `gpu` concurrency = N  runs started at once on the pool
#          global limit `gpu-slots` = N     slots held by train_segment_flow while it trains
set -euo pipefail

TYPE=process
GPUS=""
while [[ $# -gt 0 ]]; do
  case "$1" in
    --type) TYPE="$2"; shift 2 ;;
    --gpus) GPUS="$2"; shift 2 ;;
    -h|--help) sed -n '2,15p' "$0"; exit 0 ;;
    *) echo "unknown argument: $1 (see --help)" >&2; exit 2 ;;
  esac
done
if [[ -z "$GPUS" ]]; then
  if command -v nvidia-smi >/dev/null 2>&1; then
    GPUS=$(nvidia-smi -L | wc -l)
  else
    echo "give --gpus N (total GPUs of all GPU workers); nvidia-smi is not here to count them" >&2
    exit 2
  fi
fi
if ! [[ "$GPUS" =~ ^[1-9][0-9]*$ ]]; then echo "--gpus must be a positive integer, got '$GPUS'" >&2; exit 2; fi
case "$TYPE" in process|kubernetes) ;; *) echo "--type is process or kubernetes, got '$TYPE'" >&2; exit 2 ;; esac
: "${PREFECT_API_URL:?set PREFECT_API_URL, e.g. http://prefect-server:4200/api}"
HERE="$(cd "$(dirname "${BASH_SOURCE[0]}")" && pwd)"

echo "== work pool 'control' (process): the production orchestrator"
prefect work-pool create control --type process --overwrite

echo "== work pool 'gpu' ($TYPE), at most $GPUS runs at once"
if existing=$(prefect work-pool inspect gpu 2>/dev/null) && ! grep -q "type='$TYPE'" <<< "$existing"; then
  echo "work pool 'gpu' exists with another type; a pool cannot change type:" >&2
  echo "  prefect work-pool delete gpu   (when no run is using it), then run this again" >&2
  exit 1
fi
if [[ "$TYPE" == kubernetes ]]; then
  prefect work-pool create gpu --type kubernetes \
    --base-job-template "$HERE/k8s/gpu-job-template.json" --overwrite
else
  prefect work-pool create gpu --type process --overwrite
fi
prefect work-pool set-concurrency-limit gpu "$GPUS"

echo "== global concurrency limit 'gpu-slots' = $GPUS (one slot per GPU)"
if prefect gcl inspect gpu-slots >/dev/null 2>&1; then
  prefect gcl update gpu-slots --limit "$GPUS"
else
  prefect gcl create gpu-slots --limit "$GPUS"
fi

echo "== automation: crash flow runs whose heartbeats stopped"
if prefect automation inspect "volcap: crash zombie flow runs" >/dev/null 2>&1; then
  echo "   exists"
else
  prefect automation create --from-file "$HERE/automations/crash-zombie-flows.yaml"
fi

echo "done. Next, from the repository root: env -u VOLCAP_HOME prefect deploy --all --prefect-file deploy/prefect.yaml"
