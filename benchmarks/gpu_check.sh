#!/usr/bin/env bash
# The GPU check behind docs/performance.md's "On a GPU" tables: this checkout, and optionally a
# baseline commit, each running its own bench_render.py; then bench_textures.py and the tests that
# exercise the JAX stages. Everything runs on JAX's default device: a GPU where jax is installed
# with CUDA (there the JAX stages render, as the native kernels are CPU-only).
#
#   bash benchmarks/gpu_check.sh [BASELINE_COMMIT] [OUT_DIR]
#
# OUT_DIR (default gpu_check/) receives one log per step. QUICK=1: 256² only and a few repeats
# (a smoke run); PYTHON picks the interpreter (default python3); JOBS the pytest workers (4).
set -uo pipefail
cd "$(dirname "$0")/.."
base=${1:-}
out=${2:-gpu_check}
py=${PYTHON:-python3}
mkdir -p "$out"
export PYTHONUNBUFFERED=1 XLA_PYTHON_CLIENT_PREALLOCATE=false
if [ -n "${QUICK:-}" ]; then
  render_args=(--quick --repeats 5)
  texture_args=(--repeats 3 --sizes 256)
else
  render_args=(--subdivisions 4 --repeats 30)
  texture_args=(--repeats 30)
fi
here=$PWD
with_path() { PYTHONPATH="$1${PYTHONPATH:+:$PYTHONPATH}" "${@:2}"; }

"$py" -c "import jax; print('jax', jax.__version__, jax.devices())" | tee "$out/device.txt"
if [ -n "$base" ]; then  # the baseline first, in a worktree of its own
  wt=$(mktemp -d)
  git worktree add -f --detach "$wt" "$base" >/dev/null || exit 1
  (cd "$wt" && with_path "$wt" "$py" benchmarks/bench_render.py "${render_args[@]}") 2>&1 | tee "$out/render_baseline.txt"
  git worktree remove --force "$wt"
fi
with_path "$here" "$py" benchmarks/bench_render.py "${render_args[@]}" 2>&1 | tee "$out/render.txt"
with_path "$here" "$py" benchmarks/bench_textures.py "${texture_args[@]}" 2>&1 | tee "$out/textures.txt"
with_path "$here" "$py" -m pytest -q -n "${JOBS:-4}" -p no:cacheprovider tests/test_raster.py tests/test_textures.py \
  tests/test_hard_cases.py tests/test_shading.py 2>&1 | tail -30 | tee "$out/tests.txt"
