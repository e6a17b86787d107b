"""Per-sub-step observables of a running solver: momentum, centre-of-mass velocity, contact forces.

Register an observer and the solver calls it after every sub-step:

    rec = ObservableRecorder()
    solver.observers.append(rec)
    solver.run(10)
    series = rec.arrays()        # {"time": [S], "com_velocity": [S, 3], "ground_force": [S, 3], ...}

Forces are the impulse a boundary gave the grid during the sub-step divided by its length, so
they add up with gravity to the change of momentum: M dv_com / dt = M g + ground + walls +
faces (+ velocity boxes and damping, which are not split out). A body resting on the ground
reads ground_force[2] ~ M |g| (the per-step value oscillates with the elastic waves; average it
over a few periods). A frame the divergence guard retries is observed again from its start: the
recorder then drops the samples of the rejected attempt.
"""

from __future__ import annotations

from dataclasses import dataclass, fields
from typing import Protocol

import numpy as np
import warp as wp

wp.set_module_options({"enable_backward": False})


@dataclass
class SubstepObservables:
    """What one sub-step did (SI units)."""

    time: float  # s, at the end of the sub-step
    dt: float  # s
    mass: float  # kg, of all particles
    momentum: np.ndarray  # [3] kg m/s, sum of m v over the particles
    com_velocity: np.ndarray  # [3] m/s, momentum / mass
    ground_force: np.ndarray  # [3] N, force of the ground plane on the grid during the sub-step
    wall_force: np.ndarray  # [3] N, force of the scene's side walls
    face_force: np.ndarray  # [3] N, force of the separating walls at the grid faces (0 when unused)
    face_contacts: int  # grid nodes a face wall stopped during the sub-step (0 when unused)


class SubstepObserver(Protocol):
    """Called by ``MPMSolver`` after every sub-step it takes (``solver.observers``)."""

    def observe(self, obs: SubstepObservables) -> None: ...


class ObservableRecorder:
    """Keeps every sub-step's observables; drops the samples of a frame attempt that was retried."""

    def __init__(self) -> None:
        self.samples: list[SubstepObservables] = []

    def observe(self, obs: SubstepObservables) -> None:
        start = obs.time - obs.dt
        # A retried frame restarts at an earlier time: the rejected attempt's samples go.
        while self.samples and self.samples[-1].time > start + 1e-6 * obs.dt:
            self.samples.pop()
        self.samples.append(obs)

    def arrays(self) -> dict[str, np.ndarray]:
        """Each field stacked over the sub-steps: scalars [S], vectors [S, 3]."""
        return {
            f.name: np.array([getattr(s, f.name) for s in self.samples]) for f in fields(SubstepObservables)
        }


@wp.kernel
def particle_momentum(
    v: wp.array(dtype=wp.vec3),  # [P] m/s
    mass: wp.array(dtype=float),  # [P] kg
    out: wp.array(dtype=wp.float64),  # [4] out: momentum xyz (kg m/s), mass (kg); zeroed by the caller
):
    p = wp.tid()
    m = mass[p]
    q = m * v[p]
    wp.atomic_add(out, 0, wp.float64(q[0]))
    wp.atomic_add(out, 1, wp.float64(q[1]))
    wp.atomic_add(out, 2, wp.float64(q[2]))
    wp.atomic_add(out, 3, wp.float64(m))
