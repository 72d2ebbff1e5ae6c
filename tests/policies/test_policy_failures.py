"""Failed calls change nothing, checkpoints that do not fit are refused before anything is
copied, and bad constructor arguments are named (policies, gatings, options)."""

import math

import pytest
import torch

from hireps_torch.features import IdentityFeatures, QuadraticFeatures
from hireps_torch.policies import ConstantGating, HierarchicalPolicy, LinearGaussian, SoftmaxGating

f64 = torch.float64
NAN, INF = math.nan, math.inf


def snapshot(module):
    return {k: v.clone() for k, v in module.state_dict().items()}


def assert_unchanged(module, before):
    after = module.state_dict()
    assert after.keys() == before.keys()
    for key, value in before.items():
        assert torch.equal(after[key], value), key


def fitted_policy(O=3, S=1, D=2, seed=0):
    gen = torch.Generator().manual_seed(seed)
    pol = HierarchicalPolicy.create(
        O, S, D, init_std=1.0, spread=2.0, gating_features=QuadraticFeatures(S), generator=gen
    )
    s = torch.randn(40, S, generator=gen, dtype=f64)
    theta, _ = pol.sample(s, gen)
    pol.weighted_fit(s, theta, torch.rand(40, O, generator=gen, dtype=f64))
    return pol, s, theta


def expect_unchanged(module, call, error=ValueError, match=None):
    before = snapshot(module)
    with pytest.raises(error, match=match):
        call()
    assert_unchanged(module, before)


# ---- weighted_fit either completes or changes nothing -----------------------------------------
def test_linear_gaussian_bad_fits_change_nothing(gen):
    opt = LinearGaussian(2, 2, init_std=0.5)
    x = torch.randn(10, 2, generator=gen, dtype=f64)
    y = torch.randn(10, 2, generator=gen, dtype=f64)
    w = torch.rand(10, generator=gen, dtype=f64)
    opt.weighted_fit(x, y, w)
    huge = y.clone()
    huge[3] = 1e200
    for args, match in [
        ((x, y, -w), "non-negative"),
        ((x, y, w[:5]), r"weights must have shape \(10,\)"),
        ((x, y[:, :1], w), r"targets must have shape \(10, 2\)"),
        ((x.T, y, w), r"features must have shape \(N, 2\)"),
        ((x, y.masked_fill(y > 1, NAN), w), "targets contains"),
        ((x, huge, w), "overflows"),
        ((x, y, torch.zeros(10)), "not all zero"),
    ]:
        expect_unchanged(opt, lambda a=args: opt.weighted_fit(*a), match=match)
    expect_unchanged(opt, lambda: opt.weighted_fit(x, y, w, ridge=NAN), match="ridge")
    expect_unchanged(opt, lambda: opt.set_covariance(torch.eye(3)), match=r"\(2, 2\)")
    expect_unchanged(opt, lambda: opt.set_covariance(torch.eye(2) * INF), match="cov")


def test_gating_bad_fits_change_nothing(gen):
    x = torch.randn(30, 2, generator=gen, dtype=f64)
    t = torch.softmax(torch.randn(30, 3, generator=gen, dtype=f64), -1)
    w = torch.rand(30, generator=gen, dtype=f64)
    soft = SoftmaxGating(2, 3)
    soft.weighted_fit(x, t, w)
    const = ConstantGating.from_kmeans(x, 3)
    for gating in (soft, const):
        for args, match in [
            ((x, t, -w), "sample_weights"),
            ((x, t, 0 * w), "all zero"),
            ((x, t[:, :2], w), r"targets must have shape \(30, 3\)"),
            ((x, -t, w), "targets must be finite and non-negative"),
            ((x[:, :1], t, w), r"gating features must have shape \(N, 2\)"),
            ((x.masked_fill(x > 1, INF), t, w), "gating features contains"),
        ]:
            expect_unchanged(gating, lambda g=gating, a=args: g.weighted_fit(*a), match=match)
    huge = x * 1e200  # the logistic regression overflows
    expect_unchanged(soft, lambda: soft.weighted_fit(huge, t, w), match="rescale")


def test_hierarchical_fit_failing_late_changes_nothing(gen):
    pol, s, theta = fitted_policy()
    w = torch.rand(40, 3, generator=gen, dtype=f64)
    far = theta.clone()
    far[0] = 1e200  # only option 2 sees this sample: its covariance overflows
    w_far = w.clone()
    w_far[0, :2] = 0.0
    expect_unchanged(pol, lambda: pol.weighted_fit(s, far, w_far), match="option 2: .*overflows")
    for args, match in [
        ((s, theta, w[:, :2]), r"weights must have shape \(40, 3\)"),
        ((s, theta, -w), "non-negative"),
        ((s, theta, w * NAN), "finite"),
        ((s, theta[:, :1], w), r"theta must have shape \(40, 2\)"),
        ((s[:3], theta, w), r"theta must have shape \(3, 2\)"),
        ((s * NAN, theta, w), "context contains"),
        ((s, theta.masked_fill(theta > 0, INF), w), "theta contains"),
        ((torch.zeros(40, 2), theta, w), r"context must have shape \(N, C\) = \(N, 1\)"),
    ]:
        expect_unchanged(pol, lambda a=args: pol.weighted_fit(*a), match=match)


def test_an_option_failing_after_the_others_were_fitted_changes_nothing(gen, monkeypatch):
    pol, s, theta = fitted_policy()
    calls = []

    def fail(*args, **kwargs):
        calls.append(1)
        raise ValueError("the covariance overflows (injected)")

    monkeypatch.setattr(pol.sub_policies[2], "fit_checked", fail)
    w = torch.rand(40, 3, generator=gen, dtype=f64)
    expect_unchanged(pol, lambda: pol.weighted_fit(s, theta, w), match="option 2: .*injected")
    assert calls == [1]


def test_prune_with_bad_input_changes_nothing():
    pol, s, _ = fitted_policy()
    for threshold in (NAN, -0.1, 1.0, torch.tensor([0.1, 0.2])):
        expect_unchanged(pol, lambda t=threshold: pol.prune(s, t), match="threshold")
    expect_unchanged(pol, lambda: pol.prune(s[:0]), match="at least one context")
    expect_unchanged(pol, lambda: pol.prune(s * NAN), match="context contains")


# ---- load_state_dict ----------------------------------------------------------------------------
@pytest.mark.parametrize(
    "other, saved",
    [
        (dict(O=5), r"gating.weight: saved \(5, 2\), expected \(3, 2\)"),
        (dict(D=3), r"options.0.weight: saved \(3, 1\), expected \(2, 1\)"),
        (dict(S=2), r"gating.weight: saved \(3, 5\), expected \(3, 2\)"),
    ],
)
def test_a_checkpoint_of_another_shape_is_refused_naming_both_shapes(other, saved):
    pol, _, _ = fitted_policy()
    state = fitted_policy(**other)[0].state_dict()
    expect_unchanged(pol, lambda: pol.load_state_dict(state), match=saved)


def test_a_broken_checkpoint_is_refused_before_anything_is_copied():
    pol, _, _ = fitted_policy()
    good = fitted_policy(seed=1)[0].state_dict()

    def broken(change):
        state = {k: v.clone() for k, v in good.items()}
        change(state)
        return state

    for change, match in [
        (lambda st: st.pop("options.1.chol"), r"missing keys \['options.1.chol'\]"),
        (lambda st: st.update(extra=torch.zeros(1)), r"unexpected keys \['extra'\]"),
        (lambda st: st["options.2.bias"].fill_(NAN), "'options.2.bias' holds non-finite"),
        (lambda st: st["gating.active"].fill_(False), "every option pruned"),
        (lambda st: st.update({"gating.active": torch.ones(3)}), "must be bool"),
        (lambda st: st["options.0.chol"].mul_(-1), "positive diagonal"),
        (lambda st: st["options.0.chol"].fill_(1.0), "lower triangular"),
        (lambda st: st.update({"options.0.bias": [0.0, 0.0]}), "must be a tensor"),
    ]:
        # the good entries before the broken one must not be copied either
        expect_unchanged(pol, lambda c=change: pol.load_state_dict(broken(c)), Exception, match)
    expect_unchanged(pol, lambda: pol.load_state_dict([1, 2]), TypeError, "mapping")
    pol.load_state_dict(good)
    assert_unchanged(pol, good)


def test_a_single_option_and_a_partial_load():
    one = HierarchicalPolicy.create(1, 1, 2, init_std=0.5)
    other = HierarchicalPolicy.create(1, 1, 2, init_std=2.0)
    one.options[0].weight.data.fill_(0.25)
    sd = other.state_dict()
    sd.pop("options.0.weight")
    one.load_state_dict(sd, strict=False)  # what torch allows: the missing entry is kept
    assert torch.equal(one.options[0].chol, other.options[0].chol)
    assert bool((one.options[0].weight == 0.25).all())
    s = torch.zeros(4, 1)
    th, opt = one.sample(s)
    assert opt.tolist() == [0] * 4 and bool(one.responsibilities(s, th).eq(1).all())


# ---- construction and inputs ------------------------------------------------------------------
@pytest.mark.parametrize(
    "kwargs, error, match",
    [
        (dict(init_mean=torch.tensor([NAN, 0.0])), ValueError, "init_mean contains"),
        (dict(init_mean=torch.full((3, 2), INF)), ValueError, "init_mean contains"),
        (dict(init_std=INF), ValueError, "init_std must be finite"),
        (dict(init_std=torch.tensor([1.0, NAN])), ValueError, "init_std must be finite"),
        (dict(init_std=torch.ones(3)), ValueError, r"init_std must be a float or a \(2,\)"),
        (dict(spread=NAN), ValueError, "spread must be finite"),
        (dict(spread=-1.0), ValueError, "spread"),
        (dict(min_variance=NAN), ValueError, "min_variance"),
        (dict(min_variance=torch.tensor([1e-3, INF])), ValueError, "min_variance"),
        (dict(covariance_prior=NAN), ValueError, "covariance_prior"),
        (dict(covariance_prior=torch.ones(2)), ValueError, r"covariance_prior must be one"),
        (dict(n_options=0), ValueError, "n_options must be >= 1"),
        (dict(n_options=2.0), TypeError, "n_options must be an integer"),
        (dict(action_dim=True), TypeError, "action_dim must be an integer"),
        (dict(gating_features=QuadraticFeatures(2)), ValueError, "context_dim = 1"),
    ],
)
def test_create_names_bad_arguments(kwargs, error, match):
    args = dict(n_options=3, context_dim=1, action_dim=2) | kwargs
    gen = torch.Generator().manual_seed(0)
    with pytest.raises(error, match=match):
        HierarchicalPolicy.create(**args, generator=gen)
    assert torch.equal(gen.get_state(), torch.Generator().manual_seed(0).get_state())


def test_constructors_name_bad_arguments():
    with pytest.raises(ValueError, match="l2"):
        SoftmaxGating(2, 3, l2=NAN)
    with pytest.raises(TypeError, match="dtype"):
        SoftmaxGating(2, 3, dtype=torch.int64)
    with pytest.raises(ValueError, match="centroids contains"):
        ConstantGating(torch.tensor([[NAN, 0.0]]))
    with pytest.raises(ValueError, match="points contains"):
        ConstantGating.from_kmeans(torch.full((5, 2), INF), 2)
    with pytest.raises(TypeError, match="dtype"):
        LinearGaussian(0, 2, dtype=torch.int64)
    with pytest.raises(ValueError, match="init_mean contains"):
        LinearGaussian(0, 2, init_mean=torch.tensor([0.0, INF]))
    gating = SoftmaxGating(4, 2)
    opts = [LinearGaussian(1, 1), LinearGaussian(1, 1)]
    with pytest.raises(ValueError, match="contexts of dimension 4 but policy_features of .* 1"):
        HierarchicalPolicy(gating, opts)
    with pytest.raises(ValueError, match="gating_features give 1 features but the gating takes 4"):
        HierarchicalPolicy(gating, opts, gating_features=IdentityFeatures(1))
    with pytest.raises(
        ValueError, match=r"policy_features give 2 features but the options take \[1\]"
    ):
        HierarchicalPolicy(SoftmaxGating(2, 2), opts, policy_features=IdentityFeatures(2))


def test_bad_parameters_to_log_prob_and_responsibilities_are_named():
    pol, s, theta = fitted_policy()
    with pytest.raises(
        ValueError, match=r"theta contains 1 non-finite value\(s\) \(first at index"
    ):
        pol.log_prob(s[:2], torch.tensor([[0.0, 1.0], [NAN, 0.0]], dtype=f64))
    with pytest.raises(ValueError, match="theta contains"):
        pol.responsibilities(s[:1], torch.tensor([[INF, 0.0]], dtype=f64))
    with pytest.raises(ValueError, match=r"theta\[1\] has zero density under every active"):
        pol.responsibilities(s[:2], torch.tensor([[0.0, 0.0], [1e200, 0.0]], dtype=f64))
    with pytest.raises(ValueError, match=r"theta must have shape \(2, 2\)"):
        pol.log_prob(s[:2], theta[:3])
    # bool / integer tensors are numbers: used as float64
    ints, ctx = theta[:4].round().to(torch.int64), s[:4].round().to(torch.int64)
    assert torch.equal(pol.log_prob(ctx, ints), pol.log_prob(ctx.double(), ints.double()))
    flags = torch.tensor([[True], [False]])
    assert torch.equal(pol.mean_action(flags)[0], pol.mean_action(flags.double())[0])


def test_wrong_device_empty_batches_and_all_pruned():
    pol, s, theta = fitted_policy()
    with pytest.raises(ValueError, match="context is on device meta but the other inputs are on"):
        pol.sample(torch.zeros(3, 1, device="meta"))
    th, opt = pol.sample(s[:0])
    assert th.shape == (0, 2) and opt.shape == (0,)
    assert pol.mean_action(s[:0])[0].shape == (0, 2)
    with pytest.raises(ValueError, match="not all zero"):
        pol.weighted_fit(s[:0], theta[:0], torch.zeros(0, 3))
    pol.gating.active.fill_(False)  # by hand: load_state_dict refuses such a state
    with pytest.raises(ValueError, match="every option of this policy is pruned"):
        pol.sample(s)
