#!/usr/bin/env bash
# The GPU checks (benchmarks/gpu_checks.py) on a lent GPU machine, in one call of the device tool:
#   here:   python benchmarks/gpu_checks.py prepare     (wheels and the learned split into .whl/, ignored by git)
#   device: run(command="bash benchmarks/gpu_checks.sh", carry=[".whl"], timeout_s=560)
#   after:  python benchmarks/gpu_checks.py score-learned FILES_AT --out DIR   (held-out scores of the returned model)
# $OUT/gpu_checks.md opens with issue #68's targets (each measured figure beside its goal) and ends with
# each step's seconds against the budget. Extra arguments go to `gpu_checks.py run` (e.g. --steps 1000
# --skip-tests --learned-steps 500 --skip-learned --skip-vector-env --skip-cpu).
# Step 7 (the learned estimator's long training, after `prepare --learned-full ...`) is a call of its own:
#   device: run(command="bash benchmarks/gpu_checks.sh --learned-full-only --learned-full-steps 4800:16000",
#               carry=[".whl"], timeout_s=560)
set -euo pipefail
cd "$(dirname "$0")/.."
out="${OUT:-/tmp/gpu_checks}"
# The device tool returns at most 8 files from $OUT: the checks write into a work folder and only
# the report, its log, the tests' log and the GPU-trained learned models (for `score-learned`) are copied back.
work="${GPU_CHECKS_WORK:-/tmp/gpu_checks_work}"
mkdir -p "$out" "$work"
if compgen -G ".whl/*.whl" >/dev/null; then
  python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site .whl/*.whl
  export PYTHONPATH="/tmp/site${PYTHONPATH:+:$PYTHONPATH}"
fi
export PYTHONPATH="$PWD/src${PYTHONPATH:+:$PYTHONPATH}" PYTHONUNBUFFERED=1
# gsplat compiles its CUDA extension on first use: for this GPU only, with every core
export MAX_JOBS="${MAX_JOBS:-$(nproc)}" FAST_COMPILE="${FAST_COMPILE:-1}"
if [ -z "${TORCH_CUDA_ARCH_LIST:-}" ]; then
  TORCH_CUDA_ARCH_LIST="$(python3 -c 'import torch; c = torch.cuda.get_device_capability() if torch.cuda.is_available() else None; print(f"{c[0]}.{c[1]}" if c else "")')"
  [ -n "$TORCH_CUDA_ARCH_LIST" ] && export TORCH_CUDA_ARCH_LIST || unset TORCH_CUDA_ARCH_LIST
fi
status=0
# cut short inside the device call's limit (GPU_CHECKS_BUDGET_S, 480 s) so that what was measured,
# saved after every step, still comes back
timeout -k 10 "${GPU_CHECKS_BUDGET_S:-480}" python3 benchmarks/gpu_checks.py run --out "$work" "$@" 2>&1 \
  | tee "$out/gpu_checks.log" || status=$?
for f in gpu_checks.json gpu_checks.md pytest.log learned_cuda/model.pt learned_cuda_bf16/model.pt \
         learned_cuda_paper_bf16/model.pt learned_full/model.pt; do
  if [ -f "$work/$f" ] && [ "$work" != "$out" ]; then mkdir -p "$out/$(dirname "$f")"; cp "$work/$f" "$out/$f"; fi
done
exit "$status"
