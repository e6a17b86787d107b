"""The tables of physgm's real-object sets: which files make each object, its hand label and why.

``OBJECTS`` is the evaluation set, ``GATE_OBJECTS`` the domain gate's training set (disjoint from
it), ``SETS`` names them; ``physgm.data.real_objects`` builds either. Paths are relative to the
installed package's folder (``physgm.data.asset_packages.package_root``).
"""

from __future__ import annotations

from dataclasses import dataclass

SPLIT_OF_SOURCE = {"robosuite": "val", "genesis": "val", "metaworld": "test"}
# MJCF files name meshes and textures relative to the top-level model's folder.
SEARCH_DIRS = {"robosuite": ("models/assets/objects",), "metaworld": ("assets/sawyer_xyz",)}
MW = "assets/objects/assets/"  # metaworld's object MJCF folder
RS = "models/assets/objects/"  # robosuite's
GN = "assets/meshes/"  # genesis-world's
RB = "models/assets/robots/"  # robosuite's robots
GU = "assets/urdf/"  # genesis-world's URDF models


@dataclass(frozen=True)
class RealObject:
    """One object of the set: where its geometry and colours are, and its hand label."""

    id: str
    source: str  # module of the pip package holding the files: "robosuite", "genesis" or "metaworld"
    material: str  # hand label, one of MATERIAL_NAMES
    reason: str  # why that material
    mesh: str = ""  # a mesh file in the package (OBJ with its MTL texture, GLB, or STL) ...
    xml: str = ""  # ... or an MJCF file whose body is assembled from its geoms
    deps: tuple[str, ...] = ()  # MJCF files declaring its meshes, materials and default classes;
    # for a `mesh`: the object's other mesh files, in the same frame (a model in several parts)
    body: str = ""  # MJCF body to start from (default: the file's first)
    rgba: tuple[float, float, float] | None = None  # colour of a `mesh` that has none of its own
    texture: str = ""  # box-projected texture for a `mesh` without texture coordinates
    yaw_deg: float = 0.0  # turn about +z so the object's front faces +x (view 000)
    up: str = "auto"  # the mesh file's up axis (from_meshes.up_rotation): "y", "z" or "auto"

    @property
    def split(self) -> str:
        """Its split in the evaluation set (by package); ``RealSet.split_of`` for any set."""
        return SPLIT_OF_SOURCE[self.source]


def _mw(id, material, reason, xml, deps="", **kw) -> RealObject:
    """A metaworld MJCF object; its dependencies file is ``<xml stem>_dependencies.xml`` unless named."""
    deps = deps or xml.removesuffix(".xml") + "_dependencies.xml"
    return RealObject(id, "metaworld", material, reason, xml=MW + xml, deps=(MW + deps,), **kw)


OBJECTS: tuple[RealObject, ...] = (
    # robosuite -> val
    RealObject(
        "rs_bottle",
        "robosuite",
        "glass",
        "a green glass bottle (robosuite draws it with its glass texture)",
        mesh=RS + "meshes/bottle.obj",
        texture="models/assets/textures/glass.png",
    ),
    RealObject(
        "rs_can",
        "robosuite",
        "metal",
        "an aluminium soda can with a printed label",
        mesh=RS + "meshes/can.obj",
    ),
    RealObject(
        "rs_cereal",
        "robosuite",
        "paper",
        "a printed cardboard cereal box",
        mesh=RS + "meshes/cereal.obj",
        yaw_deg=-90,
    ),
    RealObject(
        "rs_milk", "robosuite", "paper", "a milk carton: coated paperboard", mesh=RS + "meshes/milk.obj"
    ),
    RealObject(
        "rs_bread",
        "robosuite",
        "foam",
        "a bread roll: a porous solid foam that squashes and springs back, "
        "the closest of the 15 in behaviour",
        mesh=RS + "meshes/bread.obj",
    ),
    RealObject(
        "rs_round_nut",
        "robosuite",
        "metal",
        "a large steel nut (scratched-steel texture)",
        xml=RS + "round-nut.xml",
    ),
    RealObject(
        "rs_square_nut",
        "robosuite",
        "metal",
        "a large steel nut (scratched-steel texture)",
        xml=RS + "square-nut.xml",
    ),
    RealObject(
        "rs_plate_with_hole",
        "robosuite",
        "wood",
        "a flat board with a square hole, red-wood texture",
        xml=RS + "plate-with-hole.xml",
    ),
    RealObject(
        "rs_door",
        "robosuite",
        "wood",
        "a dark-wood door panel (most of the object) with a brass handle in a white frame",
        xml=RS + "door.xml",
    ),
    # genesis-world -> val: the meshes its examples drop, cut and pour
    RealObject(
        "gn_duck", "genesis", "rubber", "a yellow rubber bath duck", mesh=GN + "duck/duck.obj", up="y"
    ),
    RealObject(
        "gn_ball",
        "genesis",
        "rubber",
        "a plain black toy ball, as bouncy balls are",
        mesh="assets/tower/ball.glb",
    ),
    RealObject(
        "gn_wooden_sphere",
        "genesis",
        "wood",
        "a turned wooden sphere with visible grain",
        mesh=GN + "wooden_sphere_OBJ/wooden_sphere.obj",
    ),
    RealObject(
        "gn_chopping_board",
        "genesis",
        "wood",
        "a pale wooden chopping board with a handle slot",
        mesh=GN + "chopping-board/source/chopping_board.glb",
    ),
    RealObject(
        "gn_boat", "genesis", "wood", "a planked, red-painted rowing boat", mesh=GN + "boat/boat.obj", up="y"
    ),
    RealObject(
        "gn_water_wheel",
        "genesis",
        "wood",
        "a water wheel: wooden rim, spokes and paddles",
        mesh="assets/urdf/wheel/fancy_wheel.obj",
    ),
    RealObject(
        "gn_bathtub",
        "genesis",
        "ceramic",
        "a bathtub: glazed enamel or ceramic",
        mesh=GN + "bathtub/bathtub.obj",
        up="y",
    ),
    RealObject(
        "gn_bunny",
        "genesis",
        "ceramic",
        "the Stanford bunny, scanned from a terracotta figurine; drawn plain grey",
        mesh=GN + "bunny.obj",
    ),
    RealObject(
        "gn_dragon",
        "genesis",
        "stone",
        "a green dragon figurine, like carved jade",
        mesh=GN + "dragon/dragon.obj",
        up="y",
    ),
    RealObject(
        "gn_airplane",
        "genesis",
        "metal",
        "a light aircraft: aluminium skin",
        mesh=GN + "Airplane/airplane.obj",
        up="y",
    ),
    RealObject(
        "gn_dispenser",
        "genesis",
        "metal",
        "an ice-cream dispenser: a stainless-steel machine (untextured)",
        mesh=GN + "icecream_dispenser.obj",
        up="y",
    ),
    RealObject("gn_stirrer", "genesis", "metal", "a thin steel stirring rod", mesh=GN + "stirrer.obj"),
    # metaworld -> test
    _mw(
        "mw_mug",
        "ceramic",
        "a white coffee mug with a handle",
        "mug.xml",
        "coffeemachine_dependencies.xml",
        yaw_deg=90,
    ),
    RealObject(
        "mw_cup",
        "metaworld",
        "ceramic",
        "the coffee machine's espresso cup (a mesh no geom uses), coloured like the mug",
        mesh="assets/objects/meshes/coffeemachine/cup.stl",
        rgba=(0.85, 0.85, 0.85),
    ),
    _mw("mw_basketball", "rubber", "a basketball: orange rubber with black seams", "basketball.xml"),
    _mw(
        "mw_soccer_ball",
        "leather",
        "a black-and-white panelled football; panels are (synthetic) leather",
        "soccer_ball.xml",
        "soccer_dependencies.xml",
    ),
    _mw(
        "mw_puck",
        "rubber",
        "a black ice-hockey puck: vulcanised rubber",
        "puck.xml",
        "puck_goal_dependencies.xml",
    ),
    _mw("mw_nail", "metal", "a steel nail", "hammerblock.xml", "hammer_dependencies.xml", body="nail_link"),
    _mw(
        "mw_hammer_block",
        "wood",
        "a wooden block with a nail in it; the block is nearly all of it",
        "hammerblock.xml",
        "hammer_dependencies.xml",
        yaw_deg=90,
    ),
    _mw(
        "mw_safe",
        "metal",
        "a steel safe with a handle and a lock",
        "doorlockA.xml",
        "doorlock_dependencies.xml",
        yaw_deg=90,
    ),
    _mw(
        "mw_laptop",
        "plastic",
        "an open laptop, grey plastic shell and black screen",
        "laptop.xml",
        yaw_deg=90,
    ),
    _mw(
        "mw_shelf", "wood", "a wooden shelf unit (wood texture) with white supports", "shelf.xml", yaw_deg=90
    ),
    _mw(
        "mw_bin", "plastic", "a glossy red storage tray: moulded plastic", "binA.xml", "bin_dependencies.xml"
    ),
    _mw("mw_box", "wood", "an open box with a wood texture", "box.xml"),
    _mw("mw_faucet", "metal", "a tap: metal body and spout with a red lever", "faucet.xml"),
    _mw("mw_thermos", "metal", "a steel thermos flask with a handle", "thermos.xml", yaw_deg=90),
    _mw(
        "mw_button_box",
        "plastic",
        "a yellow-and-black stop-button box with a red push button",
        "buttonbox.xml",
        yaw_deg=90,
    ),
    _mw("mw_block", "wood", "a wooden toy cube (wood texture)", "block.xml"),
    _mw("mw_peg_block", "wood", "a wooden block with a red-lined peg hole", "peg_block.xml", yaw_deg=90),
    _mw("mw_table", "wood", "a wooden table", "table.xml"),
    _mw(
        "mw_coffee_machine",
        "plastic",
        "a coffee machine with a moulded dark-red and black plastic body",
        "coffeemachine.xml",
        yaw_deg=90,
    ),
    _mw("mw_lever", "metal", "a metal lever arm on a metal base with a blue knob", "lever.xml", yaw_deg=90),
    _mw(
        "mw_wall",
        "stone",
        "a brick wall section: fired-clay masonry, rigid, matte and rough like stone",
        "wall.xml",
        yaw_deg=90,
    ),
    _mw(
        "mw_window",
        "glass",
        "a sash window: two large panes of glass in a thin frame",
        "window.xml",
        yaw_deg=90,
    ),
)
# Left out on purpose: robosuite's lemon (no material of the 15 behaves like fruit flesh); metaworld's
# dial (its dark metal texture renders as black plastic without MuJoCo's reflections), hammer and
# golf club (half wood or plastic, half metal), drawer and stick (painted, material unreadable), the
# goals and hoop (nets and frames), and the robot itself; genesis-world's worm (soft tissue), tank (a
# plain container of unreadable material), camera (a flat dark silhouette), the cloth, terrain,
# environment sphere and the robots. Several of these train the domain gate instead (GATE_OBJECTS).

# The domain gate's training objects (``--set gate``): none is an ``OBJECTS`` row or a near-copy of
# one. The gate reads only the images; a label is still needed by the asset format, so it is a best
# guess, and painted or mixed-material objects say so.
GATE_OBJECTS: tuple[RealObject, ...] = (
    # robosuite: the lemon and handles no task uses, robot links and grippers
    RealObject(
        "rs_lemon",
        "robosuite",
        "rubber",
        "a lemon; no material of the 15 is fruit, rubber is the nearest firm elastic solid (approximate)",
        mesh=RS + "meshes/lemon.obj",
    ),
    RealObject(
        "rs_handles",
        "robosuite",
        "metal",
        "a grey box with two carrying handles, untextured; metal is a guess",
        mesh=RS + "meshes/handles.obj",
    ),
    RealObject(
        "rs_sawyer_l0",
        "robosuite",
        "metal",
        "Sawyer's shoulder link: red-painted cast aluminium",
        mesh=RB + "sawyer/obj_meshes/l0.obj",
    ),
    RealObject(
        "rs_sawyer_head",
        "robosuite",
        "plastic",
        "Sawyer's head: a display screen in a moulded housing",
        mesh=RB + "sawyer/obj_meshes/head.obj",
    ),
    RealObject(
        "rs_iiwa_link2",
        "robosuite",
        "metal",
        "a KUKA iiwa arm link: orange-painted cast aluminium",
        mesh=RB + "iiwa/meshes/link_2_vis.obj",
    ),
    RealObject(
        "rs_jaco_forearm",
        "robosuite",
        "plastic",
        "a Kinova Jaco forearm: a black carbon-fibre tube; plastic stands for the composite (approximate)",
        mesh=RB + "jaco/meshes/forearm.obj",
    ),
    RealObject(
        "rs_baxter_head",
        "robosuite",
        "plastic",
        "Baxter's head pan: black moulded plastic",
        mesh=RB + "baxter/obj_meshes/head/H0.obj",
    ),
    RealObject(
        "rs_panda_link7",
        "robosuite",
        "metal",
        "a Franka Panda flange link: grey aluminium",
        xml=RB + "panda/robot.xml",
        body="link7",
    ),
    RealObject(
        "rs_ur5e_wrist3",
        "robosuite",
        "metal",
        "a UR5e wrist link: aluminium",
        xml=RB + "ur5e/robot.xml",
        body="wrist_3_link",
    ),
    RealObject(
        "rs_panda_gripper",
        "robosuite",
        "plastic",
        "a Franka hand: plastic housing with two metal fingers (approximate)",
        xml="models/assets/grippers/panda_gripper.xml",
        yaw_deg=90,
    ),
    RealObject(
        "rs_rethink_gripper",
        "robosuite",
        "metal",
        "Rethink's electric parallel gripper: metal body and fingers, red trim",
        xml="models/assets/grippers/rethink_gripper.xml",
    ),
    RealObject(
        "rs_robotiq_gripper",
        "robosuite",
        "metal",
        "a Robotiq 2F-140 gripper: black anodised body, aluminium fingers",
        xml="models/assets/grippers/robotiq_gripper_140.xml",
        yaw_deg=90,
    ),
    # genesis-world: props of its examples, a PartNet bottle, a drone and a robot link
    RealObject(
        "gn_worm",
        "genesis",
        "rubber",
        "a worm: soft tissue; rubber stands for its soft, elastic body (approximate)",
        mesh=GN + "worm/worm.obj",
        # its OBJ names a material its MTL does not define, so the skin is laid on by projection
        texture=GN + "worm/bdy_Base_Color.png",
        up="y",
    ),
    RealObject(
        "gn_tank",
        "genesis",
        "plastic",
        "a rounded open tank, untextured; plastic is a guess",
        mesh=GN + "tank.obj",
        up="y",
    ),
    RealObject(
        "gn_camera",
        "genesis",
        "plastic",
        "a film camera with two reels, drawn near-black; plastic is a guess",
        mesh=GN + "camera/camera.glb",
    ),
    RealObject(
        "gn_bolt",
        "genesis",
        "metal",
        "a threaded hex bolt",
        mesh=GN + "bolt_nut/bolt.stl",
        rgba=(0.6, 0.6, 0.6),
    ),
    RealObject(
        "gn_nut", "genesis", "metal", "a threaded hex nut", mesh=GN + "bolt_nut/nut.stl", rgba=(0.6, 0.6, 0.6)
    ),
    RealObject(
        "gn_bottle",
        "genesis",
        "glass",
        "an amber glass bottle with a black cap (PartNet-Mobility 3763: body, neck and cap)",
        mesh=GU + "3763/textured_objs/original-3.obj",
        deps=(GU + "3763/textured_objs/original-1.obj", GU + "3763/textured_objs/original-2.obj"),
        up="y",
    ),
    RealObject(
        "gn_blue_box",
        "genesis",
        "plastic",
        "a blue open box modelled in CAD, in its URDF colour; plastic is a guess",
        mesh=GU + "blue_box/assets/part_1.stl",
        rgba=(0.0, 0.0, 1.0),
    ),
    RealObject(
        "gn_drone",
        "genesis",
        "plastic",
        "a Crazyflie quadcopter: circuit board, motors and plastic arms (approximate)",
        mesh=GU + "drones/body.obj",
    ),
    RealObject(
        "gn_trash_bag",
        "genesis",
        "plastic",
        "a thin plastic bin bag with a yellow drawstring rim",
        mesh=GN + "trashbag_rope.glb",
    ),
    RealObject(
        "gn_panda_link1",
        "genesis",
        "metal",
        "a Franka Panda arm link: white-painted cast aluminium",
        mesh=GU + "panda_bullet/meshes/visual/link1.obj",
    ),
    # metaworld: the task objects the evaluation set leaves out
    _mw("mw_assembly_peg", "metal", "a steel ring on a green grip, like a ring spanner", "assembly_peg.xml"),
    _mw(
        "mw_basketball_hoop",
        "metal",
        "a hoop on a steel pole with a white backboard (approximate: the board is plastic)",
        "basketballhoop.xml",
        "basketball_dependencies.xml",
        yaw_deg=90,
    ),
    _mw(
        "mw_golf_club",
        "metal",
        "a golf club: steel head, drawn with a wood-textured grip (approximate)",
        "club.xml",
        yaw_deg=90,
    ),
    _mw(
        "mw_dial",
        "metal",
        "a dial knob on a round base; the file calls it metal, it renders dark",
        "dial.xml",
        yaw_deg=90,
    ),
    _mw(
        "mw_drawer",
        "wood",
        "a painted chest with a drawer and a metal handle; the paint hides the material (a guess)",
        "drawer.xml",
        yaw_deg=90,
    ),
    _mw("mw_hammer", "metal", "a hammer: steel head on a red handle", "hammer.xml", yaw_deg=90),
    _mw(
        "mw_handle_press",
        "metal",
        "a press: a dark metal housing with a lever and a red grip",
        "handle_press.xml",
        yaw_deg=90,
    ),
    _mw("mw_plug", "plastic", "a mains plug: moulded black plastic with brass pins", "plug.xml", yaw_deg=90),
    _mw("mw_plug_wall", "plastic", "a wall socket: a plastic face plate on a grey block", "plug_wall.xml"),
    _mw(
        "mw_hockey_goal",
        "metal",
        "an ice-hockey goal: red frame, white net (approximate: the net is fabric)",
        "puck_goal.xml",
        yaw_deg=90,
    ),
    _mw(
        "mw_soccer_goal",
        "metal",
        "a football goal: white frame, blue net (approximate: the net is fabric)",
        "soccer_goal.xml",
        "soccer_dependencies.xml",
        yaw_deg=90,
    ),
)
# Left out of the gate set. Near-copies of evaluation objects: metaworld's binB (~ binA), doorlockB
# (~ doorlockA), shelfb (~ shelf), window_horiz (~ window), table_hole (~ table), boxtop (~ box) and
# the robot (xyz_base: Sawyer, whose links robosuite's rows cover); genesis-world's duck.obj and
# dragon.obj (other files of the duck and the dragon), urdf/wheel/wheel.obj (the water wheel's
# 44-triangle stand-in), the tower's rings and pole (the toy generate_tower.py makes with the
# evaluation set's black ball), and its KUKA and Franka models (robosuite's rows hold those arms).
# Single primitives, which the synthetic shape families already draw: metaworld's objA (a cube),
# block_cyl (a cylinder) and stick (a box); genesis-world's cross_cutter (a 44-triangle flat blade,
# invisible edge-on). Files that do not load: robosuite's robotiq_gripper_85.xml (names _vis STL
# files the package lacks); genesis-world's ANYmal C, Go2, drone cf2.dae and KUKA base (COLLADA,
# which trimesh reads only with pycollada, not installed); metaworld's peg_insert (no visible geom).


@dataclass(frozen=True)
class RealSet:
    """A table of objects and the split each goes to."""

    objects: tuple[RealObject, ...]
    split: str = ""  # every object's split; "" = each object's own (RealObject.split, by package)

    def split_of(self, obj: RealObject) -> str:
        return self.split or obj.split


SETS = {"eval": RealSet(OBJECTS), "gate": RealSet(GATE_OBJECTS, split="train")}
