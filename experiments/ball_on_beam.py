"""Ball on a beam with infinite-horizon HiREPS (paper Fig 19)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import torch

from hireps_torch.algorithms import InfiniteHorizonHiREPS
from hireps_torch.checks import check_positive_float
from hireps_torch.envs._common import MemberTasks, ScalarActionBatchEnv
from hireps_torch.envs.ball_on_beam import (
    BeamEvaluation,
    BeamParams,
    BeamTask,
    evaluate_beam,
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
from hireps_torch.policies import HierarchicalPolicy
from hireps_torch.rollout import (
    make_collector,
    member_transitions,
    policy_module,
    shutdown_collector,
)

__all__ = [
    "BallOnBeamConfig",
    "GoalBowlFeatures",
    "GoalOffsetFeatures",
    "closer_goal",
    "build_ball_on_beam_policy",
    "EXPERIMENT",
    "run",
    "value_features",
]


@dataclass(frozen=True)
class BallOnBeamConfig(RunOptions):
    """Ball on a beam with infinite-horizon HiREPS (paper Fig 19): 3 episodes per iteration."""

    n_options: int = 5
    """Number of linear-Gaussian options."""
    episodes: int = 30
    """Total episodes (20 s of experience per beam each)."""
    episodes_per_iteration: int = 3
    """Episodes per policy update = parallel beams."""
    epsilon: float = 1.0
    """KL bound per iteration (nats; why 1.0: benchmarks/README.md, "Ball on a beam defaults")."""
    kappa_rel: float | None = None
    """Entropy bound as a fraction of the mean responsibility entropy (None: off, the default
    here; why: benchmarks/README.md, "Ball on a beam defaults")."""
    init_std: float = 0.05
    """Initial exploration std of the desired beam angle (rad)."""
    min_variance: float = 1e-6
    """Floor on the option variance (rad^2)."""
    fourier_bases: int = 4
    """Fourier bases per state dimension of the value features."""
    fourier_coupling: int | None = None
    """Most state dimensions one Fourier term may couple (None: all; 1: no products)."""
    value_beam_angle: bool = False
    """Include the beam angle in the value features (off: a function of (x, x') only)."""
    value_goal_bowl: bool = True
    """Add GoalBowlFeatures (a bowl around the closer goal) to the value features."""
    option_goal_offset: bool = True
    """Options linear in GoalOffsetFeatures, the state seen from the closer goal
    (--no-option-goal-offset: in the state)."""
    max_velocity: float = 1.0
    """Ball speed (m/s) the value and gating features are scaled to."""
    eval_episodes: int = 10
    """Noise-free evaluation episodes after every iteration (alternating sides)."""


def build_ball_on_beam_policy(
    cfg: BallOnBeamConfig, generator: torch.Generator | None = None
) -> HierarchicalPolicy:
    """Options (x, x', alpha) -> desired beam angle, softmax gating on the squared expansion."""
    return HierarchicalPolicy.create(
        cfg.n_options,
        3,
        1,
        init_std=cfg.init_std,
        gating_features=QuadraticFeatures(3, scale=_beam_box(cfg)),
        policy_features=GoalOffsetFeatures(BeamParams()) if cfg.option_goal_offset else None,
        min_variance=cfg.min_variance,
        generator=generator,
    )


def _beam_box(cfg: BallOnBeamConfig) -> torch.Tensor:
    """(3,) half-widths of the state box the beam's features are scaled to."""
    p = BeamParams()
    return torch.tensor([p.half_length, cfg.max_velocity, p.max_angle])


def closer_goal(x: torch.Tensor, goal: float) -> torch.Tensor:
    """The goal ``+-goal`` on the ball's side (``+goal`` at ``x = 0``): (...,) -> (...,)."""
    g = x.new_tensor(goal)
    return torch.where(x >= 0, g, -g)


class GoalBowlFeatures(FeatureMap):
    """The quadratic bowl around the closer goal: ``(..., 3) -> (..., 3)``, ``[e^2, e v, v^2]``
    with ``e = (x - g) / half_length`` (``g = +-goal`` on the ball's side, ``+goal`` at
    ``x = 0``) and ``v = x' / max_velocity``.

    Args:
        params: the task (its goal and half length).
        max_velocity: ball speed (m/s) the velocity is scaled by.
    """

    def __init__(self, params: BeamParams, max_velocity: float = 1.0) -> None:
        super().__init__()
        self.in_features, self.out_features = 3, 3
        self.goal = float(params.goal)
        self.half_length = float(params.half_length)
        self.max_velocity = check_positive_float("max_velocity", max_velocity)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """x: (..., 3) states (x, x', alpha) -> (..., 3)."""
        x = self._input(x)
        goal = closer_goal(x[..., 0], self.goal)
        e = (x[..., 0] - goal) / self.half_length
        v = x[..., 1] / self.max_velocity
        return torch.stack([e * e, e * v, v * v], dim=-1)


class GoalOffsetFeatures(FeatureMap):
    """The state seen from the closer goal: ``(..., 3) -> (..., 3)``, ``[x - g, x', alpha]``
    (``g = +-goal`` on the ball's side, ``+goal`` at ``x = 0``).

    Args:
        params: the task (its goal).
    """

    def __init__(self, params: BeamParams) -> None:
        super().__init__()
        self.in_features, self.out_features = 3, 3
        self.goal = float(params.goal)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """x: (..., 3) states (x, x', alpha) -> (..., 3)."""
        x = self._input(x)
        goal = closer_goal(x[..., 0], self.goal)
        return torch.cat([(x[..., 0] - goal)[..., None], x[..., 1:]], dim=-1)


def value_features(cfg: BallOnBeamConfig) -> FeatureMap:
    """Fourier value features on the state box (the beam angle only with ``value_beam_angle``),
    then :class:`GoalBowlFeatures` with ``value_goal_bowl``."""
    box = _beam_box(cfg)
    n = cfg.fourier_bases
    bases = (n, n, n if cfg.value_beam_angle else 1)
    fourier = FourierFeatures(-box, box, bases, coupling=cfg.fourier_coupling)
    if not cfg.value_goal_bowl:
        return fourier
    return ConcatFeatures(fourier, GoalBowlFeatures(BeamParams(), cfg.max_velocity))


def _make_algorithm(
    cfg: BallOnBeamConfig, params: BeamParams, seeds: list[int]
) -> InfiniteHorizonHiREPS:
    """The members' algorithm, member s's from the streams of ``seeds[s]``."""
    gens = [torch.Generator().manual_seed(stream_seed(s, "policy")) for s in seeds]
    policy = HierarchicalPolicy.stack([build_ball_on_beam_policy(cfg, g) for g in gens])
    sides = torch.where(torch.arange(1000) % 2 == 0, 1.0, -1.0)
    algo = InfiniteHorizonHiREPS(
        policy,
        value_features(cfg),
        torch.stack([sample_start(sides, params, g) for g in gens]),
        gamma=params.gamma,
        epsilon=cfg.epsilon,
        kappa_rel=cfg.kappa_rel,
        seed=[stream_seed(s, "sampling") for s in seeds],
    )
    algo.seeds = seeds  # names the members in warnings
    return algo


def _checked(cfg: BallOnBeamConfig) -> int:
    """Every option of ``cfg`` checked; the number of iterations."""
    check_options(cfg, counts=("fourier_coupling",), positive=("init_std", "max_velocity"))
    check_variance_floor(cfg)
    check_fourier_bases(cfg, 3 if cfg.value_beam_angle else 2)
    if cfg.fourier_coupling is not None and cfg.fourier_coupling > 3:
        raise option_error("fourier_coupling", cfg.fourier_coupling, "in 1..3 (or None)")
    return check_budget(
        cfg.episodes,
        cfg.episodes_per_iteration,
        n_options=cfg.n_options,
        eval_episodes=cfg.eval_episodes,
    )


def algorithm(cfg: BallOnBeamConfig) -> InfiniteHorizonHiREPS:
    """``cfg`` checked as :func:`run` checks it, and the untrained algorithm it starts from."""
    _checked(cfg)
    return _make_algorithm(cfg, BeamParams(), member_seeds(cfg))


def run(cfg: BallOnBeamConfig) -> dict[str, Any]:
    """Infinite-horizon HiREPS on the ball on a beam (one seed or a population); its summary."""
    iterations = _checked(cfg)
    resume = resume_point(EXPERIMENT, cfg)
    B = cfg.episodes_per_iteration
    params = BeamParams()
    seeds = member_seeds(cfg)
    S = len(seeds)
    algo = _make_algorithm(cfg, params, seeds).to(cfg.device)
    policy, dev = algo.policy, algo.device
    frames = S * B * params.decisions_per_episode
    actor = policy_module(policy, generator=algo.generator)  # each member's own generator
    collector = make_collector(
        lambda: ScalarActionBatchEnv(
            MemberTasks(
                [BeamTask(B, params, seed=stream_seed(s, "env"), device=dev) for s in seeds]
            )
        ),
        actor,
        frames_per_batch=frames,
        total_frames=frames * iterations,
        reset_at_each_iter=True,
    )
    eval_seeds = [stream_seed(s, "eval") for s in seeds]
    label = f"ball-on-beam/{cfg.n_options}opt"
    state = RunState(algo, env=BatchedTaskState(collector, carry=False))
    try:
        with Run(EXPERIMENT, cfg, state, resume) as run:
            batches = iter(collector)
            for it in run.iterations(iterations, label, infinite_horizon_postfix):
                s, a, r, s_next, terminated = member_transitions(next(batches), S)
                diag = algo.update(s, a, r, s_next, terminated)
                evs: list[BeamEvaluation] = evaluate_beam(
                    lambda x: policy.mean_action(x.to(dev))[0].cpu(),
                    params,
                    n_episodes=cfg.eval_episodes,
                    seed=eval_seeds,
                )
                average, falls = (r.sum(-1) / B).tolist(), terminated.sum(-1).tolist()
                run.log(
                    [
                        {
                            "iteration": it + 1,
                            "episodes": (it + 1) * B,
                            "average_return": average[m],
                            "falls": int(falls[m]),
                            "eval_return": ev.average_return,
                            "eval_success_rate": ev.success_rate,
                        }
                        | {key: value[m] for key, value in diag.items()}
                        for m, ev in enumerate(evs)
                    ]
                )
            active = policy.active.sum(-1).tolist()
            summaries = [
                _summary(c, r, iterations, int(n))
                for c, r, n in zip(run.configs, run.rows, active, strict=True)
            ]
            return run.finish(summaries, title=label)
    finally:
        shutdown_collector(collector)


def _summary(
    cfg: BallOnBeamConfig, rows: list[dict[str, Any]], iterations: int, n_active: int
) -> dict[str, Any]:
    """A run's ``summary.json`` from its rows."""
    first_success = next((int(w["episodes"]) for w in rows if w["eval_success_rate"] >= 0.9), None)
    last = rows[-1]
    return {
        "experiment": "ball-on-beam",
        "n_options": cfg.n_options,
        "seed": cfg.seed,
        "episodes": iterations * cfg.episodes_per_iteration,
        "iterations": iterations,
        "final_average_return": last["average_return"],
        "final_eval_return": last["eval_return"],
        "final_return": last["eval_return"],
        "success_rate": last["eval_success_rate"],
        "episodes_to_success": first_success,
        "n_active_options": n_active,
    }


EXPERIMENT = Experiment(
    "ball-on-beam",
    BallOnBeamConfig,
    run,
    algorithm,
    metric="success_rate",
    curve="eval_return",
    curves=("average_return", "eval_return"),
)
