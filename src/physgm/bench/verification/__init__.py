"""Verification cases of the simulator, run by ``python -m physgm.bench sim-verify`` and the tests.

``analytic``: the MPM engine against analytic results (free fall, resting block, bar vibration,
cantilever, spinning cube, colliding spheres, restitution, sand pile); ``all_cases`` lists what
sim-verify runs. ``granular``: granular column collapse against published run-out laws.
``contact``: Hertz contact time and the sideways drift of a dropped box. ``planner``: an elastic
cube of Gaussians through ``physgm.sim.gaussian_trajectory.simulate`` at the planner's defaults
against its static sag.
"""
