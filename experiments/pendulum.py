"""Pendulum swing-up with infinite-horizon HiREPS (paper Figs 16-18)."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Literal

import torch

from hireps_torch._linalg import reduce_each
from hireps_torch.algorithms import InfiniteHorizonHiREPS
from hireps_torch.envs._common import MemberTasks, ScalarActionBatchEnv
from hireps_torch.envs.pendulum import (
    PendulumParams,
    PendulumTask,
    SwingUpEvaluation,
    evaluate_swing_up,
    mirror_decisions,
    sample_start,
)
from hireps_torch.experiments.checkpoint import RunState
from hireps_torch.experiments.envstate import BatchedTaskState
from hireps_torch.experiments.options import (
    RunOptions,
    check_fourier_bases,
    check_options,
    check_variance_floor,
    member_seeds,
    option_error,
    stream_seed,
)
from hireps_torch.experiments.runner import (
    Experiment,
    Run,
    check_budget,
    infinite_horizon_postfix,
    resume_point,
)
from hireps_torch.features import ConcatFeatures, FeatureMap, FourierFeatures, QuadraticFeatures
from hireps_torch.policies import ConstantGating, HierarchicalPolicy
from hireps_torch.rollout import (
    make_collector,
    member_transitions,
    policy_module,
    shutdown_collector,
)

__all__ = [
    "PendulumConfig",
    "epsilon_at",
    "build_pendulum_policy",
    "pendulum_quadratic_features",
    "pendulum_value_features",
    "EXPERIMENT",
    "run",
]


@dataclass(frozen=True)
class PendulumConfig(RunOptions):
    """Pendulum swing-up with infinite-horizon HiREPS (paper Figs 16-18)."""

    gating: Literal["learned", "constant", "flat"] = "learned"
    """learned: softmax gating on the squared state expansion; constant: k-means over 1000
    states uniform in +-[pi, 50], frozen; flat: one linear-Gaussian policy on the gating's
    features."""
    n_options: int = 5
    """Number of options (ignored for flat)."""
    steps_per_decision: int = 5
    """d: control steps (at 100 Hz) per decision."""
    restart_probability: float | None = None
    """Restart probability per decision, 1 - gamma (None: the paper's 0.02 / d)."""
    episodes: int = 1000
    """Total episodes (episode_seconds of experience per parallel pendulum each)."""
    episodes_per_iteration: int = 20
    """Episodes per policy update = parallel pendulums."""
    episode_seconds: float = 10.0
    """Simulated time per episode (s): one pendulum's experience between two updates."""
    kp: float = 60.0
    """PD controller stiffness (N m / rad)."""
    kd: float = 10.0
    """PD controller damping (N m s / rad)."""
    start_noise: float = 0.1
    """Std of the start perturbation around hanging down (rad and rad/s)."""
    reset_each_iteration: bool = False
    """Restart every iteration's episodes (off: the pendulums run on across iterations)."""
    epsilon: float = 0.5
    """KL bound of the first update (nats)."""
    epsilon_end: float | None = 0.1
    """KL bound of the last update (nats), linear from epsilon at the first (None: epsilon
    throughout; why 0.1: benchmarks/README.md, "Pendulum defaults")."""
    kappa_rel: float = 0.9
    """Entropy bound relative to the mean responsibility entropy (learned gating only)."""
    init_std: float = 1.5
    """Initial exploration std of the desired angle (rad)."""
    mirror_samples: bool = True
    """Also update on the mirror image (-theta, -theta', -desired angle) of every decision (not
    in the paper; why: benchmarks/README.md, "Pendulum defaults")."""
    init_means: Literal["spaced", "random"] = "spaced"
    """Initial option means (desired angles): spaced over [-2 pi, 2 pi], or random (init_std)."""
    min_variance: float = 1e-4
    """Floor on the option variance (rad^2)."""
    fourier_bases: int = 5
    """Fourier bases per state dimension of the value features."""
    value_features: Literal["fourier", "fourier+quadratic"] = "fourier+quadratic"
    """Value features: the Fourier basis alone, or next to the gating's squared expansion."""
    max_velocity: float = 10.0
    """Velocity range (rad/s) the Fourier and gating features are scaled to."""
    workers: int = 1
    """Collector worker processes (1: torchrl Collector in this process; >1: MultiSyncCollector,
    whose workers draw the noise: another run of the same seed)."""
    eval_rollouts: int = 50
    """Noise-free evaluation rollouts (5 s each), at the end and every eval_every iterations."""
    eval_every: int = 5
    """Evaluate the noise-free policy every this many iterations (columns eval_success_rate
    and eval_return, nan in the other rows; 0: never during training). The final policy is
    evaluated too, into summary.json, whose episodes_to_success is the first evaluation (the
    final included) with success >= 0.9."""


def epsilon_at(cfg: PendulumConfig, update: int, updates: int) -> float:
    """The KL bound of update ``update`` (0-based) of ``updates``: linear from ``epsilon`` to
    ``epsilon_end`` (``epsilon`` throughout when that is None or there is one update)."""
    if cfg.epsilon_end is None or updates <= 1:
        return cfg.epsilon
    t = min(max(update, 0), updates - 1) / (updates - 1)
    return cfg.epsilon + t * (cfg.epsilon_end - cfg.epsilon)


MAX_DECISIONS = 10**6
"""The most decisions one pendulum episode (``episode_seconds``) may hold."""


def pendulum_quadratic_features(cfg: PendulumConfig) -> QuadraticFeatures:
    """The squared expansion of (theta / pi, theta' / max_velocity): (N, 2) -> (N, 5)."""
    return QuadraticFeatures(2, scale=torch.tensor([math.pi, cfg.max_velocity]))


def pendulum_value_features(cfg: PendulumConfig) -> FeatureMap:
    """Periodic Fourier basis of (theta, theta') on [-pi, pi] x [-max_velocity, max_velocity],
    plus the squared expansion when ``cfg.value_features == "fourier+quadratic"``."""
    vmax = cfg.max_velocity
    fourier = FourierFeatures(
        [-math.pi, -vmax], [math.pi, vmax], cfg.fourier_bases, periodic=[True, False]
    )
    if cfg.value_features == "fourier":
        return fourier
    return ConcatFeatures(fourier, pendulum_quadratic_features(cfg))


def build_pendulum_policy(cfg: PendulumConfig, generator: torch.Generator) -> HierarchicalPolicy:
    """The policy of one gating kind: options linear in (theta, theta') -> desired angle."""
    quad = pendulum_quadratic_features(cfg)
    std = torch.tensor([cfg.init_std], dtype=torch.float64)
    if cfg.gating == "flat":
        return HierarchicalPolicy.create(
            1, 2, 1, init_std=std, policy_features=quad, min_variance=cfg.min_variance
        )
    gating = None
    if cfg.gating == "constant":  # k-means on the raw state, as in the paper
        box = torch.tensor([math.pi, 50.0], dtype=torch.float64)
        points = (2 * torch.rand(1000, 2, generator=generator, dtype=torch.float64) - 1) * box
        seed = int(torch.randint(0, 2**31 - 1, (1,), generator=generator))
        gating = ConstantGating.from_kmeans(points, cfg.n_options, seed=seed)
    init_mean = None
    if cfg.init_means == "spaced":  # cell centres of [-2 pi, 2 pi]
        cells = (torch.arange(cfg.n_options, dtype=torch.float64) + 0.5) / cfg.n_options
        init_mean = (4.0 * cells - 2.0)[:, None] * math.pi
    return HierarchicalPolicy.create(
        cfg.n_options,
        2,
        1,
        init_mean=init_mean,
        init_std=std,
        gating_features=quad if gating is None else None,
        min_variance=cfg.min_variance,
        generator=generator,
        gating=gating,
    )


def _make_algorithm(
    cfg: PendulumConfig, params: PendulumParams, seeds: list[int]
) -> InfiniteHorizonHiREPS:
    """The members' algorithm, member s's from the streams of ``seeds[s]``."""
    gens = [torch.Generator().manual_seed(stream_seed(s, "policy")) for s in seeds]
    policy = HierarchicalPolicy.stack([build_pendulum_policy(cfg, g) for g in gens])
    algo = InfiniteHorizonHiREPS(
        policy,
        pendulum_value_features(cfg),
        torch.stack([sample_start(1000, params, g) for g in gens]),
        gamma=params.gamma,
        epsilon=cfg.epsilon,
        kappa_rel=cfg.kappa_rel if cfg.gating == "learned" else None,
        prune_threshold=1e-4 if cfg.gating == "learned" else 0.0,
        seed=[stream_seed(s, "sampling") for s in seeds],
    )
    algo.seeds = seeds  # names the members in warnings
    return algo


def _checked(cfg: PendulumConfig) -> tuple[PendulumParams, int]:
    """The task constants and the number of iterations of ``cfg`` (every option checked)."""
    check_options(
        cfg,
        counts=("eval_rollouts",),
        positive=("episode_seconds", "init_std", "max_velocity", "kp", "epsilon", "epsilon_end"),
        nonnegative=("kd", "start_noise", "eval_every"),
    )
    check_variance_floor(cfg)
    check_fourier_bases(cfg, 2)
    p = cfg.restart_probability
    if p is not None and not 0.0 < p < 1.0:  # the dual needs restarts: gamma < 1
        raise option_error("restart_probability", p, "in (0, 1), or None for 0.02 / d")
    B = cfg.episodes_per_iteration
    iterations = check_budget(
        cfg.episodes,
        B,
        n_options=cfg.n_options,
        steps_per_decision=cfg.steps_per_decision,
        workers=cfg.workers,
    )
    params = PendulumParams(
        steps_per_decision=cfg.steps_per_decision,
        kp=cfg.kp,
        kd=cfg.kd,
        start_noise=cfg.start_noise,
        restart_probability=cfg.restart_probability,
    )
    if cfg.episode_seconds / params.decision_seconds > MAX_DECISIONS:
        raise option_error(
            "episode_seconds",
            cfg.episode_seconds,
            f"at most {MAX_DECISIONS:.0e} decisions of {params.decision_seconds} s",
        )
    if cfg.workers > 1 and cfg.seeds is not None:
        raise option_error("workers", cfg.workers, "1 for a population (one batched process)")
    if cfg.workers > 1 and B % cfg.workers:
        raise ValueError(
            f"episodes_per_iteration ({B}) must be divisible by workers ({cfg.workers})"
        )
    return params, iterations


def algorithm(cfg: PendulumConfig) -> InfiniteHorizonHiREPS:
    """``cfg`` checked as :func:`run` checks it, and the untrained algorithm it starts from."""
    params, _ = _checked(cfg)
    return _make_algorithm(cfg, params, member_seeds(cfg))


def run(cfg: PendulumConfig) -> dict[str, Any]:
    """Infinite-horizon HiREPS on the swing-up, one seed or a population; returns the summary."""
    params, iterations = _checked(cfg)
    resume = resume_point(EXPERIMENT, cfg)
    B, d = cfg.episodes_per_iteration, params.steps_per_decision
    seeds = member_seeds(cfg)
    S = len(seeds)
    algo = _make_algorithm(cfg, params, seeds).to(cfg.device)
    policy, dev = algo.policy, algo.device
    decisions = max(1, round(cfg.episode_seconds / params.decision_seconds))
    frames = S * B * decisions
    # each member explores with its own generator (worker processes: their own global RNGs)
    actor = policy_module(policy, generator=algo.generator if cfg.workers == 1 else None)
    collector = make_collector(
        lambda: ScalarActionBatchEnv(
            MemberTasks(
                [
                    PendulumTask(B // cfg.workers, params, seed=stream_seed(s, "env"), device=dev)
                    for s in seeds
                ]
            )
        ),
        actor,
        frames_per_batch=frames,
        total_frames=frames * iterations,
        num_workers=cfg.workers,
        reset_at_each_iter=cfg.reset_each_iteration,
        seed=stream_seed(seeds[0], "env") if cfg.workers > 1 else None,
    )
    n_opt = cfg.n_options if cfg.gating != "flat" else 1
    label = f"pendulum/{cfg.gating}/{n_opt}opt/d{cfg.steps_per_decision}"
    state = RunState(algo, env=BatchedTaskState(collector, carry=not cfg.reset_each_iteration))
    eval_seeds = [stream_seed(s, "eval") for s in seeds]

    def evaluate() -> list[SwingUpEvaluation]:
        """Each member's noise-free policy on ``eval_rollouts`` swing-ups."""
        return evaluate_swing_up(
            lambda x: policy.mean_action(x.to(dev))[0].cpu(),
            params,
            n_rollouts=cfg.eval_rollouts,
            seed=eval_seeds,
        )

    try:
        with Run(EXPERIMENT, cfg, state, resume) as run:
            batches = iter(collector)
            for it in run.iterations(iterations, label, infinite_horizon_postfix):
                s, a, r, s_next, terminated = member_transitions(next(batches), S)
                average = (reduce_each(r, "mean", -1) / d).tolist()
                if cfg.mirror_samples:
                    s, a, r, s_next, terminated = mirror_decisions(s, a, r, s_next, terminated)
                epsilon = epsilon_at(cfg, it, iterations)  # the KL schedule
                diag = algo.update(s, a, r, s_next, terminated, epsilon=epsilon)
                if cfg.workers > 1:
                    collector.update_policy_weights_()
                due = cfg.eval_every > 0 and (it + 1) % cfg.eval_every == 0
                evs = evaluate() if due else None
                run.log(
                    [
                        {
                            "iteration": it + 1,
                            "episodes": (it + 1) * B,
                            "average_return": average[m],
                            "eval_success_rate": math.nan if evs is None else evs[m].success_rate,
                            "eval_return": math.nan if evs is None else evs[m].average_return,
                        }
                        | {key: value[m] for key, value in diag.items()}
                        for m in range(S)
                    ]
                )
            final = evaluate()
            active = policy.active.sum(-1).tolist()
            summaries = [
                _summary(c, r, ev, iterations, int(n))
                for c, r, ev, n in zip(run.configs, run.rows, final, active, strict=True)
            ]
            return run.finish(summaries, title=label)
    finally:
        shutdown_collector(collector)


def _summary(
    cfg: PendulumConfig,
    rows: list[dict[str, Any]],
    ev: SwingUpEvaluation,
    iterations: int,
    n_active: int,
) -> dict[str, Any]:
    """A run's ``summary.json`` from its rows and final noise-free evaluation ``ev``."""
    B = cfg.episodes_per_iteration
    first_success = next(
        (int(w["episodes"]) for w in rows if float(w["eval_success_rate"]) >= 0.9),
        iterations * B if ev.success_rate >= 0.9 else None,  # seen first by the final one
    )
    return {
        "experiment": "pendulum",
        "gating": cfg.gating,
        "n_options": cfg.n_options if cfg.gating != "flat" else 1,
        "steps_per_decision": cfg.steps_per_decision,
        "seed": cfg.seed,
        "episodes": iterations * B,
        "iterations": iterations,
        "final_average_return": rows[-1]["average_return"],
        "final_return": ev.average_return,
        "success_rate": ev.success_rate,
        "episodes_to_success": first_success,
        "time_to_upright": ev.time_to_upright,
        "reached_upright_share": ev.reached_share,
        "n_active_options": n_active,
    }


EXPERIMENT = Experiment(
    "pendulum", PendulumConfig, run, algorithm, metric="success_rate", curve="average_return"
)
