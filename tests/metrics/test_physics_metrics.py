import math

import pytest
import torch

from physgm.metrics.physics_metrics import PhysicsMetrics
from physgm.model.posterior import LOG10_E_RANGE, PhysicsPosterior, normalise_log10_E, normalise_nu


def posterior(logits, log10_E, E_std_decades, nu, nu_std) -> PhysicsPosterior:
    span_E, span_nu = (LOG10_E_RANGE[1] - LOG10_E_RANGE[0]) / 2, 0.25
    return PhysicsPosterior(
        material_logits=torch.as_tensor(logits, dtype=torch.float32),
        z_E_mean=normalise_log10_E(torch.as_tensor(log10_E)),
        z_E_logvar=torch.log((torch.as_tensor(E_std_decades) / span_E) ** 2),
        z_nu_mean=normalise_nu(torch.as_tensor(nu)),
        z_nu_logvar=torch.log((torch.as_tensor(nu_std) / span_nu) ** 2),
    )


def test_accuracy_errors_and_confusion_by_hand():
    m = PhysicsMetrics(num_materials=3)
    post = posterior(
        [[5.0, 0, 0], [0, 5.0, 0], [0, 0, 5.0], [5.0, 0, 0]],
        [5.0, 6.0, 7.0, 8.0],
        [1.0] * 4,
        [0.3] * 4,
        [0.05] * 4,
    )
    m.update(
        post,
        torch.tensor([0, 1, 1, 0]),
        torch.tensor([5.5, 6.0, 9.0, 8.2]),
        torch.tensor([0.3, 0.4, 0.3, 0.2]),
    )
    out = m.compute()
    assert out["material_acc"].item() == pytest.approx(0.75)
    assert out["abs_log10E_mean"].item() == pytest.approx((0.5 + 0 + 2 + 0.2) / 4, abs=1e-5)
    # 2.0 decades off with std 1: outside 1.645 std; the others are inside.
    assert out["coverage90_E"].item() == pytest.approx(0.75)
    assert out["coverage90_nu"].item() == pytest.approx(
        0.5
    )  # errors 0, 0.1, 0, 0.1 against a half-width of 0.082
    assert out["confusion"].tolist() == [[2, 0, 0], [0, 1, 1], [0, 0, 0]]
    assert "abs_log10E_simulated_median" not in out  # 3 classes: not the material table's


def test_coverage_of_calibrated_gaussian_is_ninety_percent():
    g = torch.Generator().manual_seed(0)
    n = 20000
    mean_E = torch.rand(n, generator=g) * 6 + 4
    true_E = mean_E + 0.7 * torch.randn(n, generator=g)
    post = posterior(
        torch.zeros(n, 2), mean_E, torch.full((n,), 0.7), torch.full((n,), 0.25), torch.full((n,), 0.05)
    )
    m = PhysicsMetrics(num_materials=2)
    m.update(post, torch.zeros(n, dtype=torch.long), true_E, 0.25 + 0.05 * torch.randn(n, generator=g))
    out = m.compute()
    assert out["coverage90_E"].item() == pytest.approx(0.9, abs=0.01)
    assert out["coverage90_nu"].item() == pytest.approx(0.9, abs=0.01)
    assert out["abs_log10E_median"].item() == pytest.approx(0.7 * 0.6745, rel=0.03)  # median of |N(0, s)|
    # NLL: categorical log 2 plus the Gaussian NLLs on the normalised scale.
    s_E, s_nu = 0.7 / ((LOG10_E_RANGE[1] - LOG10_E_RANGE[0]) / 2), 0.05 / 0.25
    expected = math.log(2) + sum(0.5 * math.log(2 * math.pi * s * s) + 0.5 for s in (s_E, s_nu))
    assert out["nll"].item() == pytest.approx(expected, abs=0.03)


def test_calibration_offset_widens_an_over_confident_posterior_to_ninety_percent():
    """Errors drawn with twice the predicted std: the offset is 2 log 2, and applied, it covers 90 %."""
    g = torch.Generator().manual_seed(1)
    n = 20000
    mean_E = torch.rand(n, generator=g) * 6 + 4
    true_E = mean_E + 1.0 * torch.randn(n, generator=g)  # true spread 1.0 decade
    true_nu = 0.25 + 0.025 * torch.randn(n, generator=g)  # nu: half the predicted 0.05, under-confident

    def scores(E_std):
        post = posterior(torch.zeros(n, 2), mean_E, E_std, torch.full((n,), 0.25), torch.full((n,), 0.05))
        m = PhysicsMetrics(num_materials=2)
        m.update(post, torch.zeros(n, dtype=torch.long), true_E, true_nu)
        return m.compute()

    out = scores(torch.full((n,), 0.5))  # predicted 0.5: over-confident by 2x
    assert out["coverage90_E"].item() == pytest.approx(0.59, abs=0.02)  # P(|N(0,1)| < 0.82)
    assert out["calibration_logvar_offset_E"].item() == pytest.approx(2 * math.log(2.0), abs=0.05)
    assert out["calibration_logvar_offset_nu"].item() == pytest.approx(2 * math.log(0.5), abs=0.05)
    widened = 0.5 * math.exp(out["calibration_logvar_offset_E"].item() / 2)
    assert scores(torch.full((n,), widened))["coverage90_E"].item() == pytest.approx(0.9, abs=0.005)


def test_simulated_E_is_the_mean_projected_onto_the_predicted_materials_range():
    """simulate.py runs the predicted material at the mean E clipped to that material's range."""
    from physgm.physics.materials import MATERIAL_NAMES, log10_E_range

    M = len(MATERIAL_NAMES)
    jelly, metal = MATERIAL_NAMES.index("jelly"), MATERIAL_NAMES.index("metal")
    lo_j, hi_j = log10_E_range("jelly")
    lo_m, _ = log10_E_range("metal")
    logits = torch.zeros(3, M)
    logits[0, jelly] = logits[1, jelly] = logits[2, metal] = 5.0
    # jelly predicted 2 decades above its range; jelly inside it; metal predicted below its range
    means = torch.tensor([hi_j + 2.0, lo_j + 0.5, lo_m - 1.0])
    truth = torch.tensor([hi_j - 0.3, lo_j + 0.2, lo_m - 1.0])
    m = PhysicsMetrics(num_materials=M)
    post = posterior(logits, means, [0.5] * 3, [0.3] * 3, [0.05] * 3)
    m.update(post, torch.tensor([jelly, jelly, 0]), truth, torch.full((3,), 0.3))
    out = m.compute()
    # raw errors 2.3, 0.3, 0; simulated errors 0.3, 0.3, 1.0 (the third is clipped up into metal's range)
    assert out["abs_log10E_mean"].item() == pytest.approx(2.6 / 3, abs=1e-4)
    assert out["abs_log10E_simulated_mean"].item() == pytest.approx(1.6 / 3, abs=1e-4)
    assert out["abs_log10E_simulated_median"].item() == pytest.approx(0.3, abs=1e-4)


def test_material_frame_coverage_is_the_mixtures_central_interval():
    """Half jelly (log10 E 3-5), half metal: the true E's CDF is a sum over the two materials."""
    from physgm.model.posterior import material_E_ranges
    from physgm.physics.materials import MATERIAL_NAMES

    jelly, metal = MATERIAL_NAMES.index("jelly"), MATERIAL_NAMES.index("metal")
    logits = torch.full((3, 15), -1e4)
    logits[:, [jelly, metal]] = 0.0
    post = PhysicsPosterior(
        logits,
        torch.zeros(3),
        torch.full((3,), math.log(0.01)),
        torch.zeros(3),
        torch.zeros(3),
        E_ranges=material_E_ranges(),
    )
    lo, hi = material_E_ranges()[[jelly, metal]].unbind(-1)
    truth = torch.tensor([(lo[0] + hi[0]) / 2, (lo[1] + hi[1]) / 2, 2.0])  # the centres, and below both
    # At jelly's centre: half of jelly's Gaussian and none of metal's; at metal's: all of jelly's and half.
    assert post.log10_E_cdf(truth).tolist() == pytest.approx([0.25, 0.75, 0.0], abs=1e-5)
    m = PhysicsMetrics(num_materials=15)
    m.update(post, torch.tensor([jelly, metal, jelly]), truth, torch.zeros(3))
    assert m.compute()["coverage90_E"].item() == pytest.approx(2 / 3)
