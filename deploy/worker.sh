#!/usr/bin/env bash
# Start one volcap GPU worker per GPU of this machine (process work pool `gpu`), plus one
# `control` worker for the production orchestrator when asked. Each GPU worker sees only its GPU
# (CUDA_VISIBLE_DEVICES) and runs one flow run at a time, so a segment owns its GPU.
#
#   deploy/worker.sh                 # every GPU of this machine
#   deploy/worker.sh --gpus 0,1      # these GPUs only
#   deploy/worker.sh --control       # also the control-pool worker (run it on one machine)
#
# Needs, in the environment (never in a file of the repository):
#   PREFECT_API_URL      http://<prefect-server>:4200/api
#   VOLCAP_HOME          this machine's checkout of volcap (the deployments' pull step cds there)
#   VOLCAP_STORE         the shared store, e.g. s3://studio-volcap/store
#   AWS_ACCESS_KEY_ID, AWS_SECRET_ACCESS_KEY, AWS_DEFAULT_REGION [, AWS_ENDPOINT_URL]
#                        store credentials (or a Prefect Secret block the flows read)
# `volcap worker` (flows/cli.py) is `prefect worker start` with volcap's settings (DO_NOT_TRACK,
# heartbeats every 60 s, one OpenMP thread per process); VOLCAP_WORKER_CMD overrides the command,
# and this script sets the same defaults for it. Logs: VOLCAP_WORKER_LOGS
# (default $VOLCAP_HOME/.volcap/workers).
# SIGTERM / SIGINT stop every worker gracefully (a Prefect worker stops on SIGTERM by sending
# itself SIGINT) and exit; when one worker exits, the others are stopped the same way and the
# script exits with that worker's status, so a supervisor (systemd) restarts the whole set.
set -euo pipefail

GPU_LIST=""
CONTROL=0
while [[ $# -gt 0 ]]; do
  case "$1" in
    --gpus) GPU_LIST="$2"; shift 2 ;;
    --control) CONTROL=1; shift ;;
    -h|--help) sed -n '2,22p' "$0"; exit 0 ;;
    *) echo "unknown argument: $1 (see --help)" >&2; exit 2 ;;
  esac
done
: "${PREFECT_API_URL:?set PREFECT_API_URL, e.g. http://prefect-server:4200/api}"
: "${VOLCAP_HOME:?set VOLCAP_HOME to the volcap checkout on this machine}"
WORKER=(${VOLCAP_WORKER_CMD:-volcap worker})
export DO_NOT_TRACK=1 PREFECT_SERVER_ANALYTICS_ENABLED=false
export PREFECT_FLOWS_HEARTBEAT_FREQUENCY="${PREFECT_FLOWS_HEARTBEAT_FREQUENCY:-60}"
# one OpenMP/MKL thread per process, before any flow run imports torch (flows/runtime.py
# reproducible_cpu_defaults: bit-reproducible CPU work); set them to trade that for speed
export OMP_NUM_THREADS="${OMP_NUM_THREADS:-1}" MKL_NUM_THREADS="${MKL_NUM_THREADS:-1}"
# the compiled (numba) kernels' OpenMP threads sleep between kernels instead of spinning
export OMP_WAIT_POLICY="${OMP_WAIT_POLICY:-PASSIVE}"

if [[ -z "$GPU_LIST" ]]; then
  if ! command -v nvidia-smi >/dev/null 2>&1; then
    echo "give --gpus 0,1,... (the GPU indices to use); nvidia-smi is not here to list them" >&2
    exit 2
  fi
  GPU_LIST=$(nvidia-smi --query-gpu=index --format=csv,noheader | paste -sd, -)
fi
if ! [[ "$GPU_LIST" =~ ^[0-9]+(,[0-9]+)*$ ]]; then
  echo "--gpus is a comma-separated list of GPU indices (e.g. 0,1), got '$GPU_LIST'" >&2
  exit 2
fi
IFS=, read -r -a GPUS <<< "$GPU_LIST"
LOGDIR="${VOLCAP_WORKER_LOGS:-$VOLCAP_HOME/.volcap/workers}"
mkdir -p "$LOGDIR"
PIDS=()

# SIGTERM to every worker, then wait for them (each stops gracefully: see the header)
stop() {
  trap - INT TERM EXIT
  kill -TERM "${PIDS[@]}" 2>/dev/null || true
  wait || true
}
trap 'stop; exit 143' TERM
trap 'stop; exit 130' INT
trap stop EXIT

# start one worker in the background. `trap - INT`: bash starts background commands of a script
# with SIGINT ignored, and a Prefect worker stops on SIGTERM by sending itself SIGINT: without
# it, the worker would never stop on SIGTERM (only the SIGKILL of a second SIGTERM would end it)
start_worker() {  # NAME CUDA_VISIBLE_DEVICES ARGS...
  local name="$1" gpus="$2"
  shift 2
  ( trap - INT; export CUDA_VISIBLE_DEVICES="$gpus"; exec "${WORKER[@]}" "$@" --name "$name" ) \
    >"$LOGDIR/$name.log" 2>&1 &
  PIDS+=("$!")
}

for gpu in "${GPUS[@]}"; do
  name="$(hostname -s)-gpu$gpu"
  echo "starting $name (CUDA_VISIBLE_DEVICES=$gpu), log $LOGDIR/$name.log"
  start_worker "$name" "$gpu" --pool gpu --limit 1
done
if [[ "$CONTROL" == 1 ]]; then
  name="$(hostname -s)-control"
  echo "starting $name (no GPU), log $LOGDIR/$name.log"
  start_worker "$name" "" --pool control
fi
# exit (and stop the others) as soon as one worker exits: a supervisor (systemd) restarts us
status=0
wait -n || status=$?
echo "a worker exited (status $status); stopping the others" >&2
stop
exit "$status"
