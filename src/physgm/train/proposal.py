"""Where DPO's physics candidates come from: the policy, or a proposal wider than the policy.

DPO's loss needs only the policy's and the reference's log-probabilities of the chosen and the
rejected physics, so the pairs may come from any proposal. Drawn from the policy alone they stay
within about a decade of its mean, and the stage-1 model starts 1-3 decades too stiff, where the
score has no slope towards the truth (``python -m physgm.bench dpo-landscape``). The ``wide``
proposal therefore draws part of each scene's K candidates stratified over log10 E across the
whole range the material table gives the candidate's material, and the rest from the policy.

Proposals are looked up by name in ``PROPOSALS`` (``stage.rollout.proposal``).
"""

from __future__ import annotations

import math
import zlib
from collections.abc import Callable
from dataclasses import dataclass, replace

import torch

from physgm.model.posterior import NU_RANGE, PhysicsPosterior, PhysicsSample
from physgm.physics.materials import log10_E_range


@dataclass
class ProposalSettings:
    """What a proposal needs from the rollout config."""

    material: str = "sample"  # "sample": candidates draw the material; "mode": all take the most likely
    min_std_decades: float = 0.3  # exploration floor of the policy draws' log10 E std
    min_std_nu: float = 0.03  # and of nu's
    wide_fraction: float = 2 / 3  # share of the K candidates the wide proposal stratifies


@dataclass
class Draws:
    """K candidates of one scene and where each came from."""

    sample: PhysicsSample  # [1, K] raw values, as the policy's log_prob needs them
    sources: list[str]  # [K] "policy" or "wide"


def widen(posterior: PhysicsPosterior, min_std_decades: float, min_std_nu: float) -> PhysicsPosterior:
    """The posterior with its E and nu standard deviations floored (the exploration proposal)."""
    # decades per unit of z_E: the global frame's, or the most likely material's (E_frame "material")
    decades = posterior.log10_E_std / torch.exp(0.5 * posterior.z_E_logvar)
    z_per_nu = 2.0 / (NU_RANGE[1] - NU_RANGE[0])
    floor_E = 2.0 * torch.log((min_std_decades / decades).clamp_min(1e-12))
    floor_nu = 2.0 * math.log(max(min_std_nu * z_per_nu, 1e-12))
    return replace(
        posterior,
        z_E_logvar=torch.maximum(posterior.z_E_logvar, floor_E),
        z_nu_logvar=posterior.z_nu_logvar.clamp_min(floor_nu),
    )


def scene_generator(seed: int, round_: int, scene: str) -> torch.Generator:
    """The same candidates for a scene and round whatever the rank count or restart."""
    return torch.Generator().manual_seed(
        (seed * 1_000_003 + round_ * 10_007 + zlib.crc32(scene.encode())) % 2**63
    )


def policy_proposal(
    posterior: PhysicsPosterior, k: int, cfg: ProposalSettings, generator: torch.Generator
) -> Draws:
    """K draws from the policy with its std floored (``widen``); [1] posterior on the CPU."""
    proposal = widen(posterior, cfg.min_std_decades, cfg.min_std_nu)
    draws = proposal.sample(k, generator)
    if cfg.material == "mode":  # pairs then isolate E and nu: the material terms cancel in the DPO ratio
        mode = proposal.material_logits.argmax(-1, keepdim=True).expand_as(draws.material).clone()
        draws = PhysicsSample(mode, draws.log10_E, draws.nu)
    return Draws(draws, ["policy"] * k)


def wide_count(k: int, wide_fraction: float) -> int:
    """How many of K candidates the wide proposal stratifies; the rest are policy draws."""
    return min(k, max(0, round(wide_fraction * k)))


def wide_proposal(
    posterior: PhysicsPosterior, k: int, cfg: ProposalSettings, generator: torch.Generator
) -> Draws:
    """``round(wide_fraction K)`` candidates stratified over their material's log10 E range, the rest
    from the policy; materials and nu are the policy's draws either way."""
    draws = policy_proposal(posterior, k, cfg, generator)
    n_wide = wide_count(k, cfg.wide_fraction)
    u = torch.rand(n_wide, generator=generator, dtype=torch.float64)
    log10_E = draws.sample.log10_E.clone()
    for j in range(n_wide):  # candidate j takes stratum j of n_wide
        lo, hi = log10_E_range(int(draws.sample.material[0, j]))
        log10_E[0, j] = lo + (j + float(u[j])) / n_wide * (hi - lo)
    sources = ["wide"] * n_wide + ["policy"] * (k - n_wide)
    return Draws(PhysicsSample(draws.sample.material, log10_E, draws.sample.nu), sources)


Proposal = Callable[[PhysicsPosterior, int, ProposalSettings, torch.Generator], Draws]
PROPOSALS: dict[str, Proposal] = {"policy": policy_proposal, "wide": wide_proposal}


def propose(
    name: str, posterior: PhysicsPosterior, k: int, cfg: ProposalSettings, generator: torch.Generator
) -> Draws:
    """K candidates from the proposal ``name`` (a key of ``PROPOSALS``)."""
    if name not in PROPOSALS:
        raise ValueError(f"unknown rollout proposal {name!r}; choose one of {', '.join(PROPOSALS)}")
    return PROPOSALS[name](posterior, k, cfg, generator)
