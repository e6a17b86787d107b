"""physgm.sim: Gaussians in, moving Gaussians out.

``simulate(gaussians, physics, scene, cameras)`` (gaussian_trajectory.py) is the one entry the
pipeline, the data generator and the DPO rollouts call. It samples particles from the Gaussians
(sampling.py), applies a scene (scenes.py: the ``SCENES`` registry of drivers, conf/sim/scene),
plans the cheapest simulation within the pixel bound (``planner/``: settings, grid, error models,
the plan and the choice, one module each; with the bulk-stiffness cap of bulk_cap.py), runs it on
the rigid-body path (rigid.py) or the MPM engine (``physgm.sim.mpm``, whose package docstring is
the engine's contract), and moves the Gaussians with the particles (coupling.py). The
constitutive models and their parameters (``MaterialParams``, the ``MODELS`` registry) live in
``physgm.sim.constitutive``; ``linalg.py`` holds the Warp 3x3 decompositions they and the
coupling share.

Everything is SI: metres, seconds, kilograms, pascals. World frame: +z up, ground z = 0.

This package file imports nothing: the material table imports ``physgm.sim.constitutive`` to
check its rows, and that must not load torch and the whole Gaussian layer.
"""
