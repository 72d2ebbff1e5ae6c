"""Two-Gaussians toy task (AISTATS 2012): HiREPS keeps one option per mode, REPS picks one.

Every iteration also logs the versatility of ``versatility_samples`` samples of the policy
(:mod:`hireps_torch.versatility`: success rate, purity, modes held, behaviour entropy)."""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

import torch
from matplotlib.figure import Figure

from hireps_torch.algorithms import CMAES, REPS, EpisodicHiREPS
from hireps_torch.envs.toy import ContextualTwoGaussians, TwoGaussians
from hireps_torch.experiments.checkpoint import RunState
from hireps_torch.experiments.options import (
    RunOptions,
    check_options,
    check_variance_floor,
    member_seeds,
    stream_seed,
)
from hireps_torch.experiments.rundir import atomic_write
from hireps_torch.experiments.runner import Experiment, Run, check_budget, resume_point
from hireps_torch.versatility import policy_versatility

__all__ = [
    "BimodalConfig",
    "EXPERIMENT",
    "modes_covered",
    "option_summary",
    "plot_bimodal_options",
    "run",
]


@dataclass(frozen=True)
class BimodalConfig(RunOptions):
    """Two-Gaussians toy task (AISTATS 2012): HiREPS keeps one option per mode, REPS picks one."""

    algorithm: Literal["hireps", "hireps-unbounded", "hireps-versatile", "reps", "cmaes"] = "hireps"
    """hireps: mixture of linear-Gaussian options with the entropy bound; hireps-unbounded: the
    same without it; hireps-versatile: hireps with a floor on the options' prior entropy;
    reps: one Gaussian; cmaes: CMA-ES (pycma; without context only)."""
    contextual: bool = False
    """Use the contextual variant (1-D context, two linear solution families)."""
    n_options: int = 10
    """Initial number of options (hireps only); low-mass options are pruned."""
    epsilon: float = 1.0
    """KL bound per iteration."""
    kappa_rel: float = 0.8
    """Entropy bound as a fraction of the current mean responsibility entropy (hireps)."""
    entropy_floor: float = 0.5
    """hireps-versatile: the options' prior keeps an entropy of at least this fraction of
    log(n_options), or its current entropy where that is lower."""
    samples_per_iteration: int = 200
    """Episodes (parameter samples) per policy update."""
    episodes: int = 1600
    """Total number of episodes."""
    init_std: float = 2.0
    """Initial exploration standard deviation of every option."""
    bump_width: float = 1.0
    """Standard deviation of each reward bump."""
    min_variance: float = 1e-6
    """Floor on the option covariance eigenvalues."""
    versatility_samples: int = 500
    """Samples of the policy drawn after every update to measure its versatility (their
    episodes are not learned from and not counted in episodes)."""


def _validate(cfg: BimodalConfig) -> int:
    """``cfg`` checked; its iterations."""
    if cfg.algorithm == "cmaes" and cfg.contextual:
        raise ValueError(
            "algorithm cmaes searches one parameter vector: it takes no context (drop "
            "--contextual, or choose hireps, hireps-unbounded or reps)"
        )
    check_options(
        cfg,
        counts=("n_options", "versatility_samples"),
        positive=("bump_width", "init_std"),
        nonnegative=("entropy_floor",),
    )
    if cfg.entropy_floor > 1:
        raise ValueError(f"entropy_floor must be in [0, 1], got {cfg.entropy_floor}")
    check_variance_floor(cfg)
    return check_budget(cfg.episodes, cfg.samples_per_iteration, "samples_per_iteration", 2)


def _make_algorithm(
    cfg: BimodalConfig, task: TwoGaussians | ContextualTwoGaussians, seeds: list[int]
) -> EpisodicHiREPS | CMAES:
    """The algorithm of ``cfg`` for the members with ``seeds`` (their policy streams)."""
    if cfg.algorithm == "cmaes":
        return CMAES.create(
            task.param_dim,
            popsize=cfg.samples_per_iteration,
            init_std=cfg.init_std,
            seed=[stream_seed(s, "policy") for s in seeds],
        )
    common: dict[str, Any] = dict(
        context_dim=task.context_dim,
        init_std=cfg.init_std,
        epsilon=cfg.epsilon,
        min_variance=cfg.min_variance,
        seed=[stream_seed(s, "policy") for s in seeds],
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


def algorithm(cfg: BimodalConfig) -> EpisodicHiREPS | CMAES:
    """``cfg`` checked as :func:`run` checks it, and the untrained algorithm it starts from."""
    _validate(cfg)
    return _make_algorithm(cfg, _task(cfg), member_seeds(cfg))


def run(cfg: BimodalConfig) -> dict[str, Any]:
    """HiREPS or REPS on the (contextual) two-Gaussians task, one seed or a population;
    returns the summary."""
    iterations = _validate(cfg)
    resume = resume_point(EXPERIMENT, cfg)
    task = _task(cfg)
    seeds = member_seeds(cfg)
    S, n = len(seeds), cfg.samples_per_iteration
    algo = _make_algorithm(cfg, task, seeds).to(cfg.device)
    dev = algo.device
    ctx_gens = {
        f"contexts{m}": torch.Generator().manual_seed(stream_seed(s, "contexts"))
        for m, s in enumerate(seeds)
    }
    eval_ctx = torch.linspace(-1, 1, 21, dtype=torch.float64)[:, None] if cfg.contextual else None

    def score(ctx: torch.Tensor | None, theta: torch.Tensor) -> torch.Tensor:
        """The task's returns (S, N) on the algorithm's device (the task computes on the CPU)."""
        flat = theta.reshape(-1, task.param_dim).cpu()
        if isinstance(task, ContextualTwoGaussians):
            assert ctx is not None
            out = task(ctx.reshape(-1, 1).cpu(), flat)
        else:
            out = task(flat)
        return out.reshape(theta.shape[:2]).to(dev)

    def measure(it: int) -> dict[str, list[float]]:
        """Versatility of the policy from iteration ``it``'s part of the "eval" stream."""
        gens = [torch.Generator().manual_seed(stream_seed(s, "eval", it)) for s in seeds]
        M = cfg.versatility_samples
        if isinstance(task, ContextualTwoGaussians):
            ctx = torch.stack([task.sample_contexts(M, g) for g in gens]).to(dev)
        else:
            ctx = torch.zeros(S, M, 0, dtype=torch.float64, device=dev)
        return policy_versatility(algo.policy, task, ctx, gens)

    label = f"bimodal/{cfg.algorithm}"
    grid = None if eval_ctx is None else eval_ctx.expand(S, -1, -1).to(dev)
    with Run(EXPERIMENT, cfg, RunState(algo, generators=ctx_gens), resume) as run:
        for it in run.iterations(iterations, label, _postfix):
            ctx = None
            if isinstance(task, ContextualTwoGaussians):
                ctx = torch.stack([task.sample_contexts(n, g) for g in ctx_gens.values()]).to(dev)
                theta = algo.ask(ctx)
            else:
                theta = algo.ask(n)
            diag = algo.tell(ctx, theta, score(ctx, theta))
            evals = score(grid, algo.act(1 if grid is None else grid)).mean(-1).tolist()
            held = measure(it)
            run.log(
                [
                    {"iteration": it + 1, "episodes": (it + 1) * n, "eval_return": evals[m]}
                    | {key: value[m] for key, value in diag.items()}
                    | {key: value[m] for key, value in held.items()}
                    for m in range(S)
                ]
            )
        solo = [
            (EpisodicHiREPS if cfg.algorithm.startswith("hireps") else REPS)(
                algo.policy.member(m).cpu(), context_dim=task.context_dim, epsilon=cfg.epsilon
            )
            for m in range(S)
        ]
        if isinstance(task, TwoGaussians):
            for a, writer in zip(solo, run.writers, strict=True):
                plot_bimodal_options(a, task, writer.dir / "options.png")
        summaries = [
            _summary(c, a, task, r, iterations)
            for c, a, r in zip(run.configs, solo, run.rows, strict=True)
        ]
        return run.finish(
            summaries,
            title=f"two Gaussians ({cfg.algorithm}{', contextual' if cfg.contextual else ''})",
        )


def _postfix(row: dict[str, Any]) -> dict[str, Any]:
    return {
        "ret": f"{row['mean_return']:.3f}",
        "kl": f"{row.get('kl', math.nan):.2f}",  # cmaes has no KL bound
        "opts": row["n_active_options"],
    }


def _task(cfg: BimodalConfig) -> TwoGaussians | ContextualTwoGaussians:
    return (ContextualTwoGaussians if cfg.contextual else TwoGaussians)(width=cfg.bump_width)


def _summary(
    cfg: BimodalConfig,
    algo: EpisodicHiREPS,
    task: TwoGaussians | ContextualTwoGaussians,
    rows: list[dict[str, Any]],
    iterations: int,
) -> dict[str, Any]:
    options = option_summary(algo, task)
    return {
        "experiment": "bimodal",
        "algorithm": cfg.algorithm,
        "seed": cfg.seed,
        "episodes": iterations * cfg.samples_per_iteration,
        "iterations": iterations,
        "final_return": rows[-1]["eval_return"],
        "final_mean_return": rows[-1]["mean_return"],
        "n_active_options": int(algo.policy.active.sum()),
        "modes_covered": modes_covered(options, task),
        **{key: rows[-1][key] for key in VERSATILITY},
        "options": options,
    }


VERSATILITY = ("success_rate", "solutions_found", "behaviour_entropy", "purity")
"""The versatility measures logged every iteration and summarised at the end."""


def option_summary(
    algo: EpisodicHiREPS, task: TwoGaussians | ContextualTwoGaussians
) -> list[dict[str, Any]]:
    """Active options: prior mass (over the task's contexts) and mean at context 0."""
    pol = algo.policy
    zero = torch.zeros(1, task.context_dim, dtype=torch.float64)
    ctx = zero
    if isinstance(task, ContextualTwoGaussians):
        ctx = torch.linspace(-1, 1, 21, dtype=torch.float64)[:, None]
    prior = pol.gating.probs(pol.gating_features(ctx)).mean(0)
    return [
        {
            "option": o,
            "prior": float(prior[o]),
            "mean": [float(v) for v in opt.mean(pol.policy_features(zero))[0]],
            "std": [float(v) for v in opt.covariance.diagonal().sqrt()],
        }
        for o, opt in enumerate(pol.sub_policies)
        if bool(pol.active[o])
    ]


def modes_covered(
    options: list[dict[str, Any]],
    task: TwoGaussians | ContextualTwoGaussians,
    min_prior: float = 0.05,
    radius: float = 0.25,
) -> int:
    """Number of reward modes (at context 0) with an option of prior >= min_prior within radius."""
    if isinstance(task, ContextualTwoGaussians):
        modes = task.modes(torch.zeros(1, 1, dtype=torch.float64))[0]
    else:
        modes = task.modes.to(torch.float64)
    return sum(
        any(
            o["prior"] >= min_prior
            and float((torch.tensor(o["mean"], dtype=torch.float64) - m).norm()) <= radius
            for o in options
        )
        for m in modes
    )


def plot_bimodal_options(algo: EpisodicHiREPS, task: TwoGaussians, path: Path) -> None:
    """Reward landscape with each active option's mean and 2-sigma ellipse."""
    g = torch.linspace(-5, 5, 201, dtype=torch.float64)
    X, Y = torch.meshgrid(g, g, indexing="xy")
    Z = task(torch.stack([X.reshape(-1), Y.reshape(-1)], 1)).reshape(X.shape)
    fig = Figure(figsize=(5, 5))  # no pyplot: a notebook's backend is left as it is
    ax = fig.subplots()
    ax.contourf(X.numpy(), Y.numpy(), Z.numpy(), levels=20, cmap="Greys")
    pol = algo.policy
    prior = pol.gating.probs(torch.zeros(1, 0, dtype=torch.float64))[0]
    t = torch.linspace(0, 2 * math.pi, 100, dtype=torch.float64)
    circle = torch.stack([t.cos(), t.sin()], 0)
    for o, opt in enumerate(pol.sub_policies):
        if not bool(pol.active[o]):
            continue
        mu = opt.bias.detach()
        ell = mu[:, None] + 2.0 * opt.chol.detach() @ circle
        ax.plot(ell[0].numpy(), ell[1].numpy(), lw=1.5)
        ax.plot(
            [float(mu[0])],
            [float(mu[1])],
            "x",
            ms=8,
            label=f"option {o}: prior {float(prior[o]):.2f}",
        )
    ax.set_xlim(-5, 5)
    ax.set_ylim(-5, 5)
    ax.set_aspect("equal")
    ax.set_title("reward and options (mean, 2-sigma)")
    ax.legend(fontsize=7, loc="upper left")
    fig.tight_layout()
    atomic_write(path, lambda p: fig.savefig(p, format="png", dpi=110))


EXPERIMENT = Experiment(
    "bimodal",
    BimodalConfig,
    run,
    algorithm,
    metric="final_return",
    curve="eval_return",
    curves=("mean_return", "eval_return"),
    per_iteration="samples_per_iteration",
)
