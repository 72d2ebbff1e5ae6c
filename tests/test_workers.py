"""Worker processes: a multi-process collector acts with the updated policy after a weight
sync, and the interpreter exits afterwards."""

import ast
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]

SCRIPT = textwrap.dedent(
    """
    import torch
    from hireps_torch.envs.pendulum import PendulumSwingUpBatchEnv
    from hireps_torch.policies import HierarchicalPolicy
    from hireps_torch.rollout import make_collector, policy_module, shutdown_collector

    def make_env():
        return PendulumSwingUpBatchEnv(2, seed=0)

    if __name__ == "__main__":
        pol = HierarchicalPolicy.create(1, 2, 1, init_std=torch.tensor([1e-6], dtype=torch.float64))
        collector = make_collector(make_env, policy_module(pol, deterministic=True),
                                   frames_per_batch=8, total_frames=24, num_workers=2)
        means = []
        try:
            for i, batch in enumerate(collector):
                means.append(float(batch["action"].float().mean()))
                pol.sub_policies[0].bias.fill_(0.5 * (i + 1))   # the update, in this process
                collector.update_policy_weights_()               # ... sent to the workers
        finally:
            shutdown_collector(collector)
        print("MEANS", means)
    """
)


@pytest.mark.slow
def test_workers_act_with_the_updated_policy_after_a_weight_sync(tmp_path):
    script = tmp_path / "workers.py"
    script.write_text(SCRIPT)
    p = subprocess.run(
        [sys.executable, str(script)],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=240,
        env={"PYTHONPATH": str(ROOT), "OMP_NUM_THREADS": "1", "PATH": "/usr/bin:/bin"},
    )
    assert p.returncode == 0, p.stderr
    means = ast.literal_eval(p.stdout.split("MEANS", 1)[1].strip())
    assert len(means) == 3
    # batch 0 with the initial policy (mean 0), then every batch with the last synced update
    assert abs(means[0]) < 1e-6
    assert abs(means[1] - 0.5) < 1e-6 and abs(means[2] - 1.0) < 1e-6


ORPHAN_SCRIPT = textwrap.dedent(
    """
    import functools, threading, time
    from hireps_torch.experiments.workers import LocalProcessPool

    if __name__ == "__main__":
        # workers busy building their environment (a ten-minute sleep) when the parent dies
        pool = LocalProcessPool(functools.partial(time.sleep, 600), workers=2)
        threading.Thread(target=pool.play, args=(None, 0, [0, 1], 1), daemon=True).start()
        while pool.pool._executor is None or len(pool.pool._executor._processes) < 2:
            time.sleep(0.05)
        print(*pool.pool._executor._processes, flush=True)
        time.sleep(600)
    """
)


def _alive(pid):
    try:
        with open(f"/proc/{pid}/stat") as f:
            return f.read().rsplit(")", 1)[1].split()[0] != "Z"
    except FileNotFoundError:
        return False


@pytest.mark.skipif(not Path("/proc").is_dir(), reason="reads /proc")
def test_a_pools_workers_end_when_their_parent_is_killed(tmp_path):
    """kill -9 of the process that owns a LocalProcessPool (hockey --workers N): its workers
    end within seconds (before: they waited on its queue for ever, ~490 MB each)."""
    import os
    import signal
    import time

    script = tmp_path / "orphans.py"
    script.write_text(ORPHAN_SCRIPT)
    p = subprocess.Popen([sys.executable, str(script)], stdout=subprocess.PIPE, text=True, cwd=ROOT)
    workers = [int(w) for w in p.stdout.readline().split()]
    try:
        assert len(workers) == 2
        time.sleep(1.0)
        p.kill()
        p.wait()
        deadline = time.time() + 60
        while time.time() < deadline and any(_alive(w) for w in workers):
            time.sleep(0.2)
        assert not any(_alive(w) for w in workers), "a worker outlived its parent"
    finally:
        for w in workers:
            if _alive(w):
                os.kill(w, signal.SIGKILL)
