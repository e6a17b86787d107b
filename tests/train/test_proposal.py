"""DPO candidate proposals: on-policy draws, the wide stratified proposal, and their log-probabilities."""

from __future__ import annotations

import math
from types import SimpleNamespace

import pytest
import torch

from physgm.model.posterior import PhysicsPosterior
from physgm.physics.materials import MATERIAL_NAMES, log10_E_range
from physgm.train.dpo import DPOLossConfig, LitDPO, dpo_loss
from physgm.train.pairs import Candidate, SceneInputs, collate_pairs
from physgm.train.proposal import ProposalSettings, propose

JELLY = MATERIAL_NAMES.index("jelly")


def posterior(mean_log10_E: float = 9.0, std_decades: float = 0.2) -> PhysicsPosterior:
    """A [1] posterior sure of jelly, with log10 E ~ N(mean, std) and nu ~ N(0.3, 0.05)."""
    logits = torch.full((1, len(MATERIAL_NAMES)), -20.0)
    logits[0, JELLY] = 20.0
    z_per_decade = 2.0 / 8.7
    z_E = 2.0 * (mean_log10_E - 3.0) / 8.7 - 1.0
    return PhysicsPosterior(
        logits,
        torch.tensor([z_E]),
        torch.tensor([2.0 * math.log(std_decades * z_per_decade)]),
        torch.tensor([2.0 * 0.3 / 0.5 - 1.0]),
        torch.tensor([2.0 * math.log(0.05 * 4.0)]),
    )


def test_wide_candidates_are_stratified_over_the_material_range_and_policy_ones_are_not():
    cfg = ProposalSettings(material="sample", min_std_decades=0.1, wide_fraction=0.75)
    draws = propose("wide", posterior(9.0), 4, cfg, torch.Generator().manual_seed(0))
    lo, hi = log10_E_range(JELLY)
    assert (lo, hi) == pytest.approx((3.0, 5.0))  # jelly: 1e3 .. 1e5 Pa in the material table
    assert draws.sources == ["wide", "wide", "wide", "policy"]
    assert (draws.sample.material == JELLY).all()
    log_E = draws.sample.log10_E[0].tolist()
    for j, v in enumerate(log_E[:3]):  # stratum j of 3 over [3, 5]
        assert lo + j * (hi - lo) / 3 <= v <= lo + (j + 1) * (hi - lo) / 3
    assert abs(log_E[3] - 9.0) < 1.0  # the policy's own draw stays near its mean, 4+ decades away
    # Deterministic per generator seed (the pair cache relies on it).
    again = propose("wide", posterior(9.0), 4, cfg, torch.Generator().manual_seed(0))
    assert torch.equal(again.sample.log10_E, draws.sample.log10_E)
    on_policy = propose("policy", posterior(9.0), 4, cfg, torch.Generator().manual_seed(0))
    assert on_policy.sources == ["policy"] * 4 and (on_policy.sample.log10_E - 9.0).abs().max() < 1.0
    with pytest.raises(ValueError, match="unknown rollout proposal"):
        propose("uniform", posterior(), 4, cfg, torch.Generator())


def test_wide_candidates_carry_the_policy_and_reference_log_probabilities_computed_by_hand():
    """Two wide candidates as a (chosen, rejected) pair: DPO's four log-probabilities, by hand."""
    cfg = ProposalSettings(material="mode", wide_fraction=1.0)
    draws = propose("wide", posterior(9.0, 0.2), 2, cfg, torch.Generator().manual_seed(3))
    assert draws.sources == ["wide", "wide"]

    def by_hand(log10_E: float, nu: float, mean_log10_E: float, std_decades: float) -> float:
        # log p(jelly) + log N(z_E; mu, s) + log N(z_nu; mu_nu, s_nu) on the normalised coordinates.
        log_p = torch.log_softmax(torch.tensor([20.0] + [-20.0] * (len(MATERIAL_NAMES) - 1)), 0)[0].item()
        z, mu, s = (2 * (log10_E - 3) / 8.7 - 1), (2 * (mean_log10_E - 3) / 8.7 - 1), std_decades * 2 / 8.7
        zn, mun, sn = (2 * nu / 0.5 - 1), (2 * 0.3 / 0.5 - 1), 0.05 * 4.0
        gauss = -0.5 * math.log(2 * math.pi * s * s) - 0.5 * ((z - mu) / s) ** 2
        gauss_nu = -0.5 * math.log(2 * math.pi * sn * sn) - 0.5 * ((zn - mun) / sn) ** 2
        return log_p + gauss + gauss_nu

    cands = [
        Candidate(
            JELLY, "jelly", float(draws.sample.log10_E[0, k]), float(draws.sample.nu[0, k]), 0.1 * (k + 1)
        )
        for k in range(2)
    ]
    inputs = SceneInputs(
        torch.zeros(1, 3, 8, 8), torch.ones(1, 1, 8, 8), torch.eye(4)[None], torch.eye(3)[None]
    )
    batch = collate_pairs([(inputs, cands[0], cands[1], "scene", True)])  # what the DPO stage trains on
    policy, reference = posterior(8.0, 0.5), posterior(9.0, 0.2)  # the policy has moved; the reference not
    module = SimpleNamespace(loss_cfg=DPOLossConfig())
    got = [
        LitDPO.log_prob(module, p, s, batch).item()
        for p in (policy, reference)
        for s in (batch.winner, batch.loser)
    ]
    want = [by_hand(c.log10_E, c.nu, mean, std) for mean, std in ((8.0, 0.5), (9.0, 0.2)) for c in cands]
    assert got == pytest.approx(want, rel=1e-5)
    # The wide candidates sit 4+ decades below the reference mean: very unlikely under it, as they should be.
    assert max(want[2:]) < -100
    terms = dpo_loss(*(torch.tensor([v]) for v in got), beta=0.5)
    margin = 0.5 * ((want[0] - want[2]) - (want[1] - want[3]))
    assert terms.loss.item() == pytest.approx(math.log1p(math.exp(-margin)), rel=1e-4)
