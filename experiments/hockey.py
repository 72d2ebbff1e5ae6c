"""Robot hockey in pybullet (paper Fig 14): sequential (time-indexed) against episodic HiREPS."""

from __future__ import annotations

from dataclasses import dataclass
from functools import partial
from typing import Any, Literal

import torch
from torchrl.envs import GymEnv, StepCounter, TransformedEnv

import hireps_torch.envs  # noqa: F401  (registers the ids, also in worker processes)
from hireps_torch.algorithms import Algorithm, EpisodicHiREPS, Experience, TimeIndexedHiREPS
from hireps_torch.envs.hockey import (
    ENV_ID,
    EPISODIC_ENV_ID,
    AimFeatures,
    HockeyParams,
    aim_slopes,
    demo_action,
    turn_derivative,
    zone_reward,
)
from hireps_torch.experiments.checkpoint import RunState
from hireps_torch.experiments.options import (
    RunOptions,
    check_options,
    member_seeds,
    option_error,
)
from hireps_torch.experiments.runner import Experiment, Run, check_budget, resume_point
from hireps_torch.experiments.workers import (
    Backend,
    check_pool,
    make_pool,
    play_episodes,
    reproducible_mkl,
)
from hireps_torch.rollout import episodes, policy_module, time_indexed_module

__all__ = [
    "HockeyConfig",
    "HockeyEpisodicConfig",
    "HockeyFixedStartConfig",
    "HockeySequentialConfig",
    "VARIANTS",
    "hockey_params",
    "run",
]

PER_STEP = tuple(
    "eta xi kl cross_entropy effective_sample_size policy_entropy n_active_options".split()
)
"""Diagnostics the sequential variant reports per shot (columns ``eta_1``, ``eta_2``, ...)."""


@dataclass(frozen=True)
class HockeyConfig(RunOptions):
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
    velocity_std_fraction: float = 0.0
    """If > 0: each goal-velocity std as a fraction of the demo's (replaces init_std_velocity)."""
    min_velocity_std: float = 0.05
    """Smallest initial goal-velocity std (rad/s) with velocity_std_fraction."""
    min_variance: float = 1e-6
    """Smallest variance of any parameter (with the exploration floor: the larger of the two)."""
    exploration_floor: float = 0.25
    """Floor on each option's std as a fraction of the initial std, per parameter; 0: off."""
    exploration_floor_end: float | None = 0.1
    """The floor's fraction at the last update, linear from exploration_floor at the first
    (None: constant; why: benchmarks/README.md, "Robot hockey defaults")."""
    covariance_prior: float = 0.0
    """Pseudo-samples of the prior shrinking each option's covariance toward the previous one."""
    mean_prior: float = 4.0
    """Pseudo-samples of the prior holding each option's mean coefficients near the previous
    ones (0: weighted least squares; why 4: benchmarks/README.md, "Robot hockey defaults")."""
    workers: int = 1
    """Workers that play each iteration's episodes (the result does not depend on them)."""
    backend: Backend = "local"
    """local: processes on this machine; ray: Ray tasks (pip install -e '.[distributed]')."""
    ray_address: str | None = None
    """An existing Ray cluster (HOST:PORT, ray://HOST:PORT or auto) for --backend ray."""
    start_std: float = 0.1
    """Std (m) of the target puck's start in x and y (0: a fixed start, as in Fig 15b)."""
    puck_restitution: float = 0.3
    """Restitution of the pucks and the blade (why 0.3: see hireps_torch.envs.hockey.env)."""
    floor_friction: float = 0.025
    """Puck-floor Coulomb friction (ice-like)."""
    flat_pucks: bool = True
    """Pucks that cannot tip or roll on their edge (--no-flat-pucks: solid cylinders)."""
    option_features: Literal["position", "aim"] = "aim"
    """What the options are linear in: aim, the target's angle and distance from the control
    puck's spot (hireps_torch.envs.hockey.aim.AimFeatures); position, its (x, y)."""
    final_eval_episodes: int | None = None
    """Final-policy evaluation episodes (None: episodes_per_iteration; 0: none), noise-free
    (eval_average_reward) and exploring (final_policy_average_reward, the paper's "average
    reward"), from starts no training episode used."""
    aim_slopes: bool = True
    """Start every option's mean with the slopes of the kinematic aim mapping
    (hireps_torch.envs.hockey.aim) at the start mean; --no-aim-slopes: zero slopes."""


@dataclass(frozen=True)
class HockeySequentialConfig(HockeyConfig):
    """Sequential (time-indexed) HiREPS: one 14-dim policy per shot on the target position."""


@dataclass(frozen=True)
class HockeyFixedStartConfig(HockeySequentialConfig):
    """The real robot's run (paper Fig 15b) in simulation: sequential HiREPS, the target puck
    always at the same spot, 10 episodes per update, 300 episodes."""

    start_std: float = 0.0
    """Std (m) of the target puck's start in x and y (0: the one spot of Fig 15b)."""
    episodes_per_iteration: int = 10
    """Episodes (samples) per policy update (paper, real robot: 10)."""
    episodes: int = 300
    """Total episodes (paper, real robot: 300)."""


@dataclass(frozen=True)
class HockeyEpisodicConfig(HockeyConfig):
    """Episodic HiREPS: one 42-dim vector per episode from the initial target position."""


def _hockey_rows(
    rewards: torch.Tensor, final: torch.Tensor, zones: tuple[float, float, float, float]
) -> dict[str, Any]:
    """Per-iteration hockey metrics of N episodes: rewards (N, K), final positions (N, 2)."""
    zone = zone_reward(final.norm(dim=-1), zones)
    returns = rewards.sum(-1)
    return {
        "average_reward": float(returns.mean()),
        "zone3_share": float((zone == 3).double().mean()),
        "zone_reward": float(zone.mean()),
        "final_distance": float(final.norm(dim=-1).mean()),
    }


def _exploration_std(cfg: HockeyConfig, repeats: int, demo: torch.Tensor) -> torch.Tensor:
    """(14 * repeats,) initial std: goal positions then goal velocities, per shot."""
    if cfg.velocity_std_fraction > 0:
        velocity = (cfg.velocity_std_fraction * demo[7:14].abs()).clamp_min(cfg.min_velocity_std)
    else:
        velocity = torch.full((7,), cfg.init_std_velocity, dtype=torch.float64)
    std = torch.cat([torch.full((7,), cfg.init_std_position, dtype=torch.float64), velocity])
    return std.repeat(repeats)


def _make_algorithm(cfg: HockeyConfig, n_shots: int, demo: torch.Tensor, params: Any) -> Algorithm:
    """Time-indexed (14 per shot) or episodic (3 x 14) HiREPS, starting at the demo shot: a
    population whose member s is the algorithm of ``--seed s`` (one member for ``--seed``)."""
    sequential = isinstance(cfg, HockeySequentialConfig)
    std = _exploration_std(cfg, 1 if sequential else n_shots, demo)
    common: dict[str, Any] = dict(
        n_options=cfg.n_options,
        init_std=std,
        epsilon=cfg.epsilon,
        kappa_rel=cfg.kappa_rel,
        min_variance=variance_floor(cfg, std, 0, 1),
        covariance_prior=cfg.covariance_prior,
        mean_prior=cfg.mean_prior,
        seed=member_seeds(cfg),
    )
    if cfg.option_features == "aim":
        common["policy_features"] = AimFeatures(params.geometry)
    algo: Algorithm
    if sequential:
        algo = TimeIndexedHiREPS.create(n_shots, 14, 2, init_mean=demo, **common)
    else:
        algo = EpisodicHiREPS.create(
            14 * n_shots, context_dim=2, init_mean=demo.repeat(n_shots), **common
        )
    if cfg.aim_slopes:
        _aim_options(algo, demo, params)
    return algo


def _aim_options(algo: Algorithm, demo: torch.Tensor, params: Any) -> None:
    """Every option's mean = bias + W (f(p) - f(p0)) on its features f, W the aim mapping's
    slopes at the start mean p0 (the same for every shot), its mean at p0 kept."""
    p0 = torch.tensor(params.target_mean, dtype=torch.float64)  # f0: its features
    for policy in algo.policies:
        f0 = policy.policy_features(p0.reshape(1, 2))[0]
        if isinstance(policy.policy_features, AimFeatures):
            # linear in (angle, distance): the turn's derivative on the angle, none on distance
            d = turn_derivative(demo, float(f0[0]), params.geometry)
            W = torch.stack([d, torch.zeros_like(d)], dim=-1)
        else:  # IdentityFeatures: options on (x, y)
            W = aim_slopes(demo, p0, params.geometry)  # (14, 2)
        slopes = W.repeat(policy.action_dim // 14, 1)
        with torch.no_grad():
            for option in policy.sub_policies:
                option.weight.copy_(slopes)
                option.bias.sub_(slopes @ f0)


def _check(cfg: HockeyConfig) -> int:
    """Refuse the base config and bad counts; returns the number of iterations."""
    if not isinstance(cfg, (HockeySequentialConfig, HockeyEpisodicConfig)):
        raise ValueError(
            f"run_hockey needs a HockeySequentialConfig or HockeyEpisodicConfig, got "
            f"{type(cfg).__name__}"
        )
    if torch.device(cfg.device).type != "cpu":
        raise option_error("device", cfg.device, "cpu: hockey (pybullet) runs on the CPU")
    check_options(
        cfg,
        positive=("init_std_position", "init_std_velocity", "min_velocity_std"),
        nonnegative=(
            "min_variance",
            "covariance_prior",
            "mean_prior",
            "velocity_std_fraction",
            "start_std",
            "floor_friction",
            "puck_restitution",
            "final_eval_episodes",
        ),
    )
    B, W = cfg.episodes_per_iteration, cfg.workers
    iterations = check_budget(cfg.episodes, B, n_options=cfg.n_options, workers=W)
    if B < 2:
        raise ValueError(f"episodes_per_iteration must be >= 2, got {B}")
    if not 0.0 <= cfg.exploration_floor < 1.0:
        raise ValueError(f"exploration_floor must be in [0, 1), got {cfg.exploration_floor}")
    end = cfg.exploration_floor_end  # a number or None (check_options)
    if end is not None and not 0.0 <= end < 1.0:
        raise ValueError(f"exploration_floor_end must be in [0, 1) or None, got {end!r}")
    if not 0.0 <= cfg.puck_restitution <= 1.0:
        raise ValueError(f"puck_restitution must be in [0, 1], got {cfg.puck_restitution}")
    check_pool(W, cfg.backend, cfg.ray_address)
    return iterations


def hockey_params(cfg: HockeyConfig) -> Any:
    """The task constants of a run: HockeyParams with the config's start and physics."""
    return HockeyParams(
        target_std=cfg.start_std,
        puck_restitution=cfg.puck_restitution,
        floor_friction=cfg.floor_friction,
        flat_pucks=cfg.flat_pucks,
    )


def _make_env(env_id: str, sequential: bool, params: Any = None) -> Any:
    """The gymnasium env through TorchRL; the sequential variant counts its shots."""
    env = GymEnv(env_id) if params is None else GymEnv(env_id, params=params)
    return TransformedEnv(env, StepCounter()) if sequential else env


def variance_floor(cfg: HockeyConfig, std: torch.Tensor, update: int, updates: int) -> torch.Tensor:
    """The options' variance floor (D,) for update ``update`` (0-based) of ``updates``:
    ``(f std)^2``, at least ``min_variance``, ``f`` linear from ``exploration_floor`` to
    ``exploration_floor_end`` (constant when that is None)."""
    f = cfg.exploration_floor
    if cfg.exploration_floor_end is not None and updates > 1:
        t = min(max(update, 0), updates - 1) / (updates - 1)
        f = f + t * (cfg.exploration_floor_end - f)
    return ((f * std) ** 2).clamp_min(cfg.min_variance)


def _member_row(diag: dict[str, Any], m: int) -> dict[str, Any]:
    """Member ``m``'s update diagnostics as row fields (the per-shot ones as ``<name>_<shot>``)."""
    mine = {key: value[m] for key, value in diag.items()}
    steps = {
        f"{key}_{k + 1}": mine[key][k]
        for key in PER_STEP
        if isinstance(mine.get(key), (list, tuple))
        for k in range(len(mine[key]))
    }
    return {k: v for k, v in mine.items() if not isinstance(v, (list, tuple))} | steps


EVAL_FIRST_EPISODE = 10**9
"""Index of the first evaluation episode (no run trains that long)."""


def evaluate_final_policy(
    cfg: HockeyConfig, policies: list[Any], params: Any, n_episodes: int, seed: int
) -> dict[str, float]:
    """The final ``policies`` (one run's) of the run with ``seed`` on ``n_episodes`` (>= 1)
    fresh episodes in this process:
    ``eval_average_reward``, ``eval_zone3_share``, ``eval_zone_reward`` (noise-free) and
    ``final_policy_average_reward`` (exploring, on the same starts)."""
    sequential = isinstance(cfg, HockeySequentialConfig)
    env = _make_env(ENV_ID if sequential else EPISODIC_ENV_ID, sequential, params)
    K = len(policies)
    indices = range(EVAL_FIRST_EPISODE, EVAL_FIRST_EPISODE + n_episodes)
    out: dict[str, float] = {}
    try:
        for deterministic in (True, False):
            actor = (
                time_indexed_module(policies, deterministic)
                if sequential
                else policy_module(policies[0], deterministic)
            )
            _, _, r, final = episodes(play_episodes(env, actor, seed, indices, K), K)
            rows = _hockey_rows(r, final, params.zones)
            if deterministic:
                out |= {f"eval_{k}": v for k, v in rows.items() if k != "final_distance"}
            else:
                out["final_policy_average_reward"] = rows["average_reward"]
    finally:
        env.close()
    return out


def algorithm(cfg: HockeyConfig) -> Algorithm:
    """``cfg`` checked as :func:`run` checks it, and the untrained algorithm it starts from."""
    _check(cfg)
    params = hockey_params(cfg)
    demo = torch.as_tensor(demo_action(params), dtype=torch.float64)
    return _make_algorithm(cfg, params.n_shots, demo, params)


def run(cfg: HockeyConfig) -> dict[str, Any]:
    """Sequential or episodic HiREPS on the simulated robot hockey task, one seed or a
    population; returns the summary."""
    iterations = _check(cfg)
    reproducible_mkl()  # before any arithmetic (see experiments/workers.py)
    sequential = isinstance(cfg, HockeySequentialConfig)
    entry = next(e for e in VARIANTS if type(cfg) is e.config)
    resume = resume_point(entry, cfg)
    params = hockey_params(cfg)
    demo = torch.as_tensor(demo_action(params), dtype=torch.float64)  # the initial mean
    seeds = member_seeds(cfg)
    torch.manual_seed(seeds[0])
    algo = _make_algorithm(cfg, params.n_shots, demo, params)
    K = len(algo.policies)  # decision steps per episode: 3 shots, or 1 vector of 42 numbers
    B = cfg.episodes_per_iteration
    std = _exploration_std(cfg, 1 if sequential else params.n_shots, demo)
    label = f"{entry.name}/{cfg.n_options}opt"
    state = RunState(algo)  # episode e's randomness comes from (seed, e): no env state
    # the pool (worker processes, Ray) last, right before the loop; closed however it ends
    pool = make_pool(
        partial(_make_env, ENV_ID if sequential else EPISODIC_ENV_ID, sequential, params),
        cfg.workers,
        cfg.backend,
        cfg.ray_address,
    )
    try:
        with Run(entry, cfg, state, resume) as run:
            for it in run.iterations(iterations, label, _postfix):
                # member m plays episodes it B .. (it + 1) B - 1 of the run of its seed
                indices = range(it * B, (it + 1) * B)
                played = [
                    episodes(pool.play(_actor(policies, sequential), s, indices, K), K)
                    for policies, s in zip(_members(algo, len(seeds)), seeds, strict=True)
                ]
                if cfg.exploration_floor_end is not None:  # the exploration floor's schedule
                    low = variance_floor(cfg, std, it, iterations)
                    for policy in algo.policies:
                        for option in policy.sub_policies:
                            option.min_variance = low.to(option.min_variance)
                s, a, r, _ = (torch.stack(x) for x in zip(*played, strict=True))
                diag = algo.learn(Experience(states=s, actions=a, rewards=r))
                run.log(
                    [
                        {"iteration": it + 1, "episodes": (it + 1) * B}
                        | _hockey_rows(rewards, final, params.zones)
                        | _member_row(diag, m)
                        for m, (_, _, rewards, final) in enumerate(played)
                    ]
                )
            pool.close()
            shots = iterations * B * params.n_shots * len(seeds)
            elapsed = run.root.elapsed()
            n_eval = B if cfg.final_eval_episodes is None else cfg.final_eval_episodes
            summaries = []
            for seed, policies, rows in zip(
                seeds, _members(algo, len(seeds)), run.rows, strict=True
            ):
                last = rows[-1]
                summaries.append(
                    {
                        "experiment": entry.name,
                        "n_options": cfg.n_options,
                        "seed": seed,
                        "episodes": iterations * B,
                        "iterations": iterations,
                        "final_average_reward": last["average_reward"],
                        "final_return": last["average_reward"],
                        "zone3_share": last["zone3_share"],
                        "final_zone_reward": last["zone_reward"],
                        "n_active_options": [int(p.active.sum()) for p in policies],
                        "seconds_per_shot": elapsed / shots,
                        **(
                            evaluate_final_policy(cfg, policies, params, n_eval, seed)
                            if n_eval
                            else {}
                        ),
                    }
                )
            return run.finish(summaries, title=label, ylabel="average reward per episode")
    finally:
        pool.close()


def _members(algo: Algorithm, S: int) -> list[list[Any]]:
    """Each of the ``S`` members' policies (copies)."""
    return [[p.member(m) for p in algo.policies] for m in range(S)]


def _actor(policies: list[Any], sequential: bool) -> Any:
    return time_indexed_module(policies) if sequential else policy_module(policies[0])


def _postfix(row: dict[str, Any]) -> dict[str, Any]:
    return {"reward": f"{row['average_reward']:.2f}", "zone3": f"{row['zone3_share']:.2f}"}


def _entry(name: str, config: type) -> Experiment:
    return Experiment(
        name,
        config,
        run,
        algorithm,
        metric="final_average_reward",
        curve="average_reward",
        run_only=("workers",),  # its episodes are played by index, by any number of workers
    )


VARIANTS = (
    _entry("hockey-sequential", HockeySequentialConfig),
    _entry("hockey-episodic", HockeyEpisodicConfig),
    _entry("hockey-fixed-start", HockeyFixedStartConfig),
)
