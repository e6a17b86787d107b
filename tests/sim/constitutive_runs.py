"""The constitutive models' Warp kernel run on given deformation gradients, for tests that check
a model's stress, return mapping or energy against a reference (``tests/sim/test_constitutive.py``,
``tests/sim/mpm/test_pressure.py``). Import it as ``from tests.sim.constitutive_runs import run_warp``.
"""

from __future__ import annotations

import numpy as np
import warp as wp

from physgm.sim.constitutive import MaterialParams, MaterialStruct
from physgm.sim.mpm import particle_ops as K

DT = 1.0e-3  # s, the step of the plastic and viscous updates


def run_warp(
    params: MaterialParams, F: np.ndarray, plastic: np.ndarray, dt: float = DT
) -> dict[str, np.ndarray]:
    """One material's update of each F ([n, 3, 3]) with its plastic state ([n]) over dt: the new
    F, the Kirchhoff stress tau, the plastic state and the energy density, float64 numpy arrays."""
    n = len(F)
    mats = wp.array([params.pack()], dtype=MaterialStruct, device="cpu")
    outs = dict(
        F=wp.zeros(n, dtype=wp.mat33, device="cpu"),
        tau=wp.zeros(n, dtype=wp.mat33, device="cpu"),
        plastic=wp.zeros(n, dtype=float, device="cpu"),
        energy=wp.zeros(n, dtype=float, device="cpu"),
    )
    wp.launch(
        K.evaluate_constitutive,
        n,
        [
            wp.array(F.astype(np.float32), dtype=wp.mat33, device="cpu"),
            wp.array(plastic.astype(np.float32), dtype=float, device="cpu"),
            mats,
            wp.zeros(n, dtype=int, device="cpu"),
            dt,
            outs["F"],
            outs["tau"],
            outs["plastic"],
            outs["energy"],
        ],
        device="cpu",
    )
    return {k: v.numpy().astype(np.float64) for k, v in outs.items()}
