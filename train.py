"""Run the paper's experiments: ``python train.py <experiment> [--options]``.

One typed config (a dataclass) per experiment; ``python train.py <experiment> --help`` lists
its options. Every run writes a run directory (default ``runs/<experiment>/<timestamp>``,
``--run-dir`` overrides) with ``config.json``, ``metrics.csv`` (one row per iteration),
``checkpoint.pt``, ``learning_curve.png`` and, when it finished, ``summary.json``.
"""

from __future__ import annotations

import dataclasses
import json
import math
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any, Literal

import torch
import tyro
from tqdm.auto import tqdm

from environments.toy import ContextualTwoGaussians, TwoGaussians
from hireps_torch.algorithms import REPS, EpisodicHiREPS
from hireps_torch.runlog import RunWriter, default_run_dir

if TYPE_CHECKING:
    from hireps_torch.features import FeatureMap, QuadraticFeatures
    from hireps_torch.policies import HierarchicalPolicy


@dataclass(frozen=True)
class BimodalConfig:
    """Two-Gaussians toy task (AISTATS 2012): HiREPS keeps one option per mode, REPS picks one."""

    algorithm: Literal["hireps", "reps"] = "hireps"
    """hireps: mixture of linear-Gaussian options with the entropy bound; reps: one Gaussian."""
    contextual: bool = False
    """Use the contextual variant (1-D context, two linear solution families)."""
    n_options: int = 10
    """Initial number of options (hireps only); low-mass options are pruned."""
    epsilon: float = 1.0
    """KL bound per iteration."""
    kappa_rel: float = 0.8
    """Entropy bound as a fraction of the current mean responsibility entropy (hireps)."""
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
    seed: int = 0
    run_dir: Path | None = None
    """Where to write the run (default runs/bimodal/<timestamp>); must not exist or be empty."""
    progress: bool = True
    """Show a progress bar."""


def _validate(cfg: Any) -> None:
    if cfg.samples_per_iteration < 2:
        raise ValueError(f"samples_per_iteration must be >= 2, got {cfg.samples_per_iteration}")
    if cfg.episodes < cfg.samples_per_iteration:
        raise ValueError(
            f"episodes ({cfg.episodes}) must be at least samples_per_iteration "
            f"({cfg.samples_per_iteration})"
        )


def run_bimodal(cfg: BimodalConfig) -> dict[str, Any]:
    """HiREPS or REPS on the (contextual) two-Gaussians task; returns the summary."""
    _validate(cfg)
    task: TwoGaussians | ContextualTwoGaussians
    if cfg.contextual:
        task = ContextualTwoGaussians(width=cfg.bump_width)
    else:
        task = TwoGaussians(width=cfg.bump_width)
    common = dict(
        context_dim=task.context_dim,
        init_std=cfg.init_std,
        epsilon=cfg.epsilon,
        min_variance=cfg.min_variance,
        seed=cfg.seed,
    )
    algo: EpisodicHiREPS
    if cfg.algorithm == "reps":
        algo = REPS.create(task.param_dim, **common)  # type: ignore[arg-type]
    else:
        algo = EpisodicHiREPS.create(
            task.param_dim,
            n_options=cfg.n_options,
            kappa_rel=cfg.kappa_rel,
            **common,  # type: ignore[arg-type]
        )
    ctx_gen = torch.Generator().manual_seed(cfg.seed + 10_000)
    eval_ctx = torch.linspace(-1, 1, 21, dtype=torch.float64)[:, None] if cfg.contextual else None

    def evaluate() -> float:
        """Mean return of the noise-free policy (over a context grid when contextual)."""
        if isinstance(task, ContextualTwoGaussians):
            assert eval_ctx is not None
            return float(task(eval_ctx, algo.act(eval_ctx)).mean())
        return float(task(algo.act(1)).mean())

    run_dir = cfg.run_dir or default_run_dir("bimodal")
    writer = RunWriter(run_dir, {"experiment": "bimodal", **dataclasses.asdict(cfg)})
    iterations = cfg.episodes // cfg.samples_per_iteration
    bar = tqdm(range(iterations), desc=f"bimodal/{cfg.algorithm}", disable=not cfg.progress)
    for it in bar:
        n = cfg.samples_per_iteration
        if isinstance(task, ContextualTwoGaussians):
            ctx = task.sample_contexts(n, ctx_gen)
            theta = algo.ask(ctx)
            returns = task(ctx, theta)
            diag = algo.tell(ctx, theta, returns)
        else:
            theta = algo.ask(n)
            returns = task(theta)
            diag = algo.tell(None, theta, returns)
        row = {"iteration": it + 1, "episodes": (it + 1) * n, "eval_return": evaluate(), **diag}
        writer.log(row)
        bar.set_postfix(
            ret=f"{row['mean_return']:.3f}", kl=f"{diag['kl']:.2f}", opts=diag["n_active_options"]
        )

    writer.checkpoint({"algorithm": algo.state_dict(), "config": dataclasses.asdict(cfg)})
    writer.plot_learning_curve(
        "episodes",
        ["mean_return", "eval_return"],
        title=f"two Gaussians ({cfg.algorithm}{', contextual' if cfg.contextual else ''})",
    )
    options = option_summary(algo, task)
    if isinstance(task, TwoGaussians):
        plot_bimodal_options(algo, task, writer.dir / "options.png")
    return writer.finish(
        {
            "experiment": "bimodal",
            "algorithm": cfg.algorithm,
            "seed": cfg.seed,
            "episodes": iterations * cfg.samples_per_iteration,
            "iterations": iterations,
            "final_return": writer.rows[-1]["eval_return"],
            "final_mean_return": writer.rows[-1]["mean_return"],
            "n_active_options": int(algo.policy.active.sum()),
            "modes_covered": modes_covered(options, task),
            "options": options,
        }
    )


def option_summary(algo: EpisodicHiREPS, task: TwoGaussians | ContextualTwoGaussians) -> list:
    """Active options: prior mass (over the task's contexts) and mean at context 0."""
    pol = algo.policy
    ctx = torch.zeros(1, task.context_dim, dtype=torch.float64)
    if isinstance(task, ContextualTwoGaussians):
        ctx = torch.linspace(-1, 1, 21, dtype=torch.float64)[:, None]
    prior = pol.gating.probs(pol.gating_features(ctx)).mean(0)
    zero = torch.zeros(1, task.context_dim, dtype=torch.float64)
    out = []
    for o, opt in enumerate(pol.sub_policies):
        if bool(pol.active[o]):
            out.append(
                {
                    "option": o,
                    "prior": float(prior[o]),
                    "mean": [float(v) for v in opt.mean(pol.policy_features(zero))[0]],
                    "std": [float(v) for v in opt.covariance.diagonal().sqrt()],
                }
            )
    return out


def modes_covered(
    options: list,
    task: TwoGaussians | ContextualTwoGaussians,
    min_prior: float = 0.05,
    radius: float = 0.25,
) -> int:
    """Number of reward modes (at context 0) with an option of prior >= min_prior within radius."""
    if isinstance(task, ContextualTwoGaussians):
        modes = task.modes(torch.zeros(1, 1, dtype=torch.float64))[0]
    else:
        modes = task.modes.to(torch.float64)
    covered = 0
    for m in modes:
        if any(
            o["prior"] >= min_prior
            and float((torch.tensor(o["mean"], dtype=torch.float64) - m).norm()) <= radius
            for o in options
        ):
            covered += 1
    return covered


def plot_bimodal_options(algo: EpisodicHiREPS, task: TwoGaussians, path: Path) -> None:
    """Reward landscape with each active option's mean and 2-sigma ellipse."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from hireps_torch.runlog import atomic_write

    g = torch.linspace(-5, 5, 201, dtype=torch.float64)
    X, Y = torch.meshgrid(g, g, indexing="xy")
    Z = task(torch.stack([X.reshape(-1), Y.reshape(-1)], 1)).reshape(X.shape)
    fig, ax = plt.subplots(figsize=(5, 5))
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
    plt.close(fig)


# --------------------------------------------------------------------------------------------
# pendulum swing-up (infinite-horizon HiREPS)


@dataclass(frozen=True)
class PendulumConfig:
    """Pendulum swing-up with infinite-horizon HiREPS (paper Figs 16-18)."""

    gating: Literal["learned", "constant", "flat"] = "learned"
    """learned: softmax gating on the squared state expansion; constant: k-means over 1000
    states uniform in +-[pi, 50], frozen; flat: one linear-Gaussian policy on the gating's
    features."""
    n_options: int = 5
    """Number of options (ignored for flat)."""
    steps_per_decision: int = 5
    """d: control steps (at 100 Hz) per decision; restart probability 0.02 / d."""
    episodes: int = 1000
    """Total episodes (``episode_seconds`` of experience per parallel pendulum each)."""
    episodes_per_iteration: int = 20
    """Episodes per policy update = parallel pendulums."""
    episode_seconds: float = 10.0
    """Simulated time per episode: one pendulum's experience between two updates (the mean
    time between restarts is 12.5 s at d = 5). 10 s learned in 19 of 20 seeds, 5 s in 15 of
    20 (benchmarks/README.md)."""
    kp: float = 60.0
    """PD controller stiffness (N m / rad)."""
    kd: float = 10.0
    """PD controller damping (N m s / rad)."""
    start_noise: float = 0.1
    """Std of the start perturbation around hanging down (rad and rad/s)."""
    reset_each_iteration: bool = False
    """Start every iteration's episodes from the start distribution. Off by default: the
    pendulums run on across iterations, restarting only at the restart probability, so the
    samples follow the restart process's stationary distribution, as the dual assumes."""
    epsilon: float = 0.5
    """KL bound per iteration."""
    kappa_rel: float = 0.9
    """Entropy bound relative to the mean responsibility entropy (learned gating only)."""
    init_std: float = 1.5
    """Initial exploration std of the desired angle (rad)."""
    mirror_samples: bool = True
    """Also update on the mirror image (-theta, -theta', -desired angle) of every decision:
    the task is symmetric under it, and without it the policy often commits to pushing one
    way and never swings up (see benchmarks/README.md)."""
    init_means: Literal["spaced", "random"] = "spaced"
    """Initial option means (desired angles, no feedback yet): spaced evenly over
    [-2 pi, 2 pi] (one option per cell centre, so there are options that push either way at
    full torque), or random around 0 with std ``init_std``."""
    min_variance: float = 1e-4
    """Floor on the option variance (rad^2)."""
    fourier_bases: int = 5
    """Fourier bases per state dimension of the value features."""
    value_features: Literal["fourier", "fourier+quadratic"] = "fourier+quadratic"
    """Value features: the Fourier basis alone, or next to the gating's squared expansion
    (which adds a quadratic bowl around upright and, with the basis's cos(theta), the energy)."""
    max_velocity: float = 10.0
    """Velocity range (rad/s) the Fourier and gating features are scaled to (a pendulum with
    the energy of upright at rest passes the bottom at sqrt(4 g / l) = 8.9 rad/s)."""
    workers: int = 1
    """Collector worker processes (1: torchrl Collector in this process; >1: MultiSyncCollector)."""
    eval_rollouts: int = 50
    """Noise-free evaluation rollouts (5 s each) at the end."""
    seed: int = 0
    run_dir: Path | None = None
    """Where to write the run (default runs/pendulum/<timestamp>); must not exist or be empty."""
    progress: bool = True
    """Show a progress bar."""


def _validate_episodic_budget(cfg: Any, positive: tuple[str, ...]) -> None:
    """Every field in ``positive`` >= 1 and at least one iteration's episodes."""
    for name in positive:
        if getattr(cfg, name) < 1:
            raise ValueError(f"{name} must be >= 1, got {getattr(cfg, name)}")
    if cfg.episodes < cfg.episodes_per_iteration:
        raise ValueError(
            f"episodes ({cfg.episodes}) must be at least episodes_per_iteration "
            f"({cfg.episodes_per_iteration})"
        )


def _train_from_collector(
    collector: Any,
    cfg: Any,
    experiment: str,
    label: str,
    *,
    iterations: int,
    episodes_per_iteration: int,
    update: Callable[[Any], dict[str, Any]],
    postfix: Callable[[dict[str, Any]], dict[str, Any]],
) -> RunWriter:
    """The training loop of every experiment that collects with TorchRL.

    Opens the run directory, then for every collected batch: ``update(batch)`` (the policy
    update; returns the iteration's logged fields), a weight sync when there are worker
    processes, one logged row and a progress-bar step showing ``postfix(row)``. The collector
    is shut down however the loop ends (also when the run directory cannot be opened). Returns
    the writer for the summary.
    """
    from hireps_torch.rollout import shutdown_collector

    try:
        run_dir = cfg.run_dir or default_run_dir(experiment)
        writer = RunWriter(run_dir, {"experiment": experiment, **dataclasses.asdict(cfg)})
    except BaseException:
        shutdown_collector(collector)
        raise
    bar = tqdm(total=iterations, desc=label, disable=not cfg.progress)
    try:
        for it, batch in enumerate(collector):
            fields = update(batch)
            if getattr(cfg, "workers", 1) > 1:
                collector.update_policy_weights_()
            done = (it + 1) * episodes_per_iteration
            logged = {"iteration": it + 1, "episodes": done, **fields}
            writer.log(logged)
            bar.update(1)
            bar.set_postfix(**postfix(logged))
    finally:
        bar.close()
        shutdown_collector(collector)
    return writer


def _infinite_horizon_update(
    algo: Any,
    row: Callable[[torch.Tensor, torch.Tensor], dict[str, Any]],
    augment: Callable[..., tuple[torch.Tensor, ...]] | None = None,
) -> Callable[[Any], dict[str, Any]]:
    """The per-batch step of the pendulum and the beam: one ``algo.update`` on the batch's
    decisions (terminal ones flagged; passed through ``augment(s, a, r, s', terminated)``
    first when given), then ``row(rewards, terminated)`` on the collected decisions for the
    task's own columns (after the update) followed by the update's diagnostics."""
    from hireps_torch.rollout import transitions

    def update(batch: Any) -> dict[str, Any]:
        s, a, r, s_next, _ = transitions(batch, "state")
        terminated = batch["next", "terminated"].reshape(-1)
        data = (s, a, r, s_next, terminated)
        diag = algo.update(*(augment(*data) if augment is not None else data))
        return {**row(r, terminated), **diag}

    return update


def _infinite_horizon_postfix(logged: dict[str, Any]) -> dict[str, Any]:
    return {
        "ret": f"{logged['average_return']:.1f}",
        "kl": f"{logged['kl']:.2f}",
        "opts": logged["n_active_options"],
    }


def pendulum_quadratic_features(cfg: PendulumConfig) -> QuadraticFeatures:
    """The squared expansion of (theta / pi, theta' / max_velocity): (N, 2) -> (N, 5)."""
    from hireps_torch.features import QuadraticFeatures

    return QuadraticFeatures(2, scale=torch.tensor([math.pi, cfg.max_velocity]))


def pendulum_value_features(cfg: PendulumConfig) -> FeatureMap:
    """Periodic Fourier basis of (theta, theta') on [-pi, pi] x [-max_velocity, max_velocity],
    plus the squared expansion when ``cfg.value_features == "fourier+quadratic"``."""
    from hireps_torch.features import ConcatFeatures, FourierFeatures

    vmax = cfg.max_velocity
    fourier = FourierFeatures(
        [-math.pi, -vmax], [math.pi, vmax], cfg.fourier_bases, periodic=[True, False]
    )
    if cfg.value_features == "fourier":
        return fourier
    return ConcatFeatures(fourier, pendulum_quadratic_features(cfg))


def build_pendulum_policy(cfg: PendulumConfig, generator: torch.Generator) -> HierarchicalPolicy:
    """The policy of one gating kind: options linear in (theta, theta') -> desired angle."""
    from hireps_torch.policies import ConstantGating, HierarchicalPolicy

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


def run_pendulum(cfg: PendulumConfig) -> dict[str, Any]:
    """Infinite-horizon HiREPS on the swing-up; returns the summary."""
    from environments.pendulum import (
        PendulumParams,
        PendulumSwingUpBatchEnv,
        evaluate_swing_up,
        mirror_decisions,
        sample_start,
    )
    from hireps_torch.algorithms import InfiniteHorizonHiREPS
    from hireps_torch.rollout import make_collector, policy_module

    _validate_episodic_budget(
        cfg, ("n_options", "steps_per_decision", "episodes_per_iteration", "workers")
    )
    params = PendulumParams(
        steps_per_decision=cfg.steps_per_decision, kp=cfg.kp, kd=cfg.kd, start_noise=cfg.start_noise
    )
    decisions = max(1, round(cfg.episode_seconds / params.decision_seconds))
    B = cfg.episodes_per_iteration
    if cfg.workers > 1 and B % cfg.workers:
        raise ValueError(
            f"episodes_per_iteration ({B}) must be divisible by workers ({cfg.workers})"
        )
    torch.manual_seed(cfg.seed)
    gen = torch.Generator().manual_seed(cfg.seed)
    policy = build_pendulum_policy(cfg, gen)
    algo = InfiniteHorizonHiREPS(
        policy,
        pendulum_value_features(cfg),
        sample_start(1000, params, gen),
        gamma=params.gamma,
        epsilon=cfg.epsilon,
        kappa_rel=cfg.kappa_rel if cfg.gating == "learned" else None,
        prune_threshold=1e-4 if cfg.gating == "learned" else 0.0,
    )
    per_worker = B // cfg.workers
    env_seed = cfg.seed + 1

    def make_env() -> PendulumSwingUpBatchEnv:
        return PendulumSwingUpBatchEnv(per_worker, params, seed=env_seed)

    iterations = cfg.episodes // B
    frames = B * decisions
    collector = make_collector(
        make_env,
        policy_module(policy),
        frames_per_batch=frames,
        total_frames=frames * iterations,
        num_workers=cfg.workers,
        reset_at_each_iter=cfg.reset_each_iteration,
        seed=env_seed,
    )
    n_opt = cfg.n_options if cfg.gating != "flat" else 1
    label = f"pendulum/{cfg.gating}/{n_opt}opt/d{cfg.steps_per_decision}"
    writer = _train_from_collector(
        collector,
        cfg,
        "pendulum",
        label,
        iterations=iterations,
        episodes_per_iteration=B,
        update=_infinite_horizon_update(
            algo,
            lambda r, _: {"average_return": float(r.mean()) / params.steps_per_decision},
            mirror_decisions if cfg.mirror_samples else None,
        ),
        postfix=_infinite_horizon_postfix,
    )

    def act(states: torch.Tensor) -> torch.Tensor:
        return policy.mean_action(states)[0]

    ev = evaluate_swing_up(act, params, n_rollouts=cfg.eval_rollouts, seed=cfg.seed + 777)
    writer.checkpoint({"algorithm": algo.state_dict(), "config": dataclasses.asdict(cfg)})
    writer.plot_learning_curve("episodes", ["average_return"], title=label)
    return writer.finish(
        {
            "experiment": "pendulum",
            "gating": cfg.gating,
            "n_options": n_opt,
            "steps_per_decision": cfg.steps_per_decision,
            "seed": cfg.seed,
            "episodes": iterations * B,
            "iterations": iterations,
            "final_average_return": writer.rows[-1]["average_return"],
            "final_return": ev.average_return,
            "success_rate": ev.success_rate,
            "time_to_upright": ev.time_to_upright,
            "reached_upright_share": ev.reached_share,
            "n_active_options": int(policy.active.sum()),
        }
    )


# --------------------------------------------------------------------------------------------
# ball on a beam (infinite-horizon HiREPS, 30 episodes)


@dataclass(frozen=True)
class BallOnBeamConfig:
    """Ball on a beam with infinite-horizon HiREPS (paper Fig 19): 3 episodes per iteration."""

    n_options: int = 5
    """Number of linear-Gaussian options (the paper does not say; 5 as in its other tasks)."""
    episodes: int = 30
    """Total episodes (20 s of experience per beam each)."""
    episodes_per_iteration: int = 3
    """Episodes per policy update = parallel beams."""
    epsilon: float = 0.5
    """KL bound per iteration."""
    kappa_rel: float | None = None
    """Entropy bound relative to the mean responsibility entropy (None: off). Off by default
    here: with 120 decisions per iteration the bound (0.9) sharpened an over-fitted gating and
    only 3 of 10 seeds reached success in 30 episodes, against 10 of 10 without it (see
    benchmarks/README.md)."""
    init_std: float = 0.05
    """Initial exploration std of the desired beam angle (rad)."""
    min_variance: float = 1e-6
    """Floor on the option variance (rad^2)."""
    fourier_bases: int = 5
    """Fourier bases per state dimension of the value features."""
    fourier_coupling: int | None = 1
    """Most state dimensions one Fourier term may couple (1: no cross terms, 3 * 4 features;
    None: all 5^3 - 1 = 124, more than the 120 decisions of one iteration)."""
    max_velocity: float = 1.0
    """Ball speed (m/s) the value and gating features are scaled to."""
    eval_episodes: int = 10
    """Noise-free evaluation episodes after every iteration (alternating sides)."""
    seed: int = 0
    run_dir: Path | None = None
    """Where to write the run (default runs/ball_on_beam/<timestamp>); must not exist or be
    empty."""
    progress: bool = True
    """Show a progress bar."""


def build_ball_on_beam_policy(
    cfg: BallOnBeamConfig, generator: torch.Generator | None = None
) -> HierarchicalPolicy:
    """Options linear in (x, x', alpha) -> desired beam angle, softmax gating on the squared
    expansion of the state (scaled by the beam's half length, ``max_velocity`` and the angle
    limit). Load a run's policy with ``policy.load_state_dict(ckpt["algorithm"]["policy"])``."""
    from hireps_torch.features import QuadraticFeatures
    from hireps_torch.policies import HierarchicalPolicy

    return HierarchicalPolicy.create(
        cfg.n_options,
        3,
        1,
        init_std=cfg.init_std,
        gating_features=QuadraticFeatures(3, scale=_beam_box(cfg)),
        min_variance=cfg.min_variance,
        generator=generator,
    )


def _beam_box(cfg: BallOnBeamConfig) -> torch.Tensor:
    """(3,) half-widths of the state box the beam's features are scaled to."""
    from environments.ball_on_beam import BeamParams

    p = BeamParams()
    return torch.tensor([p.half_length, cfg.max_velocity, p.max_angle])


def run_ball_on_beam(cfg: BallOnBeamConfig) -> dict[str, Any]:
    """Infinite-horizon HiREPS on the simulated ball on a beam; returns the summary."""
    from environments.ball_on_beam import (
        BallOnBeamBatchEnv,
        BeamParams,
        evaluate_beam,
        sample_start,
    )
    from hireps_torch.algorithms import InfiniteHorizonHiREPS
    from hireps_torch.features import FourierFeatures
    from hireps_torch.rollout import make_collector, policy_module

    _validate_episodic_budget(cfg, ("n_options", "episodes_per_iteration", "eval_episodes"))
    params = BeamParams()
    B = cfg.episodes_per_iteration
    torch.manual_seed(cfg.seed)
    gen = torch.Generator().manual_seed(cfg.seed)
    policy = build_ball_on_beam_policy(cfg, gen)
    box = _beam_box(cfg)
    sides = torch.where(torch.arange(1000) % 2 == 0, 1.0, -1.0)
    algo = InfiniteHorizonHiREPS(
        policy,
        FourierFeatures(-box, box, cfg.fourier_bases, coupling=cfg.fourier_coupling),
        sample_start(sides, params, gen),
        gamma=params.gamma,
        epsilon=cfg.epsilon,
        kappa_rel=cfg.kappa_rel,
    )
    iterations = cfg.episodes // B
    frames = B * params.decisions_per_episode
    env_seed = cfg.seed + 1
    collector = make_collector(
        lambda: BallOnBeamBatchEnv(B, params, seed=env_seed),
        policy_module(policy),
        frames_per_batch=frames,
        total_frames=frames * iterations,
        reset_at_each_iter=True,
        seed=env_seed,
    )

    def act(states: torch.Tensor) -> torch.Tensor:
        return policy.mean_action(states)[0]

    def row(r: torch.Tensor, terminated: torch.Tensor) -> dict[str, Any]:
        ev = evaluate_beam(act, params, n_episodes=cfg.eval_episodes, seed=cfg.seed + 777)
        return {
            "average_return": float(r.sum()) / B,
            "falls": int(terminated.sum()),
            "eval_return": ev.average_return,
            "eval_success_rate": ev.success_rate,
        }

    label = f"ball_on_beam/{cfg.n_options}opt"
    writer = _train_from_collector(
        collector,
        cfg,
        "ball_on_beam",
        label,
        iterations=iterations,
        episodes_per_iteration=B,
        update=_infinite_horizon_update(algo, row),
        postfix=_infinite_horizon_postfix,
    )
    first_success = next(
        (int(w["episodes"]) for w in writer.rows if w["eval_success_rate"] >= 0.9), None
    )
    writer.checkpoint({"algorithm": algo.state_dict(), "config": dataclasses.asdict(cfg)})
    writer.plot_learning_curve("episodes", ["average_return", "eval_return"], title=label)
    last = writer.rows[-1]
    return writer.finish(
        {
            "experiment": "ball_on_beam",
            "n_options": cfg.n_options,
            "seed": cfg.seed,
            "episodes": iterations * B,
            "iterations": iterations,
            "final_average_return": last["average_return"],
            "final_eval_return": last["eval_return"],
            "final_return": last["eval_return"],
            "success_rate": last["eval_success_rate"],
            "episodes_to_success": first_success,
            "n_active_options": int(policy.active.sum()),
        }
    )


# --------------------------------------------------------------------------------------------
# robot hockey (time-indexed vs episodic HiREPS, 3 shots, paper Fig 14)


@dataclass(frozen=True)
class HockeyConfig:
    """Robot hockey in pybullet (paper Fig 14): 3 shots per episode, 14 DMP numbers per shot."""

    n_options: int = 5
    """Options per policy (paper: 5)."""
    episodes: int = 1500
    """Total episodes (paper: 1500)."""
    episodes_per_iteration: int = 30
    """Episodes (samples) per policy update (paper: 30)."""
    epsilon: float = 1.0
    """KL bound per iteration (per step for the sequential variant)."""
    kappa_rel: float | None = 0.9
    """Entropy bound relative to the mean responsibility entropy; None: off."""
    init_std_position: float = 0.02
    """Initial exploration std of the 7 DMP goal positions (rad)."""
    init_std_velocity: float = 0.3
    """Initial exploration std of the 7 DMP goal velocities (rad/s)."""
    min_variance: float = 1e-6
    """Smallest variance of any parameter (the per-parameter floor is the larger of this and
    the exploration floor)."""
    exploration_floor: float = 0.25
    """Floor on each option's std as a fraction of the initial std, per parameter (keeps the
    14-dim options from collapsing onto the few effective samples of an update); 0: off."""
    covariance_prior: float = 0.0
    """Pseudo-samples of the prior that shrinks each option's refit covariance toward the
    previous one (0: plain weighted maximum likelihood)."""
    workers: int = 1
    """Collector worker processes (1: in this process; >1: MultiSyncCollector)."""
    seed: int = 0
    run_dir: Path | None = None
    """Where to write the run (default runs/<experiment>/<timestamp>); must not exist or be
    empty."""
    progress: bool = True
    """Show a progress bar."""


@dataclass(frozen=True)
class HockeySequentialConfig(HockeyConfig):
    """Sequential (time-indexed) HiREPS: one 14-dim policy per shot on the target position."""


@dataclass(frozen=True)
class HockeyEpisodicConfig(HockeyConfig):
    """Episodic HiREPS: one 42-dim vector per episode from the initial target position."""


def _hockey_rows(
    states: torch.Tensor, rewards: torch.Tensor, final: torch.Tensor, zones: tuple
) -> dict[str, Any]:
    """Per-iteration hockey metrics of N episodes: returns (N,), final positions (N, 2)."""
    from environments.hockey import zone_reward

    zone = zone_reward(final.norm(dim=-1), zones)
    returns = rewards.sum(-1)
    return {
        "average_reward": float(returns.mean()),
        "zone3_share": float((zone == 3).double().mean()),
        "zone_reward": float(zone.mean()),
        "final_distance": float(final.norm(dim=-1).mean()),
    }


def run_hockey(cfg: HockeyConfig) -> dict[str, Any]:
    """Sequential or episodic HiREPS on the simulated robot hockey task; returns the summary."""
    from torchrl.envs import GymEnv, StepCounter, TransformedEnv

    from environments.hockey import ENV_ID, EPISODIC_ENV_ID, HockeyParams, demo_action
    from hireps_torch.algorithms import EpisodicHiREPS, TimeIndexedHiREPS
    from hireps_torch.rollout import episodes, make_collector, policy_module, time_indexed_module

    if not isinstance(cfg, (HockeySequentialConfig, HockeyEpisodicConfig)):
        raise ValueError(
            f"run_hockey needs a HockeySequentialConfig or HockeyEpisodicConfig, got "
            f"{type(cfg).__name__}"
        )
    sequential = isinstance(cfg, HockeySequentialConfig)
    experiment = "hockey_sequential" if sequential else "hockey_episodic"
    _validate_episodic_budget(cfg, ("n_options", "episodes_per_iteration", "workers"))
    B, W = cfg.episodes_per_iteration, cfg.workers
    if B < 2:
        raise ValueError(f"episodes_per_iteration must be >= 2, got {B}")
    if not 0.0 <= cfg.exploration_floor < 1.0:
        raise ValueError(f"exploration_floor must be in [0, 1), got {cfg.exploration_floor}")
    if B % W:
        raise ValueError(f"episodes_per_iteration ({B}) must be divisible by workers ({W})")
    params = HockeyParams()
    K = params.n_shots
    demo = torch.as_tensor(demo_action(params), dtype=torch.float64)  # the initial mean
    std = torch.cat(
        [
            torch.full((7,), cfg.init_std_position, dtype=torch.float64),
            torch.full((7,), cfg.init_std_velocity, dtype=torch.float64),
        ]
    )
    std_full = std if sequential else std.repeat(K)
    torch.manual_seed(cfg.seed)
    common = dict(
        n_options=cfg.n_options,
        init_std=std_full,
        epsilon=cfg.epsilon,
        kappa_rel=cfg.kappa_rel,
        min_variance=((cfg.exploration_floor * std_full) ** 2).clamp_min(cfg.min_variance),
        covariance_prior=cfg.covariance_prior,
        seed=cfg.seed,
    )
    algo: Any
    if sequential:
        algo = TimeIndexedHiREPS.create(K, 14, 2, init_mean=demo, **common)  # type: ignore[arg-type]
        actor = time_indexed_module(algo.policies)
        policies = list(algo.policies)
        frames_per_episode = K
    else:
        algo = EpisodicHiREPS.create(
            14 * K,
            context_dim=2,
            init_mean=demo.repeat(K),
            **common,  # type: ignore[arg-type]
        )
        actor = policy_module(algo.policy)
        policies = [algo.policy]
        frames_per_episode = 1
    env_id = ENV_ID if sequential else EPISODIC_ENV_ID

    def make_env() -> Any:
        import environments.hockey  # noqa: F401  (registers the ids in worker processes)

        env = GymEnv(env_id)
        return TransformedEnv(env, StepCounter()) if sequential else env

    iterations = cfg.episodes // B
    frames = B * frames_per_episode
    env_seed = cfg.seed + 1
    collector = make_collector(
        make_env,
        actor,
        frames_per_batch=frames,
        total_frames=frames * iterations,
        num_workers=W,
        reset_at_each_iter=True,
        seed=env_seed,
    )
    per_step = (
        "eta",
        "xi",
        "kl",
        "cross_entropy",
        "effective_sample_size",
        "policy_entropy",
        "n_active_options",
    )

    def update(batch: Any) -> dict[str, Any]:
        s, a, r, final = episodes(batch, frames_per_episode)
        if sequential:
            diag = algo.tell(s, a, r)
            steps = {f"{key}_{k + 1}": diag[key][k] for key in per_step for k in range(K)}
        else:
            diag = algo.tell(s[:, 0], a[:, 0], r[:, 0])
            steps = {}
        scalars = {k: v for k, v in diag.items() if not isinstance(v, (list, tuple))}
        return {**_hockey_rows(s, r, final, params.zones), **scalars, **steps}

    label = f"{experiment}/{cfg.n_options}opt"
    writer = _train_from_collector(
        collector,
        cfg,
        experiment,
        label,
        iterations=iterations,
        episodes_per_iteration=B,
        update=update,
        postfix=lambda row: {
            "reward": f"{row['average_reward']:.2f}",
            "zone3": f"{row['zone3_share']:.2f}",
        },
    )
    last = writer.rows[-1]
    writer.checkpoint({"algorithm": algo.state_dict(), "config": dataclasses.asdict(cfg)})
    writer.plot_learning_curve(
        "episodes", ["average_reward"], title=label, ylabel="average reward per episode"
    )
    shots = iterations * B * K
    return writer.finish(
        {
            "experiment": experiment,
            "n_options": cfg.n_options,
            "seed": cfg.seed,
            "episodes": iterations * B,
            "iterations": iterations,
            "final_average_reward": last["average_reward"],
            "final_return": last["average_reward"],
            "zone3_share": last["zone3_share"],
            "final_zone_reward": last["zone_reward"],
            "n_active_options": [int(p.active.sum()) for p in policies],
            "seconds_per_shot": (time.perf_counter() - writer.start) / shots,
        }
    )


EXPERIMENTS: dict[str, tuple[Any, Any]] = {
    "bimodal": (BimodalConfig, run_bimodal),
    "pendulum": (PendulumConfig, run_pendulum),
    "ball-on-beam": (BallOnBeamConfig, run_ball_on_beam),
    "hockey-sequential": (HockeySequentialConfig, run_hockey),
    "hockey-episodic": (HockeyEpisodicConfig, run_hockey),
}


def main(argv: list[str] | None = None) -> dict[str, Any]:
    argv = sys.argv[1:] if argv is None else argv
    defaults = {name: cls for name, (cls, _) in EXPERIMENTS.items()}
    cfg = tyro.extras.subcommand_cli_from_dict(defaults, args=argv, description=__doc__)
    name = next(n for n, (cls, _) in EXPERIMENTS.items() if isinstance(cfg, cls))
    summary = EXPERIMENTS[name][1](cfg)
    print(json.dumps({k: v for k, v in summary.items() if k != "options"}, indent=2))
    return summary


if __name__ == "__main__":
    try:
        main()
    except (ValueError, FileExistsError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        raise SystemExit(2) from None
