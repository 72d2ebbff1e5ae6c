"""Population runs: S seeds of one algorithm in one object, each member learning what it learns
alone (three updates equal to 1e-8, samples independent of the companions)."""

import copy
import warnings

import pytest
import torch

from hireps_torch.algorithms import (
    EpisodicHiREPS,
    Experience,
    InfiniteHorizonHiREPS,
    TimeIndexedHiREPS,
)
from hireps_torch.algorithms.base import stream_seed
from hireps_torch.features import FourierFeatures

SEEDS = [3, 5, 11]
UPDATES = 3


def objective(theta, c):
    return -((theta - c.sum(-1, keepdim=True)) ** 2).sum(-1)


def contexts(seed, S=3, N=30):
    return torch.randn(S, N, 1, generator=torch.Generator().manual_seed(seed), dtype=torch.float64)


def assert_members_equal(pop_policy, alone, atol):
    state = pop_policy.state_dict()
    for s, algo in enumerate(alone):
        for key, value in algo.policy.state_dict().items():
            if "features" in key or key.endswith("min_variance"):  # shared by the members
                continue
            mine = state[key][s]
            if value.dtype == torch.bool:
                assert torch.equal(mine, value), key
            else:
                torch.testing.assert_close(mine, value, rtol=0, atol=atol, msg=key)


@pytest.mark.parametrize("n_options, kappa_rel", [(1, None), (3, None), (3, 0.9)])
def test_episodic_population_equals_separate_runs(n_options, kappa_rel):
    kwargs = dict(context_dim=1, n_options=n_options, kappa_rel=kappa_rel, init_std=1.0)
    pop = EpisodicHiREPS.create(2, seed=SEEDS, **kwargs)
    alone = [EpisodicHiREPS.create(2, seed=s, **kwargs) for s in SEEDS]
    assert pop.population == 3 and pop.policy.population == 3
    assert_members_equal(pop.policy, alone, 0.0)  # the same initial policies
    for it in range(UPDATES):
        c = contexts(it)
        theta = pop.ask(c)
        report = pop.tell(c, theta, objective(theta, c))
        for s, algo in enumerate(alone):
            own = algo.ask(c[s])
            torch.testing.assert_close(theta[s], own, rtol=0, atol=1e-10)
            mine = algo.tell(c[s], own, objective(own, c[s]))
            for key in ("eta", "kl", "effective_sample_size", "cross_entropy"):
                assert report[key][s] == pytest.approx(mine[key], rel=1e-8, abs=1e-10), key
            assert report["n_active_options"][s] == mine["n_active_options"]
            assert report["refitted"][s] == mine["refitted"]
        assert_members_equal(pop.policy, alone, 1e-8)


def test_a_member_learns_the_same_whatever_its_companions():
    kwargs = dict(context_dim=1, n_options=3, init_std=1.0)
    first = EpisodicHiREPS.create(2, seed=[3, 5], **kwargs)
    second = EpisodicHiREPS.create(2, seed=[3, 8, 9], **kwargs)
    g = torch.Generator().manual_seed(0)
    for _ in range(2):
        c = torch.randn(1, 30, 1, generator=g, dtype=torch.float64)
        t1, t2 = first.ask(c.expand(2, -1, -1)), second.ask(c.expand(3, -1, -1))
        torch.testing.assert_close(t1[0], t2[0], rtol=0, atol=1e-10)
        first.tell(c.expand(2, -1, -1), t1, objective(t1, c))
        second.tell(c.expand(3, -1, -1), t2, objective(t2, c))
    theirs = second.policy.state_dict()
    for key, value in first.policy.state_dict().items():
        if value.dim() and value.shape[0] == 2:  # the members' own tensors
            torch.testing.assert_close(value[0], theirs[key][0], rtol=0, atol=1e-10, msg=key)


def test_copies_of_one_problem_get_identical_updates():
    pop = EpisodicHiREPS.create(2, n_options=3, seed=[7, 8, 9])
    one = {
        k: v[:1].expand_as(v).clone() for k, v in pop.policy.state_dict().items() if "feat" not in k
    }
    pop.policy.load_state_dict(one, strict=False)
    theta = pop.ask(20)[:1].expand(3, -1, -1).clone()
    pop.tell(None, theta, -(theta**2).sum(-1))
    for value in pop.policy.state_dict().values():
        if value.dim() and value.shape[0] == 3:
            assert torch.equal(value[0], value[1]) and torch.equal(value[0], value[2])


def test_a_flat_member_is_left_alone_while_the_others_learn():
    pop = EpisodicHiREPS.create(2, n_options=3, seed=[0, 1])
    before = {k: v.clone() for k, v in pop.policy.state_dict().items()}
    theta = pop.ask(20)
    returns = -(theta**2).sum(-1)
    returns[1] = 1.0  # member 1: no information
    report = pop.tell(None, theta, returns)
    assert report["refitted"] == [True, False]
    after = pop.policy.state_dict()
    for key, value in before.items():
        if value.dim() and value.shape[0] == 2:
            assert torch.equal(after[key][1], value[1]), key
    assert not torch.equal(after["options.0.bias"][0], before["options.0.bias"][0])


def test_infinite_horizon_population_equals_separate_runs():
    vf = FourierFeatures([-1.0, -1.0], [1.0, 1.0], 3)
    s0 = torch.rand(50, 2, generator=torch.Generator().manual_seed(2), dtype=torch.float64)
    kw = dict(value_features=vf, initial_states=0.2 * s0, gamma=0.95, n_options=3, init_std=0.5)
    pop = InfiniteHorizonHiREPS.create(2, 1, seed=SEEDS, **kw)
    alone = [InfiniteHorizonHiREPS.create(2, 1, seed=s, **kw) for s in SEEDS]
    g = torch.Generator().manual_seed(1)
    states = torch.rand(3, 60, 2, generator=g, dtype=torch.float64) * 2 - 1
    for _ in range(UPDATES):
        actions = pop.sample(states)
        nxt = (states + 0.1 * torch.cat([actions, -actions], -1)).clamp(-1, 1)
        rewards = -(nxt**2).sum(-1)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # the same warnings alone and together
            report = pop.learn(
                Experience(
                    states[:, :, None], actions[:, :, None], rewards[..., None], nxt[:, :, None]
                )
            )
            for s, algo in enumerate(alone):
                own = algo.sample(states[s])
                torch.testing.assert_close(actions[s], own, rtol=0, atol=1e-12)
                mine = algo.update(states[s], own, rewards[s], nxt[s])
                assert report["eta"][s] == pytest.approx(mine["eta"], rel=1e-8)
                assert report["kl"][s] == pytest.approx(mine["kl"], rel=1e-8, abs=1e-12)
                torch.testing.assert_close(
                    pop.value_weights[s], algo.value_weights, rtol=1e-8, atol=1e-8
                )
        assert_members_equal(pop.policy, alone, 1e-8)
        states = nxt
    assert pop.value(states).shape == (3, 60)


def test_population_checkpoint_round_trip():
    pop = EpisodicHiREPS.create(2, n_options=2, seed=[1, 2])
    state = copy.deepcopy(pop.state_dict())
    theta = pop.ask(10)
    pop.tell(None, theta, -(theta**2).sum(-1))
    again = EpisodicHiREPS.create(2, n_options=2, seed=[1, 2])
    again.load_state_dict(state)
    torch.testing.assert_close(again.ask(10), theta)
    with pytest.raises(ValueError, match=r"gating.bias: saved \(2, 2\), expected \(3, 2\)"):
        EpisodicHiREPS.create(2, n_options=2, seed=[1, 2, 3]).load_state_dict(state)


def test_bad_population_settings_name_the_value():
    with pytest.raises(ValueError, match=r"population = 4 does not match the 3 seeds given"):
        EpisodicHiREPS.create(2, seed=[0, 1, 2], population=4)
    with pytest.raises(ValueError, match="seed 1 is repeated"):
        EpisodicHiREPS.create(2, seed=[0, 1, 1])
    with pytest.raises(ValueError, match="seeds -1 and 18446744073709551615 .* are one seed"):
        EpisodicHiREPS.create(2, seed=[-1, 2**64 - 1])
    with pytest.raises(ValueError, match="takes one seed per member"):
        EpisodicHiREPS.create(2, seed=3, population=2)
    assert EpisodicHiREPS.create(2, population=2).population == 2
    pop = EpisodicHiREPS.create(2, context_dim=1, seed=[0, 1])
    with pytest.raises(ValueError, match=r"contexts must have shape \(S, N, C\) = \(2, N, 1\)"):
        pop.ask(torch.zeros(3, 5, 1))
    theta = pop.ask(torch.zeros(2, 5, 1))
    with pytest.raises(ValueError, match=r"returns must have shape \(S, N\) = \(2, N\)"):
        pop.tell(torch.zeros(2, 5, 1), theta, torch.zeros(5))
    with pytest.raises(ValueError, match="is on device meta"):
        pop.tell(torch.zeros(2, 5, 1), theta.to("meta"), torch.zeros(2, 5))


def test_a_members_sampling_stream_is_not_another_members_policy_stream():
    # member s's sampling generator is its seed's "sampling" stream, not seed + 1: with the
    # default seeds 0 .. S-1, seed + 1 would replay member s + 1's initial option means
    pop = EpisodicHiREPS.create(2, n_options=3, population=3)
    for s, gen in enumerate(pop.generator):
        assert torch.equal(
            gen.get_state(), torch.Generator().manual_seed(stream_seed(s, "sampling")).get_state()
        )
        for t in range(4):  # the policy streams of every member (and of seed 3)
            assert not torch.equal(gen.get_state(), torch.Generator().manual_seed(t).get_state())
    assert torch.equal(
        EpisodicHiREPS.create(2, seed=None).ask(4), EpisodicHiREPS.create(2, seed=0).ask(4)
    )


def test_the_top_seed_works_alone_and_in_a_population():
    top = 2**64 - 1
    alone, pop = EpisodicHiREPS.create(2, seed=top), EpisodicHiREPS.create(2, seed=[top, 0])
    torch.testing.assert_close(pop.ask(5)[0], alone.ask(5), rtol=0, atol=0)


@pytest.mark.parametrize(
    "make",
    [
        lambda **kw: EpisodicHiREPS.create(2, n_options=2, **kw),
        lambda **kw: TimeIndexedHiREPS.create(2, 1, 1, n_options=2, **kw),
        lambda **kw: InfiniteHorizonHiREPS.create(
            1, 1, n_options=2, value_features=FourierFeatures([-1.0], [1.0], 3),
            initial_states=torch.zeros(4, 1, dtype=torch.float64), gamma=0.9, **kw,
        ),
    ],
)  # fmt: skip
def test_every_create_takes_the_prune_threshold(make):
    assert make(prune_threshold=0.25, seed=0).prune_threshold == 0.25
    with pytest.raises(ValueError, match="prune_threshold"):
        make(prune_threshold=-1.0, seed=0)


def test_a_population_kappa_of_the_wrong_length_names_the_member_shapes():
    from hireps_torch.dual import solve_episodic_dual

    R = torch.randn(3, 20, generator=torch.Generator().manual_seed(0), dtype=torch.float64)
    lr = torch.full((3, 20, 3), -torch.log(torch.tensor(3.0)), dtype=torch.float64)
    kw = dict(epsilon=0.5, log_responsibilities=lr, population=True)
    with pytest.raises(
        ValueError, match=r"kappa must be .* or per member \(3, 1\) or \(3,\), got \(2,\)"
    ):
        solve_episodic_dual(R, kappa=torch.tensor([0.9, 0.8]), **kw)
    sol = solve_episodic_dual(R, kappa=torch.tensor([0.9, 0.8, 0.7]), **kw)
    assert sol.eta.shape[0] == 3


@pytest.mark.parametrize("kappa_rel", [None, 0.9])
def test_time_indexed_population_equals_separate_runs(kappa_rel):
    """Three steps, the first without reward in the first update (its KL bound inactive)."""
    kw = dict(n_options=3, init_std=0.5, kappa_rel=kappa_rel)
    pop = TimeIndexedHiREPS.create(3, 2, 1, seed=SEEDS, **kw)
    alone = [TimeIndexedHiREPS.create(3, 2, 1, seed=s, **kw) for s in SEEDS]
    g = torch.Generator().manual_seed(0)
    for it in range(UPDATES):
        states = torch.zeros(3, 40, 3, 1, dtype=torch.float64)
        params = torch.zeros(3, 40, 3, 2, dtype=torch.float64)
        states[:, :, 0] = torch.randn(3, 40, 1, generator=g, dtype=torch.float64)
        for k in range(3):
            params[:, :, k] = pop.ask(k, states[:, :, k])
            if k < 2:
                states[:, :, k + 1] = states[:, :, k] + params[:, :, k, :1]
        rewards = -(params**2).sum(-1) - (states[..., 0] - 1) ** 2
        if it == 0:
            rewards[:, :, 0] = 0.0
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # the same warnings alone and together
            report = pop.learn(Experience(states, params, rewards))
            for s, algo in enumerate(alone):
                own = torch.stack([algo.ask(k, states[s, :, k]) for k in range(3)], 1)
                torch.testing.assert_close(own, params[s], rtol=0, atol=1e-10)
                mine = algo.tell(states[s], own, rewards[s])
                assert report["eta"][s] == pytest.approx(mine["eta"], rel=1e-8)
                assert report["kl"][s] == pytest.approx(mine["kl"], rel=1e-8, abs=1e-12)
                assert report["n_active_options"][s] == mine["n_active_options"]
                torch.testing.assert_close(
                    pop.value_weights[s], algo.value_weights, rtol=1e-8, atol=1e-8
                )
        for k, policy in enumerate(pop.policies):
            state = policy.state_dict()
            for s, algo in enumerate(alone):
                for key, value in algo.policies[k].state_dict().items():
                    if "features" not in key and not key.endswith("min_variance"):
                        torch.testing.assert_close(
                            state[key][s].double(), value.double(), rtol=0, atol=1e-8
                        )
    assert pop.value(1, states[:, :, 1]).shape == (3, 40)


def test_the_duals_warnings_name_a_member_and_its_seed():
    # epsilon 10 >> log 20: every member's weights collapse onto ~one sample; the warning says
    # which member, with the seed a user passed (member 0 is seed 7, not seed 0)
    from hireps_torch.dual import DegenerateWeightsWarning
    from hireps_torch.dual.episodic import episodic_solution
    from hireps_torch.dual.solver import LbfgsSettings

    pop = EpisodicHiREPS.create(2, n_options=1, init_std=1.0, epsilon=10.0, seed=[7, 2])
    theta = pop.ask(20)
    with pytest.warns(DegenerateWeightsWarning) as record:
        pop.tell(None, theta, -(theta**2).sum(-1))
    text = " ".join(str(r.message) for r in record)
    assert "member 0 (seed 7), " in text and "member 1 (seed 2), " in text, text
    # a dual that cannot meet its entropy bound says so under the member's name and seed
    gen = torch.Generator().manual_seed(7)
    R = torch.randn(2, 30, generator=gen, dtype=torch.float64)
    lr = torch.log_softmax(8 * torch.randn(2, 30, 3, generator=gen, dtype=torch.float64), -1)
    lr[1] = torch.log_softmax(0.01 * torch.randn(30, 3, generator=gen, dtype=torch.float64), -1)
    eps, kappa = torch.full((2, 1), 0.05, dtype=torch.float64), torch.full((2, 1), 0.3)
    with warnings.catch_warnings(record=True) as record:
        warnings.simplefilter("always")
        episodic_solution(R, lr, eps, None, kappa.double(), LbfgsSettings(), seeds=[7, 2])
    texts = [str(r.message) for r in record]
    assert texts and all(t.startswith("member 1 (seed 2): ") for t in texts), texts


def test_every_variant_hands_its_members_seeds_to_the_dual(monkeypatch):
    import hireps_torch.dual.episodic as episodic_dual
    import hireps_torch.dual.infinite_horizon as infinite_dual
    import hireps_torch.dual.time_indexed as time_dual

    seen = []
    for module in (episodic_dual, infinite_dual, time_dual):

        def spy(*args, _real=module.solve_blocks, **kwargs):
            seen.append(kwargs.get("seeds"))
            return _real(*args, **kwargs)

        monkeypatch.setattr(module, "solve_blocks", spy)
    g = torch.Generator().manual_seed(0)
    episodic = EpisodicHiREPS.create(2, seed=SEEDS)
    theta = episodic.ask(20)
    vf = FourierFeatures([-1.0, -1.0], [1.0, 1.0], 2)
    s0 = torch.rand(3, 30, 2, generator=g, dtype=torch.float64)
    infinite = InfiniteHorizonHiREPS.create(
        2, 1, value_features=vf, initial_states=s0[0], gamma=0.9, seed=SEEDS
    )
    actions = infinite.sample(s0)
    timed = TimeIndexedHiREPS.create(2, 2, 1, seed=SEEDS)
    states = torch.randn(3, 20, 2, 1, generator=g, dtype=torch.float64)
    params = torch.stack([timed.ask(k, states[:, :, k]) for k in range(2)], 2)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        episodic.tell(None, theta, -(theta**2).sum(-1))
        infinite.update(s0, actions, -(s0**2).sum(-1), s0.flip(-1))
        timed.tell(states, params, -(params**2).sum(-1))
    assert seen == [SEEDS, SEEDS, SEEDS]
    # the names are checked where they are set: one integer per member
    with pytest.raises(ValueError, match=r"seeds must be 3 integers, one per member, got \[7\]"):
        episodic.seeds = [7]
    with pytest.raises(TypeError, match=r"seeds\[1\] must be an integer"):
        episodic.seeds = [7, 1.5, 2]
    assert episodic.seeds == SEEDS  # a refused value changes nothing
    with pytest.raises(ValueError, match="seeds must be None for one run"):
        EpisodicHiREPS.create(2, seed=3).seeds = [3]
    # a one-run policy built with a list of one seed, as before: no names, no error
    assert EpisodicHiREPS(EpisodicHiREPS.create(2).policy, seed=[3]).seeds is None
