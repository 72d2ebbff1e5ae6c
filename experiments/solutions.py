"""Tasks with several solutions (the four-goal planar arm, tetherball): does the policy keep
them apart?

HiREPS (the paper's, with its entropy bound), the same mixture without the bound
(``hireps-unbounded``, the paper's "naive hierarchical policy"), REPS and CMA-ES on the same
task, seeds and episode budget (CMA-ES on the arm only: it searches one parameter vector, not
a policy over contexts). Every iteration logs the update's diagnostics, the noise-free
policy's return and the versatility of the policy's samples (:mod:`hireps_torch.versatility`:
success rate, purity, solutions held, behaviour entropy).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Literal

import torch

from hireps_torch.algorithms import CMAES, REPS, EpisodicHiREPS
from hireps_torch.envs.planar_arm import PlanarArm
from hireps_torch.envs.tetherball import Tetherball
from hireps_torch.experiments.checkpoint import RunState
from hireps_torch.experiments.options import (
    RunOptions,
    check_options,
    check_variance_floor,
    member_seeds,
    stream_seed,
)
from hireps_torch.experiments.runner import Experiment, Run, check_budget, resume_point
from hireps_torch.versatility import policy_versatility

__all__ = ["EXPERIMENTS", "PlanarArmConfig", "SolutionsConfig", "TetherballConfig", "run"]

AlgorithmName = Literal["hireps", "hireps-unbounded", "hireps-versatile", "reps", "cmaes"]


@dataclass(frozen=True)
class SolutionsConfig(RunOptions):
    """Options shared by the tasks with several solutions."""

    init_std: float = 1.0
    """Initial standard deviation of the parameters."""
    tolerance: float = 0.1
    """A solution is reached within this distance (m)."""
    algorithm: AlgorithmName = "hireps"
    """hireps: options with the entropy bound; hireps-unbounded: without it; hireps-versatile:
    with it and a floor on the options' prior entropy; reps: one Gaussian; cmaes: CMA-ES
    (pycma), one Gaussian."""
    n_options: int = 20
    """Initial number of options (hireps, hireps-unbounded); low-mass options are pruned."""
    epsilon: float = 0.5
    """KL bound per iteration (not cmaes)."""
    kappa_rel: float = 0.9
    """Entropy bound as a fraction of the current mean responsibility entropy (hireps)."""
    entropy_floor: float = 0.5
    """hireps-versatile: the options' prior keeps an entropy of at least this fraction of
    log(n_options), or its current entropy where that is lower."""
    samples_per_iteration: int = 100
    """Episodes per policy update (cmaes: its population size)."""
    episodes: int = 10000
    """Total number of episodes."""
    min_variance: float = 1e-6
    """Floor on the option covariance eigenvalues (not cmaes)."""
    versatility_samples: int = 500
    """Samples of the policy drawn after every update to measure its versatility (their
    episodes are not learned from and not counted in episodes)."""


@dataclass(frozen=True)
class PlanarArmConfig(SolutionsConfig):
    """Four-goal planar arm (10 joints, goals at (+-7, 0), (0, +-7)): how many goals held."""

    init_std: float = 0.5
    """Initial standard deviation of joints 2-10 (rad)."""
    base_std: float = math.pi
    """Initial standard deviation of the base joint (rad): the options start spread around."""
    posture_cost: float = 0.01
    """Cost per squared angle of joints 2-10."""
    tolerance: float = 0.5
    """A goal is reached within this distance (m)."""


@dataclass(frozen=True)
class TetherballConfig(SolutionsConfig):
    """Tetherball: hit a ball on a string around a pole to a target behind it, on either side."""

    algorithm: Literal["hireps", "hireps-unbounded", "hireps-versatile", "reps"] = "hireps"
    """hireps: options with the entropy bound; hireps-unbounded: without it; hireps-versatile:
    with it and a floor on the options' prior entropy; reps: one linear-Gaussian policy."""
    n_options: int = 30
    """Initial number of options (the paper's 30); low-mass options are pruned."""
    init_std: float = 2.0
    """Initial standard deviation of the impulse (m/s)."""
    effort: float = 0.002
    """Cost per squared impulse (s^2/m^2)."""
    tolerance: float = 0.1
    """The target is reached within this distance (m)."""


Task = PlanarArm | Tetherball


def make_task(cfg: SolutionsConfig) -> Task:
    """The task of ``cfg``."""
    if isinstance(cfg, TetherballConfig):
        return Tetherball(effort=cfg.effort, tolerance=cfg.tolerance)
    assert isinstance(cfg, PlanarArmConfig)
    return PlanarArm(posture_cost=cfg.posture_cost, tolerance=cfg.tolerance)


def _check(cfg: SolutionsConfig) -> int:
    """``cfg`` checked; its iterations."""

    def has(*names: str) -> tuple[str, ...]:  # the options of this task's config
        return tuple(n for n in names if hasattr(cfg, n))

    check_options(
        cfg,
        counts=("n_options", "versatility_samples"),
        positive=("epsilon", "init_std", "tolerance", *has("base_std")),
        nonnegative=("kappa_rel", "entropy_floor", *has("posture_cost", "effort")),
    )
    if cfg.entropy_floor > 1:
        raise ValueError(f"entropy_floor must be in [0, 1], got {cfg.entropy_floor}")
    check_variance_floor(cfg)
    return check_budget(cfg.episodes, cfg.samples_per_iteration, "samples_per_iteration", 2)


def _make_algorithm(cfg: SolutionsConfig, task: Task, seeds: list[int]) -> Any:
    """The algorithm of ``cfg`` for the members with ``seeds`` (their policy streams)."""
    std = torch.full((task.param_dim,), cfg.init_std, dtype=torch.float64)
    if isinstance(cfg, PlanarArmConfig):
        std[0] = cfg.base_std
    seed = [stream_seed(s, "policy") for s in seeds]  # a run is a population of one
    if cfg.algorithm == "cmaes":
        return CMAES.create(
            task.param_dim, popsize=cfg.samples_per_iteration, init_std=std, seed=seed
        )
    common: dict[str, Any] = dict(
        context_dim=task.context_dim,
        init_std=std,
        epsilon=cfg.epsilon,
        min_variance=cfg.min_variance,
        seed=seed,
    )
    if cfg.algorithm == "reps":
        algo: EpisodicHiREPS = REPS.create(task.param_dim, **common)
    else:
        algo = EpisodicHiREPS.create(
            task.param_dim,
            n_options=cfg.n_options,
            kappa_rel=None if cfg.algorithm == "hireps-unbounded" else cfg.kappa_rel,
            prior_entropy_floor=cfg.entropy_floor if cfg.algorithm == "hireps-versatile" else None,
            **common,
        )
    algo.seeds = seeds  # names the members in warnings
    return algo


def algorithm(cfg: SolutionsConfig) -> Any:
    """``cfg`` checked as :func:`run` checks it, and the untrained algorithm it starts from."""
    _check(cfg)
    return _make_algorithm(cfg, make_task(cfg), member_seeds(cfg))


def run(cfg: SolutionsConfig) -> dict[str, Any]:
    """One algorithm on a task with several solutions, one seed or a population; returns the
    summary."""
    iterations = _check(cfg)
    entry = next(e for e in EXPERIMENTS if type(cfg) is e.config)
    resume = resume_point(entry, cfg)
    task = make_task(cfg)
    seeds = member_seeds(cfg)
    S, n = len(seeds), cfg.samples_per_iteration
    algo = _make_algorithm(cfg, task, seeds).to(cfg.device)
    dev = algo.device
    context_gens = [torch.Generator().manual_seed(stream_seed(s, "contexts")) for s in seeds]
    generators = {f"contexts{m}": g for m, g in enumerate(context_gens)}
    C = task.context_dim

    def contexts(count: int, gens: list[torch.Generator]) -> torch.Tensor:
        """``(S, count, C)`` contexts drawn by each member's generator (C may be 0)."""
        return torch.stack([task.sample_contexts(count, g) for g in gens]).to(dev)

    def score(ctx: torch.Tensor, theta: torch.Tensor) -> torch.Tensor:
        """The task's returns ``(S, N)`` on the algorithm's device (it computes on the CPU)."""
        return task(ctx.cpu(), theta.cpu()).to(dev)

    def measure(it: int) -> dict[str, list[float]]:
        """Versatility of the current policy from ``versatility_samples`` of its samples,
        drawn from iteration ``it``'s part of the "eval" stream (no update depends on it)."""
        gens = [torch.Generator().manual_seed(stream_seed(s, "eval", it)) for s in seeds]
        ctx = contexts(cfg.versatility_samples, gens)
        return policy_versatility(algo.policy, task, ctx, gens)

    evaluation = None  # the contexts of the noise-free policy's evaluation (none: the arm)
    if isinstance(task, Tetherball):
        grid = torch.linspace(-task.context_range, task.context_range, 7, dtype=torch.float64)
        evaluation = grid[:, None].expand(S, -1, -1).to(dev)
    label = f"{entry.name}/{cfg.algorithm}"
    with Run(entry, cfg, RunState(algo, generators=generators), resume) as run:
        for it in run.iterations(iterations, label, _postfix):
            ctx = contexts(n, context_gens)
            theta = algo.ask(ctx if C else n)
            diag = algo.tell(ctx if C else None, theta, score(ctx, theta))
            if evaluation is None:  # no context: the mean of the most probable option
                evals = score(ctx[..., :1, :], algo.act(1)).reshape(S).tolist()
            else:  # its mean over a grid of contexts
                evals = score(evaluation, algo.act(evaluation)).mean(-1).reshape(S).tolist()
            held = measure(it)
            run.log(
                [
                    {"iteration": it + 1, "episodes": (it + 1) * n, "eval_return": evals[m]}
                    | {key: value[m] for key, value in diag.items()}
                    | {key: value[m] for key, value in held.items()}
                    for m in range(S)
                ]
            )
        summaries = [
            {
                "experiment": entry.name,
                "algorithm": cfg.algorithm,
                "seed": c.seed,
                "episodes": iterations * n,
                "iterations": iterations,
                "final_return": rows[-1]["eval_return"],
                "final_mean_return": rows[-1]["mean_return"],
                "n_active_options": rows[-1]["n_active_options"],
                **{key: rows[-1][key] for key in held},
                "solutions_at_first_success": _at_first_success(rows),
            }
            for c, rows in zip(run.configs, run.rows, strict=True)
        ]
        return run.finish(summaries, title=f"{entry.name} ({cfg.algorithm})")


def _at_first_success(rows: list[dict[str, Any]]) -> float | None:
    """Solutions held at the first iteration whose samples succeed at least half of the time
    (None: never)."""
    return next((r["solutions_found"] for r in rows if r["success_rate"] >= 0.5), None)


def _postfix(row: dict[str, Any]) -> dict[str, Any]:
    return {
        "ret": f"{row['mean_return']:.3f}",
        "ok": f"{row['success_rate']:.2f}",
        "held": f"{row['solutions_found']:.1f}",
        "opts": row["n_active_options"],
    }


EXPERIMENTS = (
    Experiment(
        "planar-arm",
        PlanarArmConfig,
        run,
        algorithm,
        metric="solutions_found",
        curve="solutions_found",
        curves=("mean_return", "eval_return", "solutions_found"),
        per_iteration="samples_per_iteration",
    ),
    Experiment(
        "tetherball",
        TetherballConfig,
        run,
        algorithm,
        metric="solutions_found",
        curve="solutions_found",
        curves=("mean_return", "eval_return", "solutions_found"),
        per_iteration="samples_per_iteration",
    ),
)
