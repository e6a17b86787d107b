"""The engine's package docstring is its contract: what it lists can be imported from the package."""

from __future__ import annotations

import re

import physgm.sim.mpm as mpm


def _building_blocks() -> list[str]:
    """The names the docstring's "Building blocks" section opens an entry with (``Name(...)``)."""
    doc = mpm.__doc__
    section = doc[doc.index("Building blocks") : doc.index("Design notes")]
    return re.findall(r"^``(\w+)", section, flags=re.MULTILINE)


def test_every_building_block_the_docstring_lists_is_importable_from_the_package():
    names = _building_blocks()
    # The section names the grid, materials, particles, scenes, settings, the solver factory, the
    # solver, the one-call runner and the cost predictions; a reworded section must keep them.
    assert {"GridSpec", "MaterialParams", "Particles", "Scene", "SolverConfig", "make_solver"} <= set(names)
    assert {"MPMSolver", "run_solver", "cfl_dt"} <= set(names)
    missing = [name for name in names if not hasattr(mpm, name)]
    assert not missing, f"listed in physgm.sim.mpm's docstring but not importable from it: {missing}"
    assert set(names) <= set(mpm.__all__)


def test_every_integrator_the_config_accepts_is_exported_and_documented():
    for name, cls in mpm.INTEGRATORS.items():
        assert getattr(mpm, cls.__name__) is cls
        assert f'"{name}"' in mpm.__doc__ and cls.__name__ in mpm.__doc__
