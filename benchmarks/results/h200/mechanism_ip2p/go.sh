# Device run of mechanism-study parts: W workers over QUEUE until BUDGET seconds from now.
# env: W, BUDGET, QUEUE, CACHE, FLAGS, OUT; PY (python)
set -u
PY=${PY:-python3}
export XLA_PYTHON_CLIENT_PREALLOCATE=false JAX_DEFAULT_MATMUL_PRECISION=highest PYTHONUNBUFFERED=1
export JAX_COMPILATION_CACHE_DIR=/tmp/jaxcache JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS=1
R=${R:-/tmp/mech}; rm -rf $R; mkdir -p $R
$PY -c "import jax, jaxedit; print(jax.__version__, jax.devices())" || exit 3
DEADLINE=$(( $(date +%s) + BUDGET ))
pids=""
for w in $(seq 1 $W); do
  timeout $((BUDGET + 30)) $PY .devruns/parts.py $QUEUE $R $CACHE $DEADLINE $w -- $FLAGS > $R/w$w.log 2>&1 &
  pids="$pids $!"
  sleep 2
done
snap() { cat $R/units/*/runs.jsonl > $OUT/runs_gpu.jsonl 2>/dev/null; cat $R/w*.log > $OUT/workers.log; }
( while true; do sleep 15; snap; done ) &
copier=$!
( while true; do nvidia-smi --query-gpu=utilization.gpu,memory.used --format=csv,noheader 2>/dev/null; uptime; sleep 30; done ) > $OUT/gpu.log 2>&1 &
mon=$!
wait $pids
kill $copier $mon
snap
wc -l $OUT/runs_gpu.jsonl; grep -h "done in\|Error\|error" $R/w*.log | tail -40
