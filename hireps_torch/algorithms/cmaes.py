"""CMA-ES (Hansen's pycma) behind the library's ask/tell, for episodic tasks without contexts.

The baseline a user would pick instead of HiREPS: one Gaussian search distribution whose mean,
step size and covariance pycma adapts from the ranks of the returns. This adapter only
translates: ``ask(N)`` is pycma's ``ask`` of N candidates, ``tell`` gives it the negated
returns (pycma minimises). Its :attr:`policy` is a one-option :class:`HierarchicalPolicy`
holding pycma's mean and covariance ``sigma^2 C`` after every ``tell``, so that evaluations,
``load_run`` and the versatility measures treat CMA-ES as any other algorithm.

pycma's options are its defaults (the population size and per-coordinate scales aside); a
member that its termination criteria stop keeps its distribution from then on. Each member
draws its normal numbers from its own ``numpy.random.Generator`` (seeded by the member's
``"sampling"`` stream), never from numpy's global one. A checkpoint holds each member's pycma
strategy pickled: resume only from checkpoints you wrote.
"""

from __future__ import annotations

import math
import pickle
import warnings
from collections.abc import Mapping, Sequence
from typing import Any, Self

import cma
import numpy as np
import torch
from torch import Tensor

from hireps_torch.algorithms.base import Experience, HiREPSBase, member_policies
from hireps_torch.checks import as_float_tensor, check_count, check_finite

__all__ = ["CMAES"]


class _Normal:
    """pycma's ``randn(lam, N)`` from a generator of this member's own (picklable)."""

    def __init__(self, seed: int) -> None:
        self.rng = np.random.default_rng(seed)

    def __call__(self, *shape: int) -> np.ndarray:
        out: np.ndarray = self.rng.standard_normal(shape)
        return out


def _covariance(es: Any) -> np.ndarray:
    """pycma's covariance ``sigma^2 diag(s) C diag(s)`` (``s``: the coordinates' scaling,
    ``CMA_stds`` and ``minstd``), with sigma s formed first: sigma and C alone can underflow
    where the product does not."""
    scale = es.sigma * np.asarray(es.sigma_vec.scaling, dtype=np.float64)
    C = es.C
    out: np.ndarray = scale[:, None] * np.asarray(C, dtype=np.float64) * scale[None, :]
    return out


class CMAES(HiREPSBase):
    """CMA-ES with ask/tell (see the module docstring).

    Example::

        algo = CMAES.create(param_dim=10, popsize=50, init_std=1.0, seed=0)
        for _ in range(100):
            theta = algo.ask(50)                        # (50, 10)
            diagnostics = algo.tell(None, theta, objective(theta))

    Args (of :meth:`create`):
        param_dim: D >= 2 (pycma's lower limit).
        popsize: N, the candidates of every ``ask``.
        init_mean: (D,) start of the mean (zeros by default).
        init_std: initial standard deviation, a number or (D,) (pycma's ``sigma0`` times its
            ``CMA_stds``).
        seed: one seed, or S distinct seeds for a population of S independent runs (every
            input and output gains a leading S).
        population: S with the default seeds 0 .. S-1.
    """

    def __init__(
        self,
        strategies: Sequence[Any],
        policy: Any,
        *,
        seed: int | Sequence[int] | None,
    ) -> None:
        super().__init__(policy, kappa_rel=None, prune_threshold=0.0, seed=seed)
        self.strategies = list(strategies)
        self.popsize = int(self.strategies[0].popsize)
        self.param_dim = policy.action_dim
        self.context_dim = 0
        self._asked: list[np.ndarray] | None = None

    @classmethod
    def create(
        cls,
        param_dim: int,
        *,
        popsize: int,
        init_mean: Tensor | None = None,
        init_std: float | Tensor = 1.0,
        seed: int | Sequence[int] | None = None,
        population: int | None = None,
    ) -> Self:
        D = check_count("param_dim", param_dim, 2)
        N = check_count("popsize", popsize, 2)
        std = as_float_tensor("init_std", init_std).to(torch.float64).expand(D).clone()
        if not bool((torch.isfinite(std) & (std > 0)).all()):
            raise ValueError(f"init_std must be finite and > 0, got {init_std}")
        mean = torch.zeros(D, dtype=torch.float64) if init_mean is None else init_mean
        mean = as_float_tensor("init_mean", mean).to(torch.float64)
        if mean.shape != (D,):
            raise ValueError(f"init_mean must have shape ({D},), got {tuple(mean.shape)}")
        check_finite("init_mean", mean)
        policies, sampling, seeds = member_policies(
            seed, population, [mean], 1, 0, D, init_std=std, min_variance=1e-100
        )
        sigma0 = float(std.max())
        options = {
            "popsize": N,
            "CMA_stds": (std / sigma0).tolist(),
            "seed": math.nan,  # no numpy global seeding: each member its own randn
            "verbose": -9,
            "verb_log": 0,
            "verb_disp": 0,
        }
        assert sampling is not None
        members = sampling if isinstance(sampling, list) else [sampling]
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # pycma's notes on its options
            strategies = [
                cma.CMAEvolutionStrategy(mean.tolist(), sigma0, {**options, "randn": _Normal(s)})
                for s in members
            ]
        algo = cls(strategies, policies[0], seed=sampling)
        algo.seeds = seeds
        return algo

    # ---- ask / tell -------------------------------------------------------------------------
    def ask(self, contexts: Tensor | int | None) -> Tensor:
        """``popsize`` candidates: (N, D), or (S, N, D) for a population (``contexts``: N or
        None; tasks without contexts only)."""
        n = self.popsize if contexts is None else check_count("contexts", contexts, 1)
        if n != self.popsize:
            raise ValueError(f"CMA-ES asks its popsize {self.popsize} candidates, not {n}")
        asked = [np.asarray(es.ask(), dtype=np.float64) for es in self.strategies]
        self._asked = asked
        theta = torch.as_tensor(np.stack(asked), device=self.device)
        return theta if self.population is not None else theta[0]

    def act(self, contexts: Tensor | int | None) -> Tensor:
        """The mean (N, D) (or (S, N, D)) repeated for N = ``contexts``."""
        return self.mean_action(contexts)

    @torch.no_grad()
    def tell(
        self, contexts: Tensor | int | None, params: Tensor, returns: Tensor
    ) -> dict[str, Any]:
        """Update every member from the returns ([S,] N) of the candidates of the last
        :meth:`ask` (``params`` must be those); raising changes nothing.

        A member that pycma's own termination criteria stopped (its defaults: ``tolx``,
        ``tolfun``, ...) keeps its distribution: its later candidates are drawn from it and
        its ``tell`` changes nothing (``stopped``).

        Returns:
            ``sigma, policy_entropy, mean_return, max_return, n_active_options, stopped,
            iteration`` (per member).
        """
        if self._asked is None:
            raise ValueError("tell needs the candidates of an ask before it")
        lead = () if self.population is None else (self.population,)
        want = (*lead, self.popsize, self.param_dim)
        theta = as_float_tensor("params", params).to(torch.float64).cpu()
        if tuple(theta.shape) != want:
            raise ValueError(f"params must have shape {want}, got {tuple(theta.shape)}")
        if not torch.equal(theta.reshape(-1, *want[-2:]), torch.as_tensor(np.stack(self._asked))):
            raise ValueError("params must be the candidates of the last ask, unchanged")
        R = as_float_tensor("returns", returns).to(torch.float64).cpu()
        if tuple(R.shape) != want[:-1]:
            raise ValueError(f"returns must have shape {want[:-1]}, got {tuple(R.shape)}")
        check_finite("returns", R)
        R = R.reshape(-1, self.popsize)
        stopped = []
        for es, x, r in zip(self.strategies, self._asked, R, strict=True):
            if not es.stop():  # converged by pycma's own criteria (tolx, tolfun, ...): frozen
                es.tell(list(x), (-r).tolist())
            stopped.append(bool(es.stop()))
        self._asked = None
        self._sync_policy()
        self.iteration += 1
        opt = self.policy.sub_policies[0]
        entropy = opt.entropy().reshape(-1)
        one = self.population is None
        report: dict[str, Any] = {
            "iteration": self.iteration,
            "sigma": [float(es.sigma) for es in self.strategies],
            "policy_entropy": entropy.tolist(),
            "mean_return": R.mean(-1).tolist(),
            "max_return": R.amax(-1).tolist(),
            "n_active_options": [1] * R.shape[0],
            "stopped": stopped,
        }
        if one:
            return {k: v if k == "iteration" else v[0] for k, v in report.items()}
        report["iteration"] = [self.iteration] * R.shape[0]
        return report

    def _sync_policy(self) -> None:
        """The one option's mean and Cholesky factor from pycma's mean and covariance
        ``sigma^2 diag(s) C diag(s)`` (``s``: the coordinates' scaling, ``CMA_stds``)."""
        opt = self.policy.sub_policies[0]
        means = torch.as_tensor(np.stack([es.mean for es in self.strategies]))
        covs = torch.as_tensor(np.stack([_covariance(es) for es in self.strategies]))
        covs = (covs + covs.mT) / 2
        chol = torch.linalg.cholesky(covs)
        shape = opt.bias.shape
        opt.bias.copy_(means.reshape(shape).to(opt.bias))
        opt.chol.copy_(chol.reshape(opt.chol.shape).to(opt.chol))

    def learn(self, experience: Experience) -> dict[str, Any]:
        """:meth:`tell` from parameters (N, 1, D) and returns (N, 1) (no contexts)."""
        e = self._experience(experience)
        return self.tell(None, e.actions[..., 0, :], e.rewards[..., 0])

    def _states(self, states: Any) -> Tensor:
        """A count N (None: 1) or empty contexts ([S,] N, 0) as the policy's (S, N, 0)."""
        if isinstance(states, Tensor) and states.dim() >= 2:
            if states.shape[-1] != 0:
                raise ValueError(f"CMA-ES takes no context, got contexts {tuple(states.shape)}")
            states = states.shape[-2]
        n = check_count("N", states, 1) if states is not None else 1
        lead = () if self.population is None else (self.population,)
        return torch.zeros(*lead, n, 0, dtype=torch.float64, device=self.device)

    # ---- checkpointing ----------------------------------------------------------------------
    def state_dict(self) -> dict[str, Any]:
        """Each member's pycma strategy (pickled bytes) and the policy that mirrors it."""
        return self._state(
            policy=self.policy.state_dict(),
            strategies=[pickle.dumps(es) for es in self.strategies],
        )

    def load_state_dict(self, state: Mapping[str, Any]) -> None:
        """Restore :meth:`state_dict`'s output; one that does not fit raises, changing nothing."""
        state = self._keys_checked(state, "policy", "strategies")
        blobs = state["strategies"]
        if not isinstance(blobs, list | tuple) or len(blobs) != len(self.strategies):
            raise ValueError(
                f"the state holds {len(blobs) if isinstance(blobs, list | tuple) else 'no'} "
                f"strategies, this CMA-ES {len(self.strategies)}"
            )
        strategies = [pickle.loads(b) for b in blobs]
        if any(es.N != self.param_dim or es.popsize != self.popsize for es in strategies):
            raise ValueError(
                f"the state's strategies do not fit D = {self.param_dim}, popsize {self.popsize}"
            )
        self.policy.check_state_dict(state["policy"])
        self._load_shared(state)
        self.policy.load_state_dict(state["policy"])
        self.strategies = strategies
        self._asked = None
