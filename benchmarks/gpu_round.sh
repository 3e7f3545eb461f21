#!/usr/bin/env bash
# The GPU figures of the compile-and-real-scale work in one prepared run (fits 10 minutes on an
# H100): the demo cold then warm (an empty jaxedit cache, then the same cache), the users' job
# at real scale (benchmarks/real_scale.py), the SD 1.5-size editor per batch size
# (benchmarks/ip2p.py), and, if time is left, the splatter against gsplat (benchmarks/gpu.py).
#
#   bash benchmarks/gpu_round.sh prepare      # here, with network: the wheels the GPU lacks
#   bash benchmarks/gpu_round.sh run OUT      # on the GPU machine (device tool: carry .whl)
#
# Each step writes its JSON under OUT (the device tool's $OUT): first_use_gpu.json (demo cold
# and warm with their compiles), real_scale.json, ip2p.json, gpu.json; log.txt has the output.
# Commit them under benchmarks/results/h100/. Steps run in order of importance, each under a
# time limit so that one slow step cannot take the others' time.
set -uo pipefail
cd "$(dirname "$0")/.."

WHEELS=(OpenImageIO==3.1.7.0 diffusers==0.36.0 imageio-ffmpeg==0.6.0 gsplat==1.5.3)

prepare() {
  grep -qx '/.whl/' .git/info/exclude 2>/dev/null || echo /.whl/ >> .git/info/exclude
  python3 -m pip download -q --no-deps --only-binary=:all: --python-version 3.12 \
    --implementation cp --platform manylinux_2_28_x86_64 --platform manylinux_2_17_x86_64 \
    --platform manylinux2014_x86_64 -d .whl "${WHEELS[@]}"
  ls -la .whl
}

# Seconds left of the run's budget (BUDGET, default 570 of the device's 600), capped at $1.
left() { local l=$(( ${BUDGET:-570} - SECONDS )); [ "$l" -lt "$1" ] && echo $(( l > 1 ? l : 1 )) || echo "$1"; }

run() {
  local out=${1:?OUT folder}
  mkdir -p "$out"
  exec > >(tee "$out/log.txt") 2>&1
  if [ -d .whl ]; then
    python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade \
      --target /tmp/site .whl/*.whl && export PYTHONPATH=/tmp/site:$PWD
  fi
  export PYTHONUNBUFFERED=1 XLA_PYTHON_CLIENT_PREALLOCATE=false
  nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv || true

  # 1. The quick start from an empty cache, then again: cold and warm (goal 60 s / 25 s).
  local cache; cache=$(mktemp -d)
  for pass in cold warm; do
    local t0=$SECONDS
    JAXEDIT_CACHE=$cache timeout "$(left 150)" python3 -m experiments demo --out "/tmp/demo_$pass" \
      --quiet > /dev/null
    echo "demo $pass: rc $?, $((SECONDS - t0)) s"
  done
  python3 benchmarks/first_use.py --collect /tmp/demo_cold /tmp/demo_warm --out "$out" \
    --name first_use_gpu

  # 2. The users' job, cold then warm: a subtask of 3000 steps with a 512 px edit every 10.
  timeout "$(left 330)" python3 benchmarks/real_scale.py --out "$out" --subtasks 1 --steps 3000 \
    --recon-iters 1000 --batch 8 || echo "real_scale: rc $?"

  # 3. The SD 1.5-size editor, batch 1 and 8: per-edit time, compile, peak per batch size.
  timeout "$(left 150)" python3 benchmarks/ip2p.py --arch sd15 --size 512 --steps 20 \
    --batch 1 8 --out "$out" || echo "ip2p: rc $?"

  # 4. If time is left: the splatter against gsplat (builds gsplat's CUDA code, ~75 s).
  if [ "$(left 600)" -gt 150 ]; then
    TORCH_CUDA_ARCH_LIST=9.0 MAX_JOBS=14 timeout "$(left 600)" python3 benchmarks/gpu.py \
      --out "$out" || echo "gpu: rc $?"
  fi
}

case "${1:-}" in
  prepare) prepare ;;
  run) shift; run "$@" ;;
  *) echo "usage: $0 prepare | run OUT" >&2; exit 2 ;;
esac
