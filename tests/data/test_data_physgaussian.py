"""PhysGaussian simulation configs (their config/*.json layout) mapped onto simulate.yaml's settings.

The configs follow PhysGaussian's own files (jelly with a sticky ground like their ficus scene,
the PhysGM authors' y-up drop template); expected settings are worked out by hand in comments.
"""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch
from hydra import compose, initialize_config_dir

from physgm.data.readers.physgaussian import UP_ROTATIONS, PhysGaussianConfigError, read_physgaussian
from physgm.errors import UserError
from physgm.gaussians import Gaussians, write_ply
from physgm.physics.materials import PhysicsSpec
from physgm.pipeline.config import from_hydra
from physgm.pipeline.prepared_input import UP_ROTATIONS as PIPELINE_UP_ROTATIONS
from physgm.resources import conf_dir


def _box_points(extent, centre=(5.0, 5.0, 5.0)) -> tuple[np.ndarray, np.ndarray]:
    """The 8 corners of a box plus a faint stray Gaussian far below it (PhysGaussian drops it)."""
    corners = np.array([[x, y, z] for x in (-0.5, 0.5) for y in (-0.5, 0.5) for z in (-0.5, 0.5)]) * extent
    means = np.vstack([corners + centre, [[5.0, 5.0, -50.0]]])
    opacities = np.array([0.9] * 8 + [0.01])
    return means, opacities


JELLY = {
    "opacity_threshold": 0.02, "rotation_degree": [0.0], "rotation_axis": [0], "substep_dt": 1e-4,
    "frame_dt": 4e-2, "frame_num": 25, "nu": 0.4, "E": 2e6, "material": "jelly", "density": 200,
    "g": [0, 0, -9.8], "grid_v_damping_scale": 1.1, "rpic_damping": 0.0,
    "boundary_conditions": [
        {"type": "bounding_box"},
        {"type": "surface_collider", "point": [1, 1, 0.3], "normal": [0, 0, 1], "surface": "sticky",
         "friction": 0.0, "start_time": 0, "end_time": 1e3},
    ],
    "mpm_space_vertical_upward_axis": [0, 0, 1], "mpm_space_viewpoint_center": [1, 1, 1],
    "default_camera_index": -1, "show_hint": False, "init_azimuthm": -36.7, "init_elevation": 8.96,
    "init_radius": 4.11, "move_camera": True, "delta_a": 0.4, "delta_e": 0.0, "delta_r": 0.0,
}  # fmt: skip


def test_jelly_on_a_sticky_ground():
    means, opacities = _box_points(np.array([2.0, 1.0, 0.5]))
    run = read_physgaussian(JELLY, means, opacities)
    assert run.physics == PhysicsSpec("jelly", E=2e6, nu=0.4, density=200.0)
    # Largest extent 2 -> scaled to 1 m; the 0.5 tall box is 0.25 m tall, centred at z = 1, so its
    # bottom is at 0.875 m: 0.575 m above the collider at z = 0.3 (the box floor, 3 cells of
    # 2 / 50 m = 0.12 m, is lower). The faint stray Gaussian at z = -50 does not count.
    assert run.size_m == 1.0 and run.up == "z"
    assert run.drop_height_m == pytest.approx(0.575)
    assert run.ground == {"height": 0.0, "friction": 0.0, "mode": "sticky"}
    assert run.gravity == (0.0, 0.0, -9.8)
    assert run.fps == pytest.approx(25.0) and run.frames == 26  # 25 simulated frames after the rest frame
    assert run.min_opacity == 0.02 and run.fill_interior is False
    assert {"substep_dt", "init_azimuthm", "mpm_space_viewpoint_center"} <= set(run.ignored)


# The PhysGM authors' template (their configs/physical/down_template.json): y up, a slip ground.
DOWN_TEMPLATE = {
    "opacity_threshold": 0.02, "rotation_degree": [0.0], "rotation_axis": [0], "substep_dt": 2e-4,
    "frame_dt": 4e-2, "density": 5000, "frame_num": 50, "g": [0.0, -0.98, 0.0], "friction_angle": 30,
    "n_grid": 100,
    "particle_filling": {"n_grid": 50, "density_threshold": 50.0, "search_threshold": 1.0,
                         "search_exclude_direction": 2, "ray_cast_direction": 4, "max_particles_num": 200000,
                         "max_partciels_per_cell": 1, "boundary": [0.4, 1.6, 0.4, 1.6, 0.4, 1.6],
                         "smooth": True, "visualize": True},
    "boundary_conditions": [
        {"type": "bounding_box"},
        {"type": "surface_collider", "point": [1, 0.25, 1], "normal": [0.0, 1.0, 0.0], "surface": "slip",
         "friction": 0.0, "start_time": 0, "end_time": 1e3},
    ],
    "mpm_space_vertical_upward_axis": [0, 1, 0], "mpm_space_viewpoint_center": [1, 0.8, 1],
    "default_camera_index": -1, "show_hint": False, "init_azimuthm": -45, "init_elevation": 0,
    "init_radius": 1.8, "move_camera": False, "delta_a": -2.4, "delta_e": 0.0, "delta_r": 0.0,
}  # fmt: skip


def test_y_up_template_with_defaults_and_particle_filling():
    means, opacities = _box_points(np.array([1.0, 0.5, 1.0]))  # 0.5 tall along y, the up axis
    run = read_physgaussian(DOWN_TEMPLATE, means, opacities)
    # No material, E or nu: PhysGaussian's defaults (jelly, 1e5 Pa, 0.4); density from the file.
    assert run.physics == PhysicsSpec("jelly", E=1e5, nu=0.4, density=5000.0)
    assert run.up == "y"
    # y up: the object turns y -> z, and so does gravity: (0, -0.98, 0) becomes (0, 0, -0.98).
    np.testing.assert_allclose(run.gravity, (0.0, 0.0, -0.98))
    # Largest extent 1 (unscaled): the bottom along y is at 1 - 0.5 / 2 = 0.75 m, 0.5 m above the
    # slip collider at y = 0.25.
    assert run.drop_height_m == pytest.approx(0.5)
    assert run.ground == {"height": 0.0, "friction": 0.0, "mode": "slip"}
    assert run.frames == 51 and run.fill_interior is True
    assert "friction_angle" in run.ignored  # a jelly does not use it (only PhysGaussian's sand does)


def test_rotation_that_turns_a_y_up_file_upright_gives_object_up_y():
    # A 90 degree turn about x takes the file's +y to +z, PhysGaussian's up here.
    cfg = {
        **JELLY,
        "rotation_degree": [90.0],
        "rotation_axis": [0],
        "boundary_conditions": [{"type": "bounding_box"}],
    }
    means, opacities = _box_points(np.array([1.0, 0.5, 1.0]))
    run = read_physgaussian(cfg, means, opacities)
    assert run.up == "y" and run.gravity == pytest.approx((0.0, 0.0, -9.8))
    # Only the box floor: 3 cells of 2 / 50 m = 0.12 m; the bottom is at 1 - 0.25 = 0.75 m.
    assert run.ground["mode"] == "slip" and run.drop_height_m == pytest.approx(0.75 - 0.12)


def test_up_rotations_match_the_pipeline():
    for name, rot in PIPELINE_UP_ROTATIONS.items():
        np.testing.assert_array_equal(UP_ROTATIONS[name], rot)


@pytest.mark.parametrize(
    "change, key",
    [
        ({"boundary_conditions": [{"type": "cuboid", "point": [1, 1, 0.5], "size": [0.5, 0.5, 0.28],
                                   "velocity": [0, 0, 0]}]}, r"boundary_conditions\[0\]\.type: 'cuboid'"),
        ({"boundary_conditions": [{"type": "particle_impulse", "force": [-0.18, 0, 0]}]},
         r"boundary_conditions\[0\]\.type: 'particle_impulse'"),
        ({"boundary_conditions": [{"type": "surface_collider", "point": [1, 1, 0.3], "normal": [1, 0, 0],
                                   "surface": "sticky", "friction": 0, "start_time": 0, "end_time": 1e3}]},
         r"boundary_conditions\[0\]\.normal"),
        ({"boundary_conditions": [{"type": "surface_collider", "point": [1, 1, 0.95], "normal": [0, 0, 1],
                                   "surface": "sticky", "friction": 0, "start_time": 0, "end_time": 1e3}]},
         r"boundary_conditions\[0\]: .*cuts through the object"),
        ({"additional_material_params": [{"point": [1, 1, 1.5], "size": [1, 1, 0.5], "E": 2e6, "nu": 0.4}]},
         "additional_material_params"),
        ({"material": "sand", "friction_angle": 30}, "friction_angle: 30 degrees differs from physgm's sand"),
        ({"material": "metal", "yield_stress": 1e7}, "yield_stress"),
        ({"material": "water"}, "material: 'water' is not one of PhysGaussian's"),
        ({"grid_v_damping_scale": 0.9999}, "grid_v_damping_scale"),
        ({"rpic_damping": 0.1}, "rpic_damping"),
        ({"mpm_space_vertical_upward_axis": [1, 0, 0]}, "mpm_space_vertical_upward_axis"),
        ({"colour": "red"}, "colour: unknown key"),
        ({"nu": 0.5}, r"E, nu, density: nu=0\.5 must be in \[0, 0\.5\)"),
    ],
)  # fmt: skip
def test_keys_without_a_counterpart_are_errors_naming_the_key(change, key):
    means, opacities = _box_points(np.array([2.0, 1.0, 0.5]))
    with pytest.raises(PhysGaussianConfigError, match=key):
        read_physgaussian({**JELLY, **change}, means, opacities)


def _ply(path, means, opacities) -> None:
    n = len(means)
    write_ply(
        Gaussians(
            means=torch.tensor(means, dtype=torch.float32),
            quats=torch.tensor([[1.0, 0, 0, 0]]).repeat(n, 1),
            scales=torch.full((n, 3), 0.05),
            opacities=torch.tensor(opacities, dtype=torch.float32),
            colors=torch.full((n, 3), 0.5),
        ),
        path,
    )


def _compose(overrides: list[str]):
    with initialize_config_dir(config_dir=str(conf_dir()), version_base="1.3"):
        return compose("simulate", overrides=overrides)


def test_simulate_config_takes_the_physgaussian_file(tmp_path):
    means, opacities = _box_points(np.array([2.0, 1.0, 0.5]))
    _ply(tmp_path / "model.ply", means, opacities)
    (tmp_path / "jelly.json").write_text(json.dumps(JELLY))
    base = [f"input={tmp_path / 'model.ply'}", f"physgaussian_config={tmp_path / 'jelly.json'}",
            f"paths.output_dir={tmp_path / 'run'}"]  # fmt: skip
    cfg = from_hydra(_compose(base))
    assert (cfg.physics.material, cfg.physics.E, cfg.physics.nu, cfg.physics.density) == (
        "jelly",
        2e6,
        0.4,
        200.0,
    )
    assert cfg.scene == "drop" and cfg.size_m == 1.0 and cfg.up == "z"
    assert cfg.drop_height_m == pytest.approx(0.575, abs=1e-6)  # float32 PLY coordinates
    assert cfg.scene_overrides == {
        "gravity": [0.0, 0.0, -9.8],
        "ground": {"height": 0.0, "friction": 0.0, "mode": "sticky"},
    }
    assert (cfg.output.fps, cfg.output.frames) == (pytest.approx(25.0), 26)
    assert cfg.planner["min_opacity"] == 0.02 and cfg.planner["fill_interior"] is False
    assert cfg.planner["relative_opacity"] == 0.0  # the threshold as PhysGaussian applies it
    with pytest.raises(UserError, match=r"physics.E=300000.0 disagrees with .*jelly.json \(E = 2000000.0\)"):
        from_hydra(_compose([*base, "physics.E=3e5"]))
    with pytest.raises(UserError, match="cuboid"):
        (tmp_path / "jelly.json").write_text(
            json.dumps({**JELLY, "boundary_conditions": [{"type": "cuboid"}]})
        )
        from_hydra(_compose(base))
    with pytest.raises(UserError, match="goes with a 3DGS .ply input"):
        from_hydra(_compose([*base[1:], "input=examples/jelly_cube.png"]))


def test_simulate_runs_a_ply_with_its_physgaussian_config(tmp_path):
    from physgm.pipeline import run

    rng = np.random.default_rng(0)
    pts = rng.normal(size=(1500, 3))
    pts = pts / np.linalg.norm(pts, axis=1, keepdims=True) * rng.uniform(0, 1, (1500, 1)) ** (1 / 3)
    _ply(tmp_path / "blob.ply", pts * [1.0, 1.0, 0.5] + [0.3, -0.2, 2.0], np.full(1500, 0.8))
    (tmp_path / "cfg.json").write_text(json.dumps({**JELLY, "E": 2e5, "density": 1000, "frame_num": 5}))
    run(_compose([f"input={tmp_path / 'blob.ply'}", f"physgaussian_config={tmp_path / 'cfg.json'}",
                  f"paths.output_dir={tmp_path / 'run'}", "output.resolution=32", "output.progress=false"]))  # fmt: skip  # noqa: E501
    report = json.loads((tmp_path / "run" / "report.json").read_text())
    physics = json.loads((tmp_path / "run" / "physics.json").read_text())["runs"][0]
    assert (physics["material"], physics["E"], physics["nu"], physics["density"]) == ("jelly", 2e5, 0.4, 1000)
    assert report["scene_settings"]["ground"] == {"height": 0.0, "friction": 0.0, "mode": "sticky"}
    assert report["scene_settings"]["gravity"] == [0.0, 0.0, -9.8] and report["output"]["frames"] == 6
    # Half as tall as wide: the bottom is 1 - 0.25 = 0.75 m up in PhysGaussian's space, 0.45 m
    # above its collider at 0.3 (up to the sampled blob's extreme points).
    assert report["scene_settings"]["height"] == pytest.approx(0.45, abs=0.02)
