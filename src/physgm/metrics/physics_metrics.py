"""Metrics of predicted physics against the *true* values (not only the noisy annotation)."""

from __future__ import annotations

import torch
from torch import Tensor
from torchmetrics import Metric
from torchmetrics.classification import MulticlassConfusionMatrix
from torchmetrics.utilities import dim_zero_cat

from physgm.model.posterior import PhysicsPosterior, PhysicsSample
from physgm.physics.behaviour import behaviour_index
from physgm.physics.materials import MATERIAL_NAMES, log10_E_range

# Two-sided 90 % interval of a Gaussian: mean +- 1.6449 std.
Z90 = 1.6448536269514722


def calibration_logvar_offset(z: Tensor, level: float = 0.9) -> Tensor:  # z [N] -> scalar
    """The log-variance offset that makes the ``level`` interval cover that share of these errors.

    ``z`` holds |error| / predicted std. Scaling every std by s = quantile(z, level) / z_level puts
    exactly ``level`` of the errors inside mean +- z_level * s * std; in log-variance that is
    + 2 log s. Positive: the posterior was over-confident.
    """
    z_level = float(torch.special.ndtri(torch.tensor(0.5 + level / 2, dtype=torch.float64)))
    return 2.0 * torch.log(torch.quantile(z.double(), level) / z_level).to(z.dtype)


def central_coverage(cdf: Tensor, level: float = 0.9) -> Tensor:  # [N] -> scalar
    """Share of true values inside the posterior's central ``level`` interval, from the posterior's
    CDF at each true value (``PhysicsPosterior.log10_E_cdf``)."""
    return ((cdf >= 0.5 - level / 2) & (cdf <= 0.5 + level / 2)).float().mean()


STATES = ("correct", "correct_behaviour", "err_E", "err_E_simulated", "err_nu", "nll", "z_E", "z_nu", "cdf_E")


class PhysicsMetrics(Metric):
    """Material accuracy and confusion, |log10 E - true|, |nu - true|, NLL and 90 % interval coverage.

    The E coverage is that of the central 90 % interval of the posterior's E (the true E's CDF within
    0.05-0.95): its Gaussian's, or for a material-frame head the mixture over materials. The E
    calibration offset scales the most likely material's Gaussian, the one the mean is read from.

    ``compute()`` returns a dict of scalars plus ``confusion`` [M, M] (rows true, columns predicted).
    """

    full_state_update = False

    def __init__(self, num_materials: int) -> None:
        super().__init__()
        self.confusion = MulticlassConfusionMatrix(num_classes=num_materials)
        for name in STATES:
            self.add_state(name, default=[], dist_reduce_fx="cat")
        self.behaviour = behaviour_index()
        # [M, 2] log10 E range of each material: what simulate.py projects the predicted E onto
        # (pipeline.physics_choice); only with the table's materials, in its order.
        self.E_ranges = (
            torch.tensor([log10_E_range(m) for m in MATERIAL_NAMES])
            if num_materials == len(MATERIAL_NAMES)
            else None
        )

    def update(
        self,
        posterior: PhysicsPosterior,
        material: Tensor,  # [B] true material index
        log10_E: Tensor,  # [B] true log10 E, Pa
        nu: Tensor,  # [B] true Poisson ratio
    ) -> None:
        posterior = posterior.detach()
        pred = posterior.material_logits.argmax(-1)
        self.confusion.update(pred, material)
        self.correct.append((pred == material).float())
        behaviour = self.behaviour.to(pred.device)
        self.correct_behaviour.append((behaviour[pred] == behaviour[material]).float())
        self.err_E.append((posterior.log10_E_mean - log10_E).abs())
        if self.E_ranges is not None:
            lo, hi = self.E_ranges.to(pred.device, posterior.log10_E_mean.dtype)[pred].unbind(-1)
            simulated = posterior.log10_E_mean.clamp(lo, hi)
            self.err_E_simulated.append((simulated - log10_E).abs())
        self.err_nu.append((posterior.nu_mean - nu).abs())
        truth = PhysicsSample(material[:, None], log10_E[:, None], nu[:, None])
        self.nll.append(-posterior.log_prob(truth)[:, 0])
        self.z_E.append((posterior.log10_E_mean - log10_E).abs() / posterior.log10_E_std)
        self.z_nu.append((posterior.nu_mean - nu).abs() / posterior.nu_std)
        self.cdf_E.append(posterior.log10_E_cdf(log10_E))

    def compute(self) -> dict[str, Tensor]:
        names = [n for n in STATES if self.E_ranges is not None or n != "err_E_simulated"]
        cat = {name: dim_zero_cat(getattr(self, name)) for name in names}
        return {
            "material_acc": cat["correct"].mean(),
            "behaviour_acc": cat["correct_behaviour"].mean(),
            "abs_log10E_median": cat["err_E"].median(),
            "abs_log10E_mean": cat["err_E"].mean(),
            **(
                {  # the E simulate.py runs: the mean projected onto the predicted material's range
                    "abs_log10E_simulated_median": cat["err_E_simulated"].median(),
                    "abs_log10E_simulated_mean": cat["err_E_simulated"].mean(),
                }
                if self.E_ranges is not None
                else {}
            ),
            "abs_nu_median": cat["err_nu"].median(),
            "abs_nu_mean": cat["err_nu"].mean(),
            "nll": cat["nll"].mean(),
            "coverage90_E": central_coverage(cat["cdf_E"]),
            "coverage90_nu": (cat["z_nu"] <= Z90).float().mean(),
            "calibration_logvar_offset_E": calibration_logvar_offset(cat["z_E"]),
            "calibration_logvar_offset_nu": calibration_logvar_offset(cat["z_nu"]),
            "confusion": self.confusion.compute(),
        }

    def reset(self) -> None:
        super().reset()
        self.confusion.reset()


class LabelMetrics(Metric):
    """Material and behaviour accuracy against a labelled material, for assets without true physics.

    Real objects (imported meshes, photos) carry a hand or annotator label of their material and
    no true E or nu; this scores what can be scored. ``compute()`` adds ``confusion`` [M, M].
    """

    full_state_update = False

    def __init__(self, num_materials: int) -> None:
        super().__init__()
        self.confusion = MulticlassConfusionMatrix(num_classes=num_materials)
        self.add_state("correct", default=[], dist_reduce_fx="cat")
        self.add_state("correct_behaviour", default=[], dist_reduce_fx="cat")
        self.behaviour = behaviour_index()

    def update(
        self,
        material_logits: Tensor,  # [B, M]
        material: Tensor,  # [B] labelled material index
    ) -> None:
        pred = material_logits.detach().argmax(-1)
        self.confusion.update(pred, material)
        behaviour = self.behaviour.to(pred.device)
        self.correct.append((pred == material).float())
        self.correct_behaviour.append((behaviour[pred] == behaviour[material]).float())

    def compute(self) -> dict[str, Tensor]:
        return {
            "material_acc": dim_zero_cat(self.correct).mean(),
            "behaviour_acc": dim_zero_cat(self.correct_behaviour).mean(),
            "confusion": self.confusion.compute(),
        }

    def reset(self) -> None:
        super().reset()
        self.confusion.reset()
