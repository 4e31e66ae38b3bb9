#!/usr/bin/env bash
# The fast engine on a GPU against the JAX peer (benchmarks/gpu_check.py says what each row is).
#
# On a machine with network, once, from the repository's root: fetch the wheels a GPU machine
# with PyTorch, JAX and nvcc but without this project's other dependencies lacks (Python 3.12,
# x86-64 Linux; into .whl/, which git ignores):
#     bash benchmarks/gpu_check.sh --fetch
# Then on the GPU machine, from a copy of the repository with .whl/ (no network needed; a few
# minutes on an H200):
#     bash benchmarks/gpu_check.sh                    # the table; PYTHONUNBUFFERED, so rows as measured
#     bash benchmarks/gpu_check.sh --device cpu --quick   # the same rows on the CPU (a slow test runs this)
# Without nvcc there, set DRONE_TORCHRL_CUDA_LIBRARY to a CUDA engine built elsewhere
# (python -c "from pathlib import Path; from drone_torchrl.kernels import build; print(build.build_cuda(Path('x.so')))").
set -euo pipefail
cd "$(dirname "$0")/.."
# The versions this project's CI installs; pure-Python ones (any) and cp312 builds.
WHEELS=(torchrl==0.14.1 tensordict==0.14.3 hoptorch==0.1.4 pyvers==0.2.3 orjson==3.13.0 importlib_metadata==10.2.0
        hydra-core==1.3.8 omegaconf==2.3.1 gymnasium==1.4.0
        farama-notifications==0.0.6 google-crc32c==1.9.0)
if [ "${1:-}" = "--fetch" ]; then
    exclude=$(git rev-parse --git-path info/exclude 2>/dev/null || echo .git/info/exclude)
    mkdir -p "$(dirname "$exclude")" && { grep -qx '/.whl/' "$exclude" 2>/dev/null || echo '/.whl/' >> "$exclude"; }
    python3 -m pip download --no-deps --only-binary=:all: --python-version 3.12 --implementation cp \
        --platform manylinux_2_28_x86_64 --platform manylinux_2_17_x86_64 --platform manylinux2014_x86_64 \
        --platform manylinux1_x86_64 --platform any -d .whl "${WHEELS[@]}"
    # OmegaConf's parser runtime is published as a source archive only: built here (pure Python).
    python3 -m pip wheel -q --no-deps -w .whl antlr4-python3-runtime==4.9.3
    du -sh .whl
    exit 0
fi
if ! python3 -c "import torchrl, tensordict, hydra" 2> /dev/null && ls .whl/*.whl > /dev/null 2>&1; then
    python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/drone_site .whl/*.whl
    export PYTHONPATH="/tmp/drone_site:${PYTHONPATH:-}"
fi
export PYTHONPATH="$PWD:${PYTHONPATH:-}" PYTHONUNBUFFERED=1 SDL_VIDEODRIVER=dummy SDL_AUDIODRIVER=dummy
exec python3 benchmarks/gpu_check.py "$@"
