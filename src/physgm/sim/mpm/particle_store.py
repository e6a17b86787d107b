"""Particle arrays of the solver: allocation, reordering by cell, frame backups, unsorting."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import warp as wp

from physgm.sim.constitutive import MaterialParams, MaterialStruct
from physgm.sim.mpm import particle_ops as ops
from physgm.sim.mpm.grid import GridSpec
from physgm.sim.mpm.state import Particles, ParticleState
from physgm.warp_runtime import ensure_loaded

_GATHERS = {
    wp.vec3: ops.gather_vec3,
    wp.mat33: ops.gather_mat33,
    wp.float32: ops.gather_float,
    wp.int32: ops.gather_int,
}


class ParticleStore:
    """Per-particle Warp arrays, kept in cell order; ``order[s]`` is the caller's index of slot s."""

    def __init__(self, particles: Particles, materials: Sequence[MaterialParams], device) -> None:
        n = len(particles)
        self.n, self.device = n, device
        ensure_loaded(
            ops.cell_keys, device
        )  # the particle kernels (sort, gathers, stress, energy) share a module
        density = np.array([m.density for m in materials], np.float32)
        F0 = particles.F if particles.F is not None else np.tile(np.eye(3, dtype=np.float32), (n, 1, 1))
        v0 = particles.v if particles.v is not None else np.zeros((n, 3), np.float32)
        self.x = wp.array(particles.x, dtype=wp.vec3, device=device)  # [P] m
        self.v = wp.array(v0, dtype=wp.vec3, device=device)  # [P] m/s
        self.C = (
            wp.zeros(n, dtype=wp.mat33, device=device)
            if particles.C is None
            else wp.array(particles.C, dtype=wp.mat33, device=device)
        )  # [P] 1/s
        self.H = wp.array(F0 - np.eye(3, dtype=np.float32), dtype=wp.mat33, device=device)  # [P] F - I
        self.stress = wp.zeros(n, dtype=wp.mat33, device=device)  # [P] rest volume x Kirchhoff, N m
        self.plastic = (
            wp.zeros(n, dtype=float, device=device)
            if particles.plastic is None
            else wp.array(particles.plastic, dtype=float, device=device)
        )  # [P]
        self.escaped = wp.zeros(n, dtype=int, device=device)  # [P] 0/1
        self.mass = wp.array(
            (particles.volume * density[particles.material]).astype(np.float32), dtype=float, device=device
        )  # [P] kg
        self.vol0 = wp.array(particles.volume, dtype=float, device=device)  # [P] m^3
        self.material = wp.array(particles.material, dtype=int, device=device)  # [P]
        self.order = wp.array(np.arange(n, dtype=np.int32), dtype=int, device=device)  # [P]
        self.mat_table = wp.array([m.pack() for m in materials], dtype=MaterialStruct, device=device)  # [M]
        self.materials = tuple(materials)  # [M] as the solver runs them
        self._keys = wp.zeros(2 * n, dtype=int, device=device)
        self._values = wp.zeros(2 * n, dtype=int, device=device)
        self._scratch = {t: wp.empty(n, dtype=t, device=device) for t in _GATHERS}

    @property
    def dynamic(self) -> list[wp.array]:
        """Arrays a sub-step changes (saved and restored by the divergence guard)."""
        return [self.x, self.v, self.C, self.H, self.stress, self.plastic, self.escaped]

    def sort(self, grid: GridSpec) -> None:
        """Reorder every array by grid cell, so neighbouring particles share cache lines."""
        n, dev = self.n, self.device
        wp.launch(
            ops.cell_keys,
            n,
            [self.x, wp.vec3(*grid.origin), grid.dx, wp.vec3i(*grid.res), self._keys, self._values],
            device=dev,
        )
        wp.utils.radix_sort_pairs(self._keys, self._values, n)
        perm = self._values[:n]
        for a in (*self.dynamic, self.mass, self.vol0, self.material, self.order):
            scratch = self._scratch[a.dtype]
            wp.launch(_GATHERS[a.dtype], n, [a, perm, scratch], device=dev)
            wp.copy(a, scratch)

    def unsort(self, a: wp.array) -> np.ndarray:
        """Copy of ``a`` in the caller's particle order."""
        values = a.numpy()
        out = np.empty_like(values)
        out[self.order.numpy()] = values
        return out

    def state(self) -> ParticleState:
        return ParticleState(
            x=self.unsort(self.x),
            v=self.unsort(self.v),
            F=self.unsort(self.H) + np.eye(3, dtype=np.float32),
            C=self.unsort(self.C),
            plastic=self.unsort(self.plastic),
            escaped=self.unsort(self.escaped).astype(bool),
        )
