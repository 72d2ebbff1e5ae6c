"""Feature maps: shapes, the Fourier basis and its periodic variant."""

import math

import pytest
import torch

from hireps_torch.features import ConcatFeatures, FourierFeatures, QuadraticFeatures


def test_fourier_basis_matches_its_formula():
    f = FourierFeatures([-1.0, 0.0], [1.0, 10.0], n_bases=3)
    assert f.out_features == 8
    x = torch.tensor([[0.2, 7.0]], dtype=torch.float64)
    u = torch.tensor([0.6, 0.7], dtype=torch.float64)
    expected = [
        math.cos(math.pi * (c0 * u[0] + c1 * u[1]))
        for c0 in range(3)
        for c1 in range(3)
        if (c0, c1) != (0, 0)
    ]
    assert f(x)[0].tolist() == pytest.approx(expected)


def test_periodic_fourier_features_are_continuous_across_the_wrap():
    f = FourierFeatures([-math.pi, -20.0], [math.pi, 20.0], n_bases=5, periodic=[True, False])
    assert f.out_features == 48
    a = torch.tensor([[math.pi - 1e-9, 3.0]], dtype=torch.float64)
    b = torch.tensor([[-math.pi, 3.0]], dtype=torch.float64)
    assert torch.allclose(f(a), f(b), atol=1e-7)
    plain = FourierFeatures([-math.pi, -20.0], [math.pi, 20.0], n_bases=5)
    assert float((plain(a) - plain(b)).abs().max()) > 1.0  # the plain basis jumps there


def test_fourier_coupling_keeps_the_terms_with_few_coupled_dimensions():
    full = FourierFeatures([0.0] * 3, [1.0] * 3, n_bases=5)
    one = FourierFeatures([0.0] * 3, [1.0] * 3, n_bases=5, coupling=1)
    two = FourierFeatures([0.0] * 3, [1.0] * 3, n_bases=5, coupling=2)
    assert (full.out_features, one.out_features, two.out_features) == (124, 12, 60)
    x = torch.rand(7, 3, generator=torch.Generator().manual_seed(0), dtype=torch.float64)
    # every kept term is a column of the full basis
    fx = full(x)
    for sub in (one, two):
        sx = sub(x)
        for j in range(sub.out_features):
            assert float((fx - sx[:, j : j + 1]).abs().amax(0).min()) < 1e-12
    with pytest.raises(ValueError, match="coupling"):
        FourierFeatures([0.0] * 3, [1.0] * 3, coupling=4)


def test_feature_maps_reject_bad_arguments():
    with pytest.raises(ValueError, match="high > low"):
        FourierFeatures([0.0], [0.0])
    with pytest.raises(ValueError, match="n_bases"):
        FourierFeatures([0.0], [1.0], n_bases=1)
    with pytest.raises(ValueError, match=r"takes states of shape \(\.\.\., 1\), got \(3, 2\)"):
        FourierFeatures([0.0], [1.0])(torch.zeros(3, 2))


@pytest.mark.parametrize(
    "low, high",
    [([-1e308, -1e308], [1e308, 1e308]), ([0.0, 0.0], [5e-324, 5e-324])],
    ids=["width past float64", "subnormal width"],
)
def test_a_fourier_box_whose_width_is_not_a_normal_number_is_refused(low, high):
    """Its features were all 1 (an infinite width) or all NaN (a subnormal one)."""
    with pytest.raises(ValueError, match="high - low finite and at least 2.23e-308"):
        FourierFeatures(low, high, n_bases=3)


def test_quadratic_features_match_their_formula():
    # [z, z_i z_j for i <= j] with z = x / scale, batch dimensions kept
    quad = QuadraticFeatures(2, scale=torch.tensor([2.0, 1.0]))
    assert (quad.in_features, quad.out_features) == (2, 5)
    x = torch.tensor([[2.0, -3.0], [0.0, 0.5]], dtype=torch.float64)
    expected = [[1.0, -3.0, 1.0, -3.0, 9.0], [0.0, 0.5, 0.0, 0.0, 0.25]]
    assert quad(x).tolist() == expected
    assert quad(x.expand(4, 2, 2)).shape == (4, 2, 5)
    assert QuadraticFeatures(3).out_features == 3 + 6


def test_concat_features_stack_the_maps_in_order():
    four = FourierFeatures([-math.pi, -10.0], [math.pi, 10.0], n_bases=5, periodic=[True, False])
    quad = QuadraticFeatures(2, scale=torch.tensor([math.pi, 10.0]))
    both = ConcatFeatures(four, quad)
    assert both.in_features == 2 and both.out_features == 48 + 5
    x = torch.randn(6, 2, generator=torch.Generator().manual_seed(0), dtype=torch.float64)
    out = both(x)
    assert torch.equal(out[:, :48], four(x)) and torch.equal(out[:, 48:], quad(x))
    with pytest.raises(ValueError, match="in_features"):
        ConcatFeatures(four, QuadraticFeatures(3))
    with pytest.raises(ValueError, match="at least one"):
        ConcatFeatures()


def test_feature_maps_check_widths_dtypes_and_arguments():
    from hireps_torch.features import IdentityFeatures

    quad, four = QuadraticFeatures(2), FourierFeatures([0.0, 0.0], [1.0, 2.0], n_bases=3)
    for fmap in (quad, four, IdentityFeatures(2), ConcatFeatures(quad, four)):
        name = type(fmap).__name__
        with pytest.raises(
            ValueError, match=rf"{name} takes states of shape \(\.\.\., 2\), got \(3, 3\)"
        ):
            fmap(torch.zeros(3, 3))
        ints = torch.ones(4, 2, dtype=torch.long)  # integer states are used as float64
        assert torch.equal(fmap(ints), fmap(ints.double()))
        assert fmap(ints).dtype == torch.float64
    with pytest.raises(ValueError, match="scale must be positive"):
        QuadraticFeatures(2, scale=torch.tensor([math.nan, 1.0]))
    for big_or_tiny in (1e200, 1e-200):  # named as given (they were named inf / 0 in float32)
        with pytest.raises(ValueError, match=r"in float32's range, got .*e[+-]200"):
            QuadraticFeatures(2, scale=[big_or_tiny, 1.0])
    big = 2**54 + 2**30 + 1  # kept as float32 rounded once (not via float64)
    assert QuadraticFeatures(2, scale=[big, 1]).scale[0] == torch.tensor(big).to(torch.float32)
    with pytest.raises(ValueError, match="finite high > low"):
        FourierFeatures([0.0], [math.inf])
    with pytest.raises(TypeError, match="coupling must be an integer"):
        FourierFeatures([0.0, 0.0], [1.0, 1.0], coupling=1.5)
    with pytest.raises(TypeError, match="in_features must be an integer"):
        QuadraticFeatures(2.0)
    with pytest.raises(ValueError, match=r"in_features = 100000 gives 5e\+09 quadratic features"):
        QuadraticFeatures(10**5)  # before: an 80 GB allocation failing deep in torch


def test_states_on_another_device_than_the_map_are_named():
    quad, four = QuadraticFeatures(2), FourierFeatures([0.0, 0.0], [1.0, 2.0], n_bases=3)
    for fmap in (quad, four, ConcatFeatures(quad, four)):
        with pytest.raises(ValueError, match="Features are on meta but the map on cpu"):
            fmap(torch.ones(5, 2, device="meta"))


def test_fourier_bases_per_dimension_leave_out_a_dimension_with_one_basis():
    """(4, 4, 1) over 3-D states is the 4-basis map of the first two dimensions: the third
    changes nothing, and the term count is 4 * 4 * 1 - 1."""
    g = torch.Generator().manual_seed(0)
    x = torch.randn(20, 3, generator=g, dtype=torch.float64)
    three = FourierFeatures([-2.0] * 3, [2.0] * 3, n_bases=(4, 4, 1))
    two = FourierFeatures([-2.0] * 2, [2.0] * 2, n_bases=4)
    assert three.in_features == 3 and three.out_features == 15
    torch.testing.assert_close(three(x), two(x[:, :2]), rtol=0, atol=0)
    moved = x.clone()
    moved[:, 2] += 1.0
    torch.testing.assert_close(three(moved), three(x), rtol=0, atol=0)
    mixed = FourierFeatures([0.0] * 2, [1.0] * 2, n_bases=(3, 2))
    assert mixed.out_features == 3 * 2 - 1
    assert {tuple(c) for c in mixed.coefficients.tolist()} == {
        (0.0, 1.0),
        (1.0, 0.0),
        (1.0, 1.0),
        (2.0, 0.0),
        (2.0, 1.0),
    }


@pytest.mark.parametrize(
    "bases, error, match",
    [
        ((1, 1, 1), ValueError, r"at least one entry of n_bases must be >= 2, got \(1, 1, 1\)"),
        ((4, 4), ValueError, r"n_bases must have 3 entries .*got \(4, 4\)"),
        ((4, 0, 1), ValueError, r"n_bases\[1\] must be >= 1, got 0"),
        ((4, 2.0, 1), TypeError, r"n_bases\[1\] must be an integer, got float 2.0"),
        ("44", TypeError, r"n_bases must be an integer >= 2 or 3 integers >= 1, got str '44'"),
        (1, ValueError, r"n_bases must be >= 2, got 1"),
    ],
)
def test_bad_bases_per_dimension_are_named(bases, error, match):
    with pytest.raises(error, match=match):
        FourierFeatures([0.0] * 3, [1.0] * 3, n_bases=bases)
