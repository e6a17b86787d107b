"""PhysicsPosterior against torch.distributions, sampling statistics, normalisation."""

from __future__ import annotations

import math

import pytest
import torch
from torch.distributions import Categorical, Normal

from physgm.model import PhysicsPosterior, PhysicsSample
from physgm.model.posterior import (
    LOG10_E_RANGE,
    NU_MAX,
    NU_RANGE,
    denormalise_log10_E,
    denormalise_nu,
    normalise_log10_E,
    normalise_nu,
)


def make_posterior(b: int = 3, m: int = 15, seed: int = 0) -> PhysicsPosterior:
    gen = torch.Generator().manual_seed(seed)
    return PhysicsPosterior(
        material_logits=torch.randn(b, m, generator=gen, dtype=torch.float64) * 2,
        z_E_mean=torch.rand(b, generator=gen, dtype=torch.float64) * 1.6 - 0.8,
        z_E_logvar=torch.rand(b, generator=gen, dtype=torch.float64) * 4 - 5,
        z_nu_mean=torch.rand(b, generator=gen, dtype=torch.float64) * 1.6 - 0.8,
        z_nu_logvar=torch.rand(b, generator=gen, dtype=torch.float64) * 4 - 5,
    )


def test_normalisation_maps_ranges_to_unit_interval():
    ends = torch.tensor(LOG10_E_RANGE, dtype=torch.float64)
    torch.testing.assert_close(normalise_log10_E(ends), torch.tensor([-1.0, 1.0], dtype=torch.float64))
    torch.testing.assert_close(normalise_nu(torch.tensor(NU_RANGE)), torch.tensor([-1.0, 1.0]))
    x = torch.linspace(-2, 2, 9, dtype=torch.float64)
    torch.testing.assert_close(normalise_log10_E(denormalise_log10_E(x)), x)
    torch.testing.assert_close(normalise_nu(denormalise_nu(x)), x)
    # log10 E = 7.35 (22 MPa) is the middle of [3, 11.7].
    assert normalise_log10_E(torch.tensor(7.35)).abs() < 1e-6


def test_log_prob_matches_torch_distributions():
    post = make_posterior()
    sample = PhysicsSample(
        material=torch.tensor([[0, 3, 14, 7], [1, 1, 2, 9], [13, 0, 5, 5]]),
        log10_E=torch.tensor(
            [[3.5, 6.0, 9.0, 11.0], [4.0, 7.0, 7.5, 10.0], [5.0, 5.5, 8.0, 12.5]], dtype=torch.float64
        ),
        nu=torch.tensor(
            [[0.1, 0.2, 0.3, 0.45], [0.0, 0.25, 0.33, 0.4], [0.49, 0.05, 0.15, 0.6]], dtype=torch.float64
        ),
    )
    cat = Categorical(logits=post.material_logits[:, None, :])
    e_dist = Normal(post.z_E_mean[:, None], torch.exp(0.5 * post.z_E_logvar)[:, None])
    nu_dist = Normal(post.z_nu_mean[:, None], torch.exp(0.5 * post.z_nu_logvar)[:, None])
    z_E = 2 * (sample.log10_E - 3.0) / 8.7 - 1  # written out by hand on purpose
    z_nu = 2 * sample.nu / 0.5 - 1
    expected = cat.log_prob(sample.material) + e_dist.log_prob(z_E) + nu_dist.log_prob(z_nu)
    torch.testing.assert_close(post.log_prob(sample), expected)
    terms = post.log_prob_terms(sample)
    torch.testing.assert_close(terms[0], cat.log_prob(sample.material))
    torch.testing.assert_close(terms[1], e_dist.log_prob(z_E))
    torch.testing.assert_close(terms[2], nu_dist.log_prob(z_nu))
    assert post.log_prob(sample).shape == (3, 4)


def test_entropy_matches_torch_distributions():
    post = make_posterior()
    expected = (
        Categorical(logits=post.material_logits).entropy()
        + Normal(post.z_E_mean, torch.exp(0.5 * post.z_E_logvar)).entropy()
        + Normal(post.z_nu_mean, torch.exp(0.5 * post.z_nu_logvar)).entropy()
    )
    torch.testing.assert_close(post.entropy(), expected)


def test_log_prob_is_differentiable_for_dpo():
    post = make_posterior()
    leaves = [post.material_logits, post.z_E_mean, post.z_E_logvar, post.z_nu_mean, post.z_nu_logvar]
    for t in leaves:
        t.requires_grad_(True)
    sample = post.sample(5, torch.Generator().manual_seed(0))
    assert not sample.log10_E.requires_grad  # samples are data, not part of the graph
    post.log_prob(sample).sum().backward()
    assert all(t.grad is not None and t.grad.abs().sum() > 0 for t in leaves)


def test_sample_statistics_match_mean_and_variance():
    post = make_posterior(b=2, seed=4)
    k = 40000
    s = post.sample(k, torch.Generator().manual_seed(1))
    assert s.material.shape == (2, k) and s.material.dtype == torch.int64
    probs = post.material_probs
    freq = torch.stack([torch.bincount(s.material[i], minlength=15) for i in range(2)]).double() / k
    # 5 binomial standard errors (plus a floor for tiny probabilities).
    assert ((freq - probs).abs() <= 5 * (probs * (1 - probs) / k).sqrt() + 1e-3).all()
    std_E = post.log10_E_std
    torch.testing.assert_close(
        s.log10_E.mean(1), post.log10_E_mean, atol=float(5 * std_E.max() / math.sqrt(k)), rtol=0
    )
    torch.testing.assert_close(s.log10_E.std(1), std_E, rtol=0.03, atol=0)
    std_nu = post.nu_std
    torch.testing.assert_close(
        s.nu.mean(1), post.nu_mean, atol=float(5 * std_nu.max() / math.sqrt(k)), rtol=0
    )
    torch.testing.assert_close(s.nu.std(1), std_nu, rtol=0.03, atol=0)
    # Half-range of log10 E is 4.35 decades: std = exp(logvar / 2) * 4.35.
    torch.testing.assert_close(std_E, torch.exp(0.5 * post.z_E_logvar) * 4.35)


def test_sampling_is_reproducible_with_a_generator():
    post = make_posterior()
    a = post.sample(8, torch.Generator().manual_seed(7))
    b = post.sample(8, torch.Generator().manual_seed(7))
    c = post.sample(8, torch.Generator().manual_seed(8))
    assert (
        torch.equal(a.material, b.material) and torch.equal(a.log10_E, b.log10_E) and torch.equal(a.nu, b.nu)
    )
    assert not torch.equal(a.log10_E, c.log10_E)


def test_mean_and_physical_conversions():
    post = make_posterior()
    m = post.mean()
    assert m.material.shape == (3, 1)
    assert torch.equal(m.material[:, 0], post.material_logits.argmax(-1))
    torch.testing.assert_close(m.log10_E[:, 0], 3.0 + (post.z_E_mean + 1) * 4.35)
    torch.testing.assert_close(m.nu[:, 0], (post.z_nu_mean + 1) * 0.25)
    s = PhysicsSample(
        material=torch.zeros(1, 4, dtype=torch.long),
        log10_E=torch.tensor([[2.0, 6.0, 9.5, 13.0]]),
        nu=torch.tensor([[-0.1, 0.3, 0.499, 0.7]]),
    )
    torch.testing.assert_close(
        s.youngs_modulus(), torch.tensor([[1e3, 1e6, 10**9.5, 10**11.7]]), rtol=1e-5, atol=0
    )
    torch.testing.assert_close(s.poisson_ratio(), torch.tensor([[0.0, 0.3, NU_MAX, NU_MAX]]))
    assert (s.poisson_ratio() < 0.5).all()


@pytest.mark.parametrize("raw", [-50.0, 0.0, 50.0])
def test_head_logvar_stays_in_configured_bounds(raw):
    from physgm.model.config import PhysicsHeadConfig
    from physgm.model.physics_head import PhysicsHead

    head = PhysicsHead(PhysicsHeadConfig(logvar_min=-9.0, logvar_max=2.0), dim=8, num_global_tokens=3)
    lv = head._logvar(torch.tensor([raw]))
    assert -9.0 <= float(lv) <= 2.0
    post = head(torch.randn(4, 3, 8))
    assert post.material_logits.shape == (4, 15) and post.z_E_mean.shape == (4,)


def test_material_frame_reads_E_within_each_materials_range():
    """E_ranges: z_E = -1, 1 are the ends of the candidate's own material's range (hand-computed)."""
    ranges = torch.tensor([[3.0, 5.0], [10.0, 11.0]], dtype=torch.float64)
    post = PhysicsPosterior(
        material_logits=torch.tensor([[0.0, 2.0], [30.0, 0.0]], dtype=torch.float64),
        z_E_mean=torch.tensor([0.0, 0.5], dtype=torch.float64),
        z_E_logvar=torch.tensor([math.log(0.25), math.log(0.04)], dtype=torch.float64),
        z_nu_mean=torch.zeros(2, dtype=torch.float64),
        z_nu_logvar=torch.zeros(2, dtype=torch.float64),
        E_ranges=ranges,
    )
    # Mean and spread are the most likely material's: 10.5 +- 0.5 * 0.5; 4.5 +- 0.2 * 1.
    assert post.log10_E_mean.tolist() == pytest.approx([10.5, 4.5])
    assert post.log10_E_std.tolist() == pytest.approx([0.25, 0.2])
    assert post.mean().material[:, 0].tolist() == [1, 0]
    # A candidate is normalised with its own material: log10 E = 4.5 under material 0 is z = 0.5.
    cand = PhysicsSample(
        torch.tensor([[0, 1]]), torch.tensor([[4.5, 10.25]], dtype=torch.float64), torch.zeros(1, 2)
    )
    _, log_E, _ = post[:1].log_prob_terms(cand)
    expected = [Normal(0.0, 0.5).log_prob(torch.tensor(z)).item() for z in (0.5, -0.5)]
    assert log_E[0].tolist() == pytest.approx(expected)
    # Samples of the sure second scene (material 0) land in [3, 5] around 4.5 with std 0.2.
    draws = post[1:].sample(4000, torch.Generator().manual_seed(0))
    assert bool((draws.material == 0).all())
    assert draws.log10_E.mean().item() == pytest.approx(4.5, abs=0.02)
    assert draws.log10_E.std().item() == pytest.approx(0.2, rel=0.05)
    # Indexing and moving keep the table whole; the global frame is unchanged without it.
    assert post[1:].E_ranges is ranges and torch.equal(post.cpu_float().E_ranges, ranges.float())
    glob = PhysicsPosterior(*(getattr(post, k) for k in PhysicsPosterior.BATCHED))
    assert glob.log10_E_mean.tolist() == pytest.approx(denormalise_log10_E(post.z_E_mean).tolist())


def test_wide_proposal_floor_is_in_decades_of_the_material_frame():
    from physgm.train.proposal import widen

    post = PhysicsPosterior(
        torch.tensor([[0.0, 5.0]]),
        torch.zeros(1),
        torch.tensor([-20.0]),
        torch.zeros(1),
        torch.zeros(1),
        E_ranges=torch.tensor([[3.0, 5.0], [10.0, 11.0]]),
    )
    # Material 1 spans 1 decade: 0.5 decades a unit of z, so a 0.3-decade floor is a z std of 0.6.
    assert widen(post, 0.3, 0.03).log10_E_std.item() == pytest.approx(0.3, rel=1e-5)
    assert math.exp(0.5 * widen(post, 0.3, 0.03).z_E_logvar.item()) == pytest.approx(0.6, rel=1e-5)


@pytest.mark.parametrize("frame", ["global", "material"])
def test_E_log_density_is_the_derivative_of_the_cdf(frame):
    """Per decade, in both frames: the mixture's density is d/dx of its CDF (central differences)."""
    post = make_posterior(b=4, m=2, seed=3)
    if frame == "material":
        post.E_ranges = torch.tensor([[3.0, 5.0], [6.0, 10.0]], dtype=torch.float64)
    x = torch.tensor([4.0, 6.5, 8.1, 9.7], dtype=torch.float64)
    h = 1e-5
    numeric = (post.log10_E_cdf(x + h) - post.log10_E_cdf(x - h)) / (2 * h)
    torch.testing.assert_close(post.log10_E_log_density(x).exp(), numeric, rtol=1e-6, atol=1e-9)


def test_cat_joins_batches_and_keeps_the_table():
    a, b = make_posterior(b=2, seed=1), make_posterior(b=3, seed=2)
    joined = PhysicsPosterior.cat([a, b])
    assert joined.material_logits.shape == (5, 15) and joined.E_ranges is None
    torch.testing.assert_close(joined[2:].z_E_mean, b.z_E_mean)
    with pytest.raises(ValueError, match="at least one"):
        PhysicsPosterior.cat([])
