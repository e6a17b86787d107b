"""The physics posterior P(theta | I): a categorical over materials and Gaussians on log10 E and nu.

Normalisation (the one place it is defined): the Gaussians live on normalised coordinates z in
roughly [-1, 1], so both regressions have the same scale:
    z_E  = 2 * (log10 E - 3.0) / (11.7 - 3.0) - 1   (E in Pa: 1 kPa .. 500 GPa)
    z_nu = 2 * (nu - 0.0) / (0.5 - 0.0) - 1
Samples are reported in physical units (log10 E in log10 Pa, nu). ``log_prob`` is the exact log
density of the *normalised* values (categorical log prob + two Gaussian log densities), which is
what the pretraining NLL and the DPO ratio need; the constant Jacobian of the affine map is left out.

With ``E_ranges`` (a [M, 2] table of each material's log10 E range, ``material_E_ranges``) z_E is
instead relative to the material: z_E = -1 and 1 are the ends of that material's range, so E is
conditional on the material (``physics_head.E_frame="material"``). The mean and the spread are then
those of the most likely material, a sample maps its z_E with its own material's range, and
``log_prob`` normalises a candidate's E with its candidate's material (the Jacobian, now different per
material, is still left out: it cancels in the DPO ratio, where policy and reference share it).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import Tensor

LOG10_E_RANGE = (3.0, 11.7)  # log10(Pa) mapped to z in [-1, 1]
NU_RANGE = (0.0, 0.5)  # Poisson ratio mapped to z in [-1, 1]
NU_MAX = 0.49  # physical clip: nu -> 0.5 makes the Lamé lambda blow up in the simulator
_LOG_2PI = math.log(2.0 * math.pi)


def _to_unit(x: Tensor, value_range: tuple[float, float]) -> Tensor:
    """Affine map of [lo, hi] onto [-1, 1]."""
    lo, hi = value_range
    return 2.0 * (x - lo) / (hi - lo) - 1.0


def _from_unit(z: Tensor, value_range: tuple[float, float]) -> Tensor:
    """Inverse of `_to_unit`."""
    lo, hi = value_range
    return lo + (z + 1.0) * 0.5 * (hi - lo)


def normalise_log10_E(log10_E: Tensor) -> Tensor:
    return _to_unit(log10_E, LOG10_E_RANGE)


def denormalise_log10_E(z: Tensor) -> Tensor:
    return _from_unit(z, LOG10_E_RANGE)


def material_E_ranges() -> Tensor:  # [M, 2]
    """log10 of each material's E range in the material table, in ``MATERIAL_NAMES`` order."""
    from physgm.physics.materials import MATERIAL_NAMES, get_material

    return torch.tensor([[math.log10(x) for x in get_material(m).E_range] for m in MATERIAL_NAMES])


def normalise_nu(nu: Tensor) -> Tensor:
    return _to_unit(nu, NU_RANGE)


def denormalise_nu(z: Tensor) -> Tensor:
    return _from_unit(z, NU_RANGE)


@dataclass
class PhysicsSample:
    """K physics candidates per sample, in physical units, unclipped as drawn.

    Attributes:
        material: [B, K] int64 index into ``physgm.physics.materials.MATERIAL_NAMES``.
        log10_E: [B, K] log10 of Young's modulus in Pa.
        nu: [B, K] Poisson ratio.
    """

    material: Tensor  # [B, K] int64
    log10_E: Tensor  # [B, K]
    nu: Tensor  # [B, K]

    def youngs_modulus(self) -> Tensor:  # [B, K] Pa
        """Young's modulus in Pa, log10 E clipped to ``LOG10_E_RANGE`` so tails stay simulable."""
        return 10.0 ** self.log10_E.clamp(*LOG10_E_RANGE)

    def poisson_ratio(self) -> Tensor:  # [B, K]
        """Poisson ratio clipped to [0, ``NU_MAX``] (strictly below 0.5)."""
        return self.nu.clamp(NU_RANGE[0], NU_MAX)

    def __getitem__(self, index) -> PhysicsSample:
        return PhysicsSample(self.material[index], self.log10_E[index], self.nu[index])


@dataclass
class PhysicsPosterior:
    """Per-sample posterior over (material, log10 E, nu), Gaussians on normalised coordinates.

    Attributes:
        material_logits: [B, M] unnormalised log probabilities of the M materials.
        z_E_mean, z_E_logvar: [B] mean and log-variance of normalised log10 E.
        z_nu_mean, z_nu_logvar: [B] mean and log-variance of normalised nu.
        E_ranges: None (z_E in the global frame) or [M, 2] log10 E range per material (z_E relative
            to the material; not per batch element, so indexing the posterior keeps it whole).
    """

    material_logits: Tensor  # [B, M]
    z_E_mean: Tensor  # [B]
    z_E_logvar: Tensor  # [B]
    z_nu_mean: Tensor  # [B]
    z_nu_logvar: Tensor  # [B]
    E_ranges: Tensor | None = None  # [M, 2]

    BATCHED = ("material_logits", "z_E_mean", "z_E_logvar", "z_nu_mean", "z_nu_logvar")

    @property
    def material_probs(self) -> Tensor:  # [B, M]
        return self.material_logits.softmax(dim=-1)

    def _E_frame(self, material: Tensor) -> tuple[Tensor, Tensor] | tuple[float, float]:
        """(lo, hi) of log10 E that z_E = -1, 1 stand for, for ``material`` (any shape of indices)."""
        if self.E_ranges is None:
            return LOG10_E_RANGE
        ranges = self.E_ranges.to(self.z_E_mean)
        return ranges[material, 0], ranges[material, 1]

    @property
    def log10_E_mean(self) -> Tensor:  # [B] log10 Pa
        return _from_unit(self.z_E_mean, self._E_frame(self.material_logits.argmax(-1)))

    @property
    def log10_E_std(self) -> Tensor:  # [B] decades
        lo, hi = self._E_frame(self.material_logits.argmax(-1))
        return torch.exp(0.5 * self.z_E_logvar) * 0.5 * (hi - lo)

    def log10_E_cdf(self, log10_E: Tensor) -> Tensor:  # [B] -> [B]
        """P(log10 E' <= ``log10_E``) under the posterior: its Gaussian's, or with ``E_ranges`` the mixture
        over the materials of each material's Gaussian (the material probabilities as weights)."""
        std = torch.exp(0.5 * self.z_E_logvar)
        if self.E_ranges is None:
            return torch.special.ndtr((normalise_log10_E(log10_E) - self.z_E_mean) / std)
        z = _to_unit(log10_E[:, None], self._E_frame(slice(None)))  # [B, M], each material's frame
        per_material = torch.special.ndtr((z - self.z_E_mean[:, None]) / std[:, None])
        return (self.material_probs * per_material).sum(-1)

    def log10_E_log_density(self, log10_E: Tensor) -> Tensor:  # [B] -> [B]
        """log p(``log10_E``) per decade: its Gaussian's, or with ``E_ranges`` the mixture over the
        materials (each Gaussian read in its material's frame, with that frame's Jacobian)."""
        if self.E_ranges is None:
            lo, hi = LOG10_E_RANGE
            z = normalise_log10_E(log10_E)[:, None]  # [B, 1]
            return _gaussian_log_density(z, self.z_E_mean, self.z_E_logvar)[:, 0] + math.log(2.0 / (hi - lo))
        lo, hi = self._E_frame(slice(None))  # [M] each
        z = _to_unit(log10_E[:, None], (lo, hi))  # [B, M]
        per_material = _gaussian_log_density(z, self.z_E_mean, self.z_E_logvar) + torch.log(2.0 / (hi - lo))
        return torch.logsumexp(F.log_softmax(self.material_logits, dim=-1) + per_material, dim=-1)

    @property
    def nu_mean(self) -> Tensor:  # [B]
        return denormalise_nu(self.z_nu_mean)

    @property
    def nu_std(self) -> Tensor:  # [B]
        return torch.exp(0.5 * self.z_nu_logvar) * 0.5 * (NU_RANGE[1] - NU_RANGE[0])

    def sample(self, num_samples: int, generator: torch.Generator | None = None) -> PhysicsSample:
        """Draw K = ``num_samples`` independent candidates per batch element (no gradient)."""
        with torch.no_grad():
            b = self.material_logits.shape[0]
            material = torch.multinomial(
                self.material_probs, num_samples, replacement=True, generator=generator
            )
            noise = torch.randn(
                2, b, num_samples, generator=generator, device=self.z_E_mean.device, dtype=self.z_E_mean.dtype
            )
            z_E = self.z_E_mean[:, None] + torch.exp(0.5 * self.z_E_logvar)[:, None] * noise[0]
            z_nu = self.z_nu_mean[:, None] + torch.exp(0.5 * self.z_nu_logvar)[:, None] * noise[1]
        return PhysicsSample(material, _from_unit(z_E, self._E_frame(material)), denormalise_nu(z_nu))

    def mean(self) -> PhysicsSample:
        """The most likely material and the mean E and nu, as a K = 1 sample."""
        return PhysicsSample(
            self.material_logits.argmax(dim=-1, keepdim=True),
            self.log10_E_mean[:, None],
            self.nu_mean[:, None],
        )

    def log_prob_terms(self, sample: PhysicsSample) -> tuple[Tensor, Tensor, Tensor]:  # 3 x [B, K]
        """Exact log probabilities of (material, normalised log10 E, normalised nu), separately."""
        log_p = F.log_softmax(self.material_logits, dim=-1).gather(1, sample.material)
        z_E = _to_unit(sample.log10_E, self._E_frame(sample.material))
        log_E = _gaussian_log_density(z_E, self.z_E_mean, self.z_E_logvar)
        log_nu = _gaussian_log_density(normalise_nu(sample.nu), self.z_nu_mean, self.z_nu_logvar)
        return log_p, log_E, log_nu

    def log_prob(self, sample: PhysicsSample) -> Tensor:  # [B, K]
        """Joint log probability (sum of ``log_prob_terms``); differentiable w.r.t. the posterior."""
        log_p, log_E, log_nu = self.log_prob_terms(sample)
        return log_p + log_E + log_nu

    def entropy(self) -> Tensor:  # [B]
        """Entropy of the categorical plus the differential entropies of the two normalised Gaussians."""
        log_p = F.log_softmax(self.material_logits, dim=-1)
        categorical = -(log_p.exp() * log_p).sum(dim=-1)
        gaussians = 1.0 + _LOG_2PI + 0.5 * (self.z_E_logvar + self.z_nu_logvar)
        return categorical + gaussians

    def _map(self, fn) -> PhysicsPosterior:
        """The same posterior with ``fn`` applied to each batched tensor."""
        return PhysicsPosterior(**{k: fn(getattr(self, k)) for k in self.BATCHED}, E_ranges=self.E_ranges)

    def detach(self) -> PhysicsPosterior:
        return self._map(Tensor.detach)

    def cpu_float(self) -> PhysicsPosterior:
        """A float32 copy on the CPU (rollouts and the pipeline read it there)."""
        out = self._map(lambda t: t.float().cpu())
        out.E_ranges = None if self.E_ranges is None else self.E_ranges.float().cpu()
        return out

    def __getitem__(self, index) -> PhysicsPosterior:
        """The posteriors of the batch elements selected by ``index`` (mask, indices or slice)."""
        return self._map(lambda t: t[index])

    @classmethod
    def cat(cls, posteriors: list[PhysicsPosterior]) -> PhysicsPosterior:
        """One posterior of the batch elements of ``posteriors`` in order (they share ``E_ranges``)."""
        if not posteriors:
            raise ValueError("PhysicsPosterior.cat needs at least one posterior")
        fields = {k: torch.cat([getattr(p, k) for p in posteriors]) for k in cls.BATCHED}
        return cls(**fields, E_ranges=posteriors[0].E_ranges)


def _gaussian_log_density(
    z: Tensor,  # [B, K]
    mean: Tensor,  # [B]
    logvar: Tensor,  # [B]
) -> Tensor:  # [B, K]
    return -0.5 * (_LOG_2PI + logvar[:, None] + (z - mean[:, None]) ** 2 * torch.exp(-logvar)[:, None])
