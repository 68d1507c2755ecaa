#!/usr/bin/env bash
# Runs in a pack made by scripts/gpu-check (on the GPU machine: `bash target/gpu-pack/run.sh`),
# or on this CPU at tiny sizes with --dry-run. Writes gpu-check.md, gpu-check.json and
# gpu-check.log into $OUT (default: the pack's out/). Each step has its own time limit so one
# that hangs cannot take the machine's whole lease; the whole run stays under 8 minutes.
set -uo pipefail
pack="$(cd "$(dirname "${BASH_SOURCE[0]}")" && pwd)"
out="${OUT:-$pack/out}"
work="$(mktemp -d)"
mkdir -p "$out"
dry=0
[[ "${1:-}" == --dry-run ]] && dry=1
python="${PYTHON:-python3}"
torch_lib="$("$python" -c 'import os, torch; print(os.path.join(os.path.dirname(torch.__file__), "lib"))')"
"$python" -m tarfile -e "$pack/bin.tar.xz" "$work/bin" || exit 1
bin="$work/bin"
export LD_LIBRARY_PATH="$torch_lib:$bin/lib${LD_LIBRARY_PATH:+:$LD_LIBRARY_PATH}"
export GPU_WORK="$work/w" GPU_IMAGES="$pack/images" PYTHONUNBUFFERED=1
log="$out/gpu-check.log"
: >"$log"
if ((dry)); then
  export GPU_DEVICE=cpu GPU_DTYPES=f32 GPU_BATCHES=1,2 GPU_SIDE=64 GPU_SECONDS=0.05 GPU_CLIENTS=1,2 \
    GPU_ENGINE_DTYPE=f32 GPU_ENGINE_BATCH=4 GPU_TRAIN_BATCH=8 GPU_AUTOCAST=f32 PEER_COMPILE=
  search_env=(LOOPD_BENCH_SIZES=2000 LOOPD_BENCH_DIMS=256 LOOPD_BENCH_SINGLES=5)
  limit=120
else
  export GPU_DEVICE=cuda PEER_COMPILE="${PEER_COMPILE-f16:32,bf16:32}" PEER_COMPILE_UNTIL=100
  search_env=(LOOPD_BENCH_SIZES=100000,1000000 LOOPD_BENCH_DIMS=2048 LOOPD_BENCH_SINGLES=50
    LOOPD_BENCH_SEARCH_DEVICE=cuda)
  limit=0
fi
step() { # step NAME SECONDS COMMAND...: stdout to rows-NAME.jsonl, stderr to the log
  local name=$1 secs=$2
  shift 2
  ((limit)) && secs=$limit
  echo ">> $name (at most $secs s): $*" | tee -a "$log" >&2
  local t=$SECONDS
  timeout "$secs" "$@" >"$work/rows-$name.jsonl" 2>>"$log"
  local rc=$?
  echo ">> $name: rc $rc in $((SECONDS - t)) s" | tee -a "$log" >&2
}
"$python" - >"$work/meta.json" <<'PY'
import datetime, json, os, subprocess, torch
m = {"date": datetime.datetime.now(datetime.timezone.utc).strftime("%Y-%m-%d %H:%M UTC"), "torch": torch.__version__,
     "cuda": torch.version.cuda, "cpus": os.cpu_count()}
if torch.cuda.is_available():
    m["gpu"] = torch.cuda.get_device_name(0)
    try:
        m["driver"] = subprocess.run(["nvidia-smi", "--query-gpu=driver_version", "--format=csv,noheader"],
                                     capture_output=True, text=True).stdout.strip()
    except OSError:
        pass
print(json.dumps(m))
PY
if ! ((dry)) && command -v nvidia-smi >/dev/null; then
  "$python" "$pack/smi.py" "$work/smi.csv" &
  sampler=$!
fi
# GPU_SECTIONS: the sections to run (default all: forward, peer, engine, train, search).
sections=" ${GPU_SECTIONS:-forward peer engine train search} "
[[ $sections == *" forward "* ]] && step loopd-forward 140 "$bin/gpu" forward
[[ $sections == *" peer "* ]] && step peer 140 "$python" "$pack/peer.py" "$GPU_WORK"
[[ $sections == *" engine "* ]] && step loopd-engine 90 "$bin/gpu" engine
[[ $sections == *" train "* ]] && step loopd-train 50 "$bin/gpu" train
if [[ $sections == *" search "* ]]; then
  echo ">> search" | tee -a "$log" >&2
  env "${search_env[@]}" LOOPD_BENCH_INSERTS=0 LOOPD_BENCH_FAISS=0 timeout "$([[ $limit == 0 ]] && echo 130 || echo $limit)" \
    "$bin/search" >"$work/search.md" 2>>"$log"
  echo ">> search: rc $?" | tee -a "$log" >&2
fi
[[ -n "${sampler:-}" ]] && kill "$sampler" 2>/dev/null
check=()
((dry)) && check=(--check)
"$python" "$pack/report.py" "$work" "$out/gpu-check.md" "$out/gpu-check.json" "${check[@]}"
rc=$?
rm -rf "$work"
exit $rc
