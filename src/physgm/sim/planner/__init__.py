"""Simulation planner: the cheapest simulation whose visual error stays under a pixel bound.

Inputs are the object (rest particles), its physics (material, E, nu, density), the scene
(gravity, ground, prescribed boxes, initial velocities) and the output cameras. The planner
converts physical deformation estimates to pixels with the cameras' focal length over depth and
chooses, in order of cost:

1. **rigid**: if the elastic + plastic deformation the scene can cause stays under the bound
   (a steel or ceramic object dropped on the floor or thrown at a still wall); granular and fluid
   materials never go rigid, nor do scenes that prescribe motion (grips, clamps).
2. **MPM with a stiffness cap**: the explicit step scales as dx / c_p with the P-wave speed
   c_p ~ sqrt(E / rho), so a stiff object costs many sub-steps. The cap is the smallest E' whose
   *extra* deformation over the true E stays under (a share of) the bound; E' = min(E, cap) is
   simulated and reported. Not after an elastic impact, whose rebound depends on E, nor for a
   body that moving boxes drive, nor for a granular or fluid material, whose runout depends on E;
   after a landing that dents only as far as the dent's own term allows
   (``deformation.STIFFNESS_DENT_GAIN``; see the comment in ``plan_simulation``).
   Before it, a **bulk cap** (``physgm.sim.bulk_cap``) lowers only the bulk modulus of a nearly
   incompressible solid (rubber, jelly, plasticine) so its P-wave is at most ``bulk_wave_ratio``
   times its shear wave, within its own share of the bound (that one also counts the rebound of an
   elastic impact, or the dent of a landing that yields); when the stiffness cap would save
   nothing, the bulk cap alone may use the whole bound.
3. **MPM at full stiffness** (the reference).

Under the pressure integrator (``solver.integrator=pressure``, ``physgm.sim.mpm.pressure``) the
explicit step follows the material's shear part, so the sub-steps are predicted from it and the
bulk cap is not offered: the grid takes the volume term implicitly, and a cap would add its error
for no step. With the explicit integrator (the default) the planner weighs that split too, for
the elastic models in a scene it handles, on a body at least ``pressure.PRESSURE_MIN_CELLS`` (12)
cells thick: the cheapest of options 2 and 3 with it and without, counting each of its sub-steps
as ``pressure.PRESSURE_STEP_COST`` explicit ones and taking it only when it saves ``min_cap_gain``
(nearly incompressible bodies: rubber from nu of about 0.47, where the wave sets the step). It
keeps E and nu and adds no error term: on such a body its clip is as close to converged MPM as
explicit's, while a thinner one drifts from explicit from its first contact
(docs/measurements_sim.md sections 42 and 45). ``Plan.integrator`` says which runs;
``planner.allow_pressure=false`` keeps explicit.

Under the implicit integrator (``solver.integrator=implicit``, ``physgm.sim.mpm.implicit``) the
sub-steps are its own (``implicit_dt``, shorter when the body is fast) and neither cap is offered.

Modules, in the order a reader needs them:
    config.py       ``PlannerConfig``, the knobs (conf/sim/planner/default.yaml)
    domain.py       grid cell size and particle spacing (``choose_spacing``, ``stretch_splits``)
                    and the region the grid must hold (``reachable_region``, ``grid_region``)
    deformation.py  the error models: deformation estimates in metres, the stiffness cap, and
                    the metres-to-pixels scale of the output cameras
    plan.py         ``Plan``, the choice with its predicted cost and error, and its JSON summary
    choose.py       ``plan_simulation``, which weighs the options above
"""

from physgm.sim.planner.choose import FLOWING_MODELS, NEVER_RIGID_MATERIALS, plan_simulation
from physgm.sim.planner.config import PlannerConfig
from physgm.sim.planner.deformation import (
    Deformation,
    deformation_estimate,
    impact_speed,
    pixels_per_metre,
    stiffness_cap,
)
from physgm.sim.planner.domain import (
    GRANULAR_MODELS,
    choose_spacing,
    granular_runout,
    grid_region,
    heap_radius,
    reachable_region,
    stretch_splits,
)
from physgm.sim.planner.plan import Plan

__all__ = [
    "FLOWING_MODELS",
    "GRANULAR_MODELS",
    "NEVER_RIGID_MATERIALS",
    "Deformation",
    "Plan",
    "PlannerConfig",
    "choose_spacing",
    "deformation_estimate",
    "granular_runout",
    "grid_region",
    "heap_radius",
    "impact_speed",
    "pixels_per_metre",
    "plan_simulation",
    "reachable_region",
    "stiffness_cap",
    "stretch_splits",
]
