"""Policy populations (``stack``): S policies in one module, each member computing what it
would alone."""

import pytest
import torch

from hireps_torch._linalg import matmul_each, reduce_each
from hireps_torch.features import QuadraticFeatures
from hireps_torch.policies import ConstantGating, HierarchicalPolicy, LinearGaussian, SoftmaxGating
from hireps_torch.policies._population import categorical

S, N, C, D, O = 3, 40, 2, 3, 4


def members(O=O, C=C, spread=2.0, **kwargs):
    return [
        HierarchicalPolicy.create(
            O,
            C,
            D,
            spread=spread,
            gating_features=QuadraticFeatures(C),
            generator=torch.Generator().manual_seed(s),
            **kwargs,
        )
        for s in range(S)
    ]


def data(seed=0, C=C):
    g = torch.Generator().manual_seed(seed)
    ctx = torch.randn(S, N, C, generator=g, dtype=torch.float64)
    theta = 2.0 * torch.randn(S, N, D, generator=g, dtype=torch.float64)
    w = torch.rand(S, N, O, generator=g, dtype=torch.float64) ** 4
    return ctx, theta, w


def gens(offset=10):
    return [torch.Generator().manual_seed(offset + s) for s in range(S)]


def test_each_member_samples_what_it_samples_alone():
    pols = members()
    pop = HierarchicalPolicy.stack(pols)
    ctx, _, _ = data()
    theta, option = pop.sample(ctx, gens())
    assert theta.shape == (S, N, D) and option.shape == (S, N)
    for s, g in enumerate(gens()):
        alone, alone_option = pols[s].sample(ctx[s], g)
        assert torch.equal(option[s], alone_option)
        torch.testing.assert_close(theta[s], alone, rtol=0, atol=1e-12)


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
@pytest.mark.parametrize("rows,options", [(1, 1), (7, 3), (40, 5), (8000, 5), (33, 100)])
def test_categorical_draws_what_multinomial_draws(dtype, rows, options):
    # per member, the option and the generator's state after it are multinomial's, bit for bit
    g = torch.Generator().manual_seed(rows + options)
    probs = torch.softmax(3 * torch.randn(S, rows, options, generator=g, dtype=dtype), -1)
    if options > 1:
        probs[:, 0, 1] = 0.0  # an option without mass
        probs = probs / probs.sum(-1, keepdim=True)
    mine, ref = gens(), gens()
    drawn = categorical(probs, mine)
    assert drawn.shape == (S, rows) and drawn.dtype == torch.long
    for s in range(S):
        expected = torch.multinomial(probs[s], 1, generator=ref[s])[:, 0]
        assert torch.equal(drawn[s], expected)
        assert torch.equal(mine[s].get_state(), ref[s].get_state())
    one, other = gens()[0], gens()[0]
    expected = torch.multinomial(probs[0], 1, generator=other)[:, 0]
    assert torch.equal(categorical(probs[0], one), expected)


def test_a_members_samples_do_not_depend_on_its_companions():
    ctx, _, _ = data()
    pols = members()
    first = HierarchicalPolicy.stack(pols).sample(ctx, gens())[0]
    others = members(spread=0.1)  # other companions, member 0 the same
    second = HierarchicalPolicy.stack([pols[0], *others[1:]]).sample(ctx, gens())[0]
    torch.testing.assert_close(first[0], second[0], rtol=0, atol=1e-12)
    assert not torch.allclose(first[1], second[1])


def test_population_scores_equal_the_members_scores():
    pols = members()
    pop = HierarchicalPolicy.stack(pols)
    ctx, theta, _ = data()
    joint, resp = pop.log_joint(ctx, theta), pop.responsibilities(ctx, theta)
    mean, chosen = pop.mean_action(ctx)
    for s, p in enumerate(pols):
        torch.testing.assert_close(joint[s], p.log_joint(ctx[s], theta[s]), rtol=0, atol=1e-12)
        torch.testing.assert_close(resp[s], p.responsibilities(ctx[s], theta[s]))
        m, o = p.mean_action(ctx[s])
        torch.testing.assert_close(mean[s], m, rtol=0, atol=1e-12)
        assert torch.equal(chosen[s], o)
    assert pop.option_entropy(ctx, theta).shape == (S,)


@pytest.mark.parametrize("mean_prior", [0.0, 3.0])
def test_population_refit_equals_each_members_refit(mean_prior):
    pols = members(mean_prior=mean_prior, covariance_prior=2.0)
    pols[1].prune(torch.zeros(1, C), threshold=0.0)  # nothing pruned; member 2 loses option 1
    pols[2].gating.active[1] = False
    pop = HierarchicalPolicy.stack(pols)
    ctx, theta, w = data()
    w[2, :, 1] = 0.0
    w[0, :, 3] = 0.0  # member 0: option 3 without weight keeps its parameters
    new = pop.fit_parameters(ctx, theta, w)
    for s, p in enumerate(pols):
        alone = p.fit_parameters(ctx[s], theta[s], w[s])
        for key, value in alone.items():
            torch.testing.assert_close(new[key][s], value, rtol=0, atol=1e-9, msg=key)
    torch.testing.assert_close(new["options.3.bias"][0], pols[0].sub_policies[3].bias)
    torch.testing.assert_close(new["options.1.chol"][2], pols[2].sub_policies[1].chol)
    pop.weighted_fit(ctx, theta, w)
    for s, p in enumerate(pols):
        p.weighted_fit(ctx[s], theta[s], w[s])
        torch.testing.assert_close(
            pop.member(s).log_prob(ctx[s], theta[s]), p.log_prob(ctx[s], theta[s])
        )


def test_copies_of_one_policy_get_identical_refits():
    one = members()[0]
    pop = HierarchicalPolicy.stack([one, one, one])
    ctx, theta, w = data()
    ctx, theta, w = (t[:1].expand_as(t).clone() for t in (ctx, theta, w))
    new = pop.fit_parameters(ctx, theta, w)
    for value in new.values():
        assert torch.equal(value[0], value[1]) and torch.equal(value[0], value[2])


@pytest.mark.parametrize("workers", [2, 3])
def test_a_refit_with_members_side_by_side_equals_one_after_the_other(monkeypatch, workers):
    import hireps_torch._parallel as parallel

    ctx, theta, w = data()
    fits = {}
    for n in (1, workers):
        monkeypatch.setattr(parallel, "idle_workers", lambda device, n=n: n)
        monkeypatch.setattr(parallel, "MIN_SIZE", 0)  # these small problems too
        fits[n] = HierarchicalPolicy.stack(members()).fit_parameters(ctx, theta, w)
    for key, value in fits[1].items():
        assert torch.equal(value, fits[workers][key]), key


def test_gating_fit_reaches_its_minimiser():
    """LBFGS then Newton steps: the single fit is the minimiser to round-off, so a population
    (another LBFGS path) lands on the same point."""
    gating = SoftmaxGating(5, O)
    ctx, theta, w = data()
    x = QuadraticFeatures(C)(ctx[0])
    ws = w[0].sum(-1)
    fit = gating.fit_parameters(x, w[0] / ws[:, None], ws)
    Wt = fit["weight"].clone().requires_grad_(True)
    bt = fit["bias"].clone().requires_grad_(True)
    logp = torch.log_softmax(x @ Wt.T + bt, -1)
    loss = -((ws / ws.sum())[:, None] * (w[0] / ws[:, None]) * logp).sum()
    (loss + 0.5 * gating.l2 * (Wt**2).sum()).backward()
    assert float(torch.cat([Wt.grad.flatten(), bt.grad]).abs().max()) < 1e-10


def test_prune_acts_per_member():
    pols = members()
    pols[1].gating.bias.data = torch.tensor([5.0, 0.0, -20.0, -20.0], dtype=torch.float64)
    pop = HierarchicalPolicy.stack(pols)
    ctx = data()[0]
    assert pop.prune(ctx, 1e-4) == [p.prune(ctx[s], 1e-4) for s, p in enumerate(pols)]
    assert pop.active[1].tolist() == [True, True, False, False]
    assert bool(pop.active[0].all())


def test_context_free_and_constant_gatings_stack():
    free = [SoftmaxGating(0, O) for _ in range(S)]
    free[0].active[2] = False
    pop = SoftmaxGating.stack(free)
    t = torch.rand(S, N, O, dtype=torch.float64)
    t[0, :, 2] = 0.0
    t = t / t.sum(-1, keepdim=True)
    w = torch.rand(S, N, dtype=torch.float64)
    new = pop.fit_parameters(torch.zeros(S, N, 0), t, w)
    for s, g in enumerate(free):
        torch.testing.assert_close(
            new["bias"][s], g.fit_parameters(torch.zeros(N, 0), t[s], w[s])["bias"]
        )
    consts = [ConstantGating(torch.randn(O, 2, dtype=torch.float64)) for _ in range(S)]
    cpop = ConstantGating.stack(consts)
    x = torch.randn(S, N, 2, dtype=torch.float64)
    for s, g in enumerate(consts):
        assert torch.equal(cpop.log_probs(x)[s], g.log_probs(x[s]))


def test_member_gives_back_an_ordinary_copy():
    pols = members()
    pop = HierarchicalPolicy.stack(pols)
    one = pop.member(2)
    assert one.population is None and pop.population == S
    assert all(
        torch.equal(a, b)
        for a, b in zip(one.state_dict().values(), pols[2].state_dict().values(), strict=True)
    )
    one.sub_policies[0].bias.data += 1.0
    assert not torch.equal(pop.sub_policies[0].bias[2], one.sub_policies[0].bias)
    with pytest.raises(ValueError, match=r"member s must be in \[0, 3\), got 3"):
        pop.member(3)
    with pytest.raises(ValueError, match="this module holds one policy"):
        pols[0].sub_policies[0].member(0)


def test_bad_population_inputs_name_the_value():
    pols = members()
    pop = HierarchicalPolicy.stack(pols)
    ctx, theta, w = data()
    with pytest.raises(
        ValueError, match=r"context must have shape \(population, N, C\) = \(3, N, 2\)"
    ):
        pop.sample(ctx[:2], gens())
    with pytest.raises(ValueError, match="needs one generator per member, got 2"):
        pop.sample(ctx, gens()[:2])
    with pytest.raises(ValueError, match=r"theta must have shape \(3, 40, 3\)"):
        pop.fit_parameters(ctx, theta[:, :, :2], w)
    w[1] = 0.0
    with pytest.raises(ValueError, match=r"weights\[1\] are all zero"):
        pop.fit_parameters(ctx, theta, w)
    with pytest.raises(ValueError, match="is on device meta"):
        pop.log_prob(ctx.to("meta"), theta)
    with pytest.raises(ValueError, match=r"members\[1\] has 2 options but members\[0\] 4"):
        HierarchicalPolicy.stack([pols[0], members(O=2)[1]])
    other = HierarchicalPolicy.create(
        O, C, D, gating_features=QuadraticFeatures(C, scale=torch.tensor([2.0, 1.0]))
    )
    with pytest.raises(ValueError, match="gating_features differ"):
        HierarchicalPolicy.stack([pols[0], other])
    with pytest.raises(ValueError, match="a population already"):
        HierarchicalPolicy.stack([pop])
    with pytest.raises(TypeError, match="members must be a sequence"):
        LinearGaussian.stack(pols[0].sub_policies[0])
    with pytest.raises(ValueError, match=r"members\[1\] is on device \['meta'\]"):
        HierarchicalPolicy.stack([pols[0], members()[1].to("meta")])
    with pytest.raises(ValueError, match=r"members\[1\].action_dim = 2"):
        LinearGaussian.stack([LinearGaussian(1, 3), LinearGaussian(1, 2)])


def test_a_policy_of_stacked_options_under_an_ordinary_gating_is_refused():
    stacked = [LinearGaussian.stack([LinearGaussian(C, D), LinearGaussian(C, D)]) for _ in range(O)]
    with pytest.raises(ValueError, match=r"options\[0\] holds a population of 2 but the gat"):
        HierarchicalPolicy(SoftmaxGating(C, O), stacked)
    gating = SoftmaxGating.stack([SoftmaxGating(C, O), SoftmaxGating(C, O)])
    with pytest.raises(ValueError, match=r"options\[0\] holds one policy but the gating a popul"):
        HierarchicalPolicy(gating, [LinearGaussian(C, D) for _ in range(O)])
    assert HierarchicalPolicy(gating, stacked).population == 2


def test_a_policy_made_in_inference_mode_prunes_outside_it():
    with torch.inference_mode():  # buffers made here cannot be written in place outside it
        pol = HierarchicalPolicy.create(O, C, D)
        pop = HierarchicalPolicy.stack(members())
    assert pol.prune(torch.zeros(5, C)) == []
    assert bool(pol.active.all())
    with torch.inference_mode():
        pol.gating.bias.copy_(torch.tensor([5.0, 0.0, -20.0, -20.0]))
        pop.gating.bias.copy_(torch.tensor([[5.0, 0.0, -20.0, -20.0]] * S))
    assert pol.prune(torch.zeros(5, C)) == [2, 3]
    assert pol.active.tolist() == [True, True, False, False]
    assert pop.prune(torch.zeros(S, 5, C), members=torch.tensor([False, True, False]))[1] == [2, 3]
    assert pop.active.tolist() == [[True] * O, [True, True, False, False], [True] * O]


@pytest.mark.parametrize(
    "mask",
    [torch.tensor([True]), torch.ones(S), torch.ones(S, dtype=torch.bool, device="meta"), [True]],
)
def test_prune_names_a_bad_members_mask_and_prunes_nothing(mask):
    pols = members()
    pop = HierarchicalPolicy.stack(pols)
    before = pop.active.clone()
    with pytest.raises(ValueError, match=rf"must be None or a bool tensor of shape \({S},\)"):
        pop.prune(data()[0], 0.5, members=mask)
    assert torch.equal(pop.active, before)
    with pytest.raises(ValueError, match=r"must be None or a bool tensor of shape \(\) \(\[S\]"):
        pols[0].prune(data()[0][0], 0.5, members=torch.tensor([True]))


def test_matmul_each_rounds_each_member_as_its_own_run():
    """Member s of :func:`matmul_each` is its own run's product (a population of one, on
    tensors of its own) bit for bit, also for sample counts that misalign the members in
    memory; a shared right factor and a 2-D product are plain products."""
    g = torch.Generator().manual_seed(0)
    for n in (1600, 1601):
        X = torch.randn(3, n, 3, generator=g, dtype=torch.float64)
        w = torch.rand(3, n, generator=g, dtype=torch.float64)
        y = torch.randn(3, n, 1, generator=g, dtype=torch.float64)
        wx, wy = w[..., None] * X, w[..., None] * y
        for a, b in [(X.mT, wx), (X.mT, wy), (wy.mT, y)]:
            out = matmul_each(a, b)
            for s in range(3):
                assert torch.equal(out[s : s + 1], a[s : s + 1].clone() @ b[s : s + 1].clone())
        c = torch.randn(3, 26, generator=g, dtype=torch.float64)
        out = matmul_each(X, c)
        for s in range(3):
            assert torch.equal(out[s : s + 1], X[s : s + 1].clone() @ c)
    assert torch.equal(matmul_each(X[0].mT, wx[0]), X[0].mT @ wx[0])


@pytest.mark.parametrize("quadratic, dim", [(False, D), (True, 1)])
def test_population_refit_equals_each_member_as_a_population_of_one_bit_for_bit(quadratic, dim):
    """With many samples (where MKL's batched products round by the batch size and the
    member's place), member s of a population refits and scores as ``stack([policy_s])``
    does, bit for bit; also with five policy features and one action dimension (one output
    column). A member of a population run is its ordinary run."""
    pols = [
        HierarchicalPolicy.create(
            O,
            C,
            dim,
            gating_features=QuadraticFeatures(C),
            policy_features=QuadraticFeatures(C) if quadratic else None,
            generator=torch.Generator().manual_seed(s),
        )
        for s in range(S)
    ]
    pop = HierarchicalPolicy.stack(pols)
    g = torch.Generator().manual_seed(1)
    n = 1601
    ctx = torch.randn(S, n, C, generator=g, dtype=torch.float64)
    theta = torch.randn(S, n, dim, generator=g, dtype=torch.float64)
    w = torch.rand(S, n, O, generator=g, dtype=torch.float64)
    ones = [HierarchicalPolicy.stack([p]) for p in pols]
    new = pop.fit_parameters(ctx, theta, w)
    pop.weighted_fit(ctx, theta, w)
    scores, (means, _) = pop.log_joint(ctx, theta), pop.mean_action(ctx)
    for s, one in enumerate(ones):
        alone = one.fit_parameters(ctx[s : s + 1], theta[s : s + 1], w[s : s + 1])
        assert new.keys() == alone.keys()
        for key, value in alone.items():
            assert torch.equal(new[key][s : s + 1], value), (s, key)
        one.weighted_fit(ctx[s : s + 1], theta[s : s + 1], w[s : s + 1])
        assert torch.equal(scores[s : s + 1], one.log_joint(ctx[s : s + 1], theta[s : s + 1]))
        assert torch.equal(means[s : s + 1], one.mean_action(ctx[s : s + 1])[0])


def test_matmul_each_broadcasts_a_shared_or_single_member_factor():
    """A factor with one member (or none) serves every member, as torch's product does."""
    g = torch.Generator().manual_seed(2)
    a = torch.randn(3, 4, 5, generator=g, dtype=torch.float64)
    for b in (
        torch.randn(1, 5, 2, generator=g, dtype=torch.float64),
        torch.randn(5, 2, generator=g, dtype=torch.float64),
    ):
        torch.testing.assert_close(matmul_each(a, b), a @ b, rtol=1e-12, atol=1e-12)
        torch.testing.assert_close(matmul_each(b.mT, a.mT), b.mT @ a.mT, rtol=1e-12, atol=1e-12)


def test_reduce_each_sums_each_member_as_its_own_run_with_several_threads():
    """With two torch threads a sum of 40,000 numbers is split across them when it is the only
    output; :func:`reduce_each` sums each member as its own run (a population of one) does."""
    threads = torch.get_num_threads()
    torch.set_num_threads(2)
    try:
        g = torch.Generator().manual_seed(3)
        t = torch.rand(3, 8000, 5, generator=g, dtype=torch.float64)
        for op, dim in [("sum", -1), ("sum", (-2, -1)), ("mean", -2), ("sum", -2)]:
            out = reduce_each(t, op, dim)
            for s in range(3):
                own = getattr(t[s : s + 1].clone(), op)(dim)
                assert torch.equal(out[s : s + 1], own), (op, dim, s)
        flat = t.reshape(3, -1)
        kept = reduce_each(flat, "sum", -1, keepdim=True)
        assert kept.shape == (3, 1)
        for s in range(3):
            assert torch.equal(kept[s], flat[s : s + 1].clone().sum(-1, keepdim=True)[0])
    finally:
        torch.set_num_threads(threads)
