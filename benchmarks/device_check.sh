#!/bin/bash
# The GPU checks, as one command on a lent GPU machine (the `device` tool's `run`, with the
# cp312 wheels of torchrl, tensordict, gymnasium, tyro and their needs carried in .whl/):
#   bash benchmarks/device_check.sh [sizes] [episodes]
# 1. the CUDA tests (tests/test_device.py, the device cases of the env and sweep tests);
# 2. benchmarks/population_scaling.py: pendulum populations of 1, 100 and 1000 seeds on cuda.
set -o pipefail
OUT=${OUT:-/tmp/device_out}
mkdir -p "$OUT"
if [ -d .whl ]; then
    python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade \
        --target /tmp/site .whl/*.whl || exit 1
    export PYTHONPATH=/tmp/site
fi
export PYTHONPATH=$PYTHONPATH:$PWD PYTHONUNBUFFERED=1
nvidia-smi -L
python3 -c "import torch, torchrl, tensordict; print('torch', torch.__version__, 'torchrl',
torchrl.__version__, 'tensordict', tensordict.__version__, 'cuda', torch.cuda.is_available())" \
    || exit 1
timeout 150 python3 -m pytest -q -p no:cacheprovider -rs tests/test_device.py \
    tests/environments/test_env_hostile.py tests/test_sweep.py::test_a_refused_sweep_writes_nothing \
    2>&1 | tee "$OUT/tests.log" | tail -40
timeout 320 python3 benchmarks/population_scaling.py --device cuda --sizes "${1:-1,100,1000}" \
    --episodes "${2:-200}" --out /tmp/scaling 2>&1 | grep -v '^|' | tee "$OUT/scaling.log"
newest=$(ls -td /tmp/scaling/*/ 2>/dev/null | head -1)  # this call's (a warm machine keeps older)
[ -n "$newest" ] && cp "${newest}results.json" "$OUT/scaling.json"
exit 0
