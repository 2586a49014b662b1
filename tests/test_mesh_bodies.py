"""Mesh bodies (issue 14): a body from an .obj or .stl file or from inline vertices, added while the world
runs or written in a scenario, on both cores (each simulates its convex hull); part of history (a
backtick across the add is bit-exact); a file that is missing or does not parse is refused naming the
call and the field, the world left as it was."""

from __future__ import annotations

import itertools
import struct
import textwrap

import numpy as np
import pytest

from dynabrain.modules.exudyn import geometry as geo
from dynabrain.modules.exudyn.core import ExudynCore
from dynabrain.modules.mujoco.core import MujocoCore
from dynabrain.orchestrator import load_world
from dynabrain.orchestrator.kernel.core import BodySpec, JointSpec, SceneSpec
from dynabrain.orchestrator.kernel.errors import DynabrainError, ScenarioError
from dynabrain.orchestrator.kernel.meshes import Mesh, convex_hull, mass_properties, read_mesh
from dynabrain.orchestrator.kernel.specs import BodySpecError
from dynabrain.orchestrator.kernel.world import World

CORES = {"mujoco": MujocoCore, "exudyn": ExudynCore}
ENGINES = pytest.mark.parametrize("engine", list(CORES))

CUBE = [list(c) for c in itertools.product((-0.05, 0.05), repeat=3)]
"""A 10 cm cube's corners, about its centre."""
TETRA_OBJ = """# a right-angled tetrahedron, its corner at the origin
v 0 0 0
v 0.1 0 0
v 0 0.1 0
v 0 0 0.1
f 1 3 2
f 1 2 4
f 1 4 3
f 2 3 4
"""


def world_of(engine: str) -> World:
    scene = SceneSpec(bodies=(BodySpec("floor", "plane", ()),))
    return World("meshes", step="2ms", history=400, core=CORES[engine]("core", scene))


def state(world: World) -> tuple:
    """The world's whole state, comparable bit for bit."""
    snap = world.snapshot()
    return snap.tick, snap.bus.tobytes(), repr(snap.states), tuple(world.signals)


def write_binary_stl(path, vertices, faces) -> None:
    data = bytearray(b"\0" * 80 + struct.pack("<I", len(faces)))
    for f in faces:
        data += struct.pack("<3f", 0, 0, 0) + b"".join(struct.pack("<3f", *vertices[i]) for i in f) + b"\0\0"
    path.write_bytes(bytes(data))


@ENGINES
def test_a_mesh_from_a_file_and_one_from_vertices_fall_rest_on_their_hull_and_backtick_bit_exact(engine, tmp_path):
    obj = tmp_path / "tetra.obj"
    obj.write_text(TETRA_OBJ)
    world = world_of(engine)
    world.tick(9)
    before = state(world)
    world.tick(1)
    world.add_body(name="cube", shape="mesh", mesh={"vertices": CUBE}, pos=[0, 0, "150mm"], mass="200g",
                   color="blue", friction=0.6, restitution=0.1)
    world.add_body(name="tetra", shape="mesh", mesh=str(obj), scale=2, pos=[0.4, 0, 0.1], mass=0.1)
    assert world.core.body_info("cube").geoms[0]["type"] == "mesh"
    assert world.core.material("cube").friction == 0.6
    world.tick(250)
    # the cube rests on a face (its centre 5 cm up); the tetrahedron on its base (its corner, the body
    # frame's origin, at the floor), both upright: the hull's contacts and mass
    assert abs(world.get("cube.pos")[2] - 0.05) < 2e-3, world.get("cube.pos")
    assert abs(world.get("tetra.pos")[2]) < 2e-3, world.get("tetra.pos")
    for body in ("cube", "tetra"):
        assert abs(abs(world.get(f"{body}.quat")[0]) - 1) < 1e-3, (body, world.get(f"{body}.quat"))
    after = state(world)
    world.backtick(100)
    world.tick(100)
    assert state(world) == after  # the same future, bit for bit
    world.backtick(251)
    assert "cube" not in world.core.bodies() and state(world) == before
    world.close()


def test_obj_and_stl_files_read_the_same_mesh_and_its_hull_has_a_cubes_mass(tmp_path):
    faces = [(0, 1, 3), (0, 3, 2), (4, 6, 7), (4, 7, 5), (0, 4, 5), (0, 5, 1), (2, 3, 7), (2, 7, 6),
             (0, 2, 6), (0, 6, 4), (1, 5, 7), (1, 7, 3)]
    write_binary_stl(tmp_path / "cube.stl", CUBE, faces)
    (tmp_path / "cube.obj").write_text("".join(f"v {x} {y} {z}\n" for x, y, z in CUBE)
                                       + "".join(f"f {a + 1} {b + 1} {c + 1}\n" for a, b, c in faces))
    (tmp_path / "ascii.stl").write_text("solid c\n" + "".join(
        "facet normal 0 0 0\nouter loop\n" + "".join(f"vertex {x} {y} {z}\n" for x, y, z in (CUBE[i] for i in f))
        + "endloop\nendfacet\n" for f in faces) + "endsolid c\n")
    meshes = [read_mesh(tmp_path / name) for name in ("cube.obj", "cube.stl", "ascii.stl")]
    hulls = [convex_hull(m, (1.0, 1.0, 1.0)) for m in meshes]
    for points, tris in hulls:
        assert len(points) == 8 and len(tris) == 12
        volume, centre, inertia = mass_properties(points, tris)
        assert volume == pytest.approx(1e-3, rel=1e-6) and np.allclose(centre, 0, atol=1e-7)
        assert np.allclose(inertia / volume, np.eye(3) * 0.1 ** 2 / 6, rtol=1e-5)  # a box's: m (b^2 + c^2) / 12
    spec = BodySpec("c", "mesh", mesh=str(tmp_path / "cube.stl"), scale=[2, 1, 1], mass=3)
    m, inertia, centre = geo.body_mass(spec)
    assert m == 3 and np.allclose(np.diag(inertia), [3 * 0.02 / 12, 3 * 0.05 / 12, 3 * 0.05 / 12], rtol=1e-5)


@ENGINES
def test_a_bad_mesh_is_refused_naming_add_body_and_the_field_and_changes_nothing(engine, tmp_path):
    (tmp_path / "broken.obj").write_text("v 0 0 zero\n")
    (tmp_path / "flat.obj").write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nv 1 1 0\nf 1 2 3\n")
    world = world_of(engine)
    world.tick(3)
    before = state(world)
    bad = [({"mesh": str(tmp_path / "missing.obj")}, "mesh", "not found"),
           ({"mesh": str(tmp_path / "broken.obj")}, "mesh", "cannot be read"),
           ({"mesh": str(tmp_path / "flat.obj")}, "mesh", "span a volume"),
           ({"mesh": str(tmp_path / "part.ply")}, "mesh", ".obj or .stl"),
           ({"mesh": {"vertices": CUBE, "faces": [[0, 1, 8]]}}, "mesh", "vertex 8"),
           ({"mesh": {"vertices": CUBE}, "scale": [1, -1, 1]}, "scale", "positive"),
           ({"mesh": {"vertices": CUBE}, "size": [0.1]}, "size", "from its vertices"),
           ({}, "mesh", "needs mesh")]
    for fields, field, words in bad:
        with pytest.raises(BodySpecError) as err:
            world.add_body(name="m", shape="mesh", pos=[0, 0, 0.2], **fields)
        assert err.value.field == field and str(err.value).startswith("add_body(): body 'm'"), str(err.value)
        assert words in str(err.value), str(err.value)
    with pytest.raises(BodySpecError, match="field mesh: only a mesh body takes a mesh"):
        world.add_body(name="b", shape="box", size=[0.1] * 3, mesh={"vertices": CUBE})
    assert state(world) == before
    world.tick(1)
    world.close()


@ENGINES
def test_a_scenario_writes_mesh_bodies_in_its_scene_and_adds_one_by_an_event(engine, tmp_path):
    (tmp_path / "parts").mkdir()
    (tmp_path / "parts" / "tetra.obj").write_text(TETRA_OBJ)
    (tmp_path / "mesh.yaml").write_text(textwrap.dedent(f"""\
        name: meshes
        world: {{step: 2ms, core: {engine}, duration: 0.4s}}
        scene:
          - plane: {{name: floor}}
          - mesh: {{name: tetra, mesh: parts/tetra.obj, scale: 1.5, pos: [0, 0, 0.05], mass: 100g, color: green}}
        events:
          - {{at: 0.1s, add_body: {{mesh: {{name: cube, mesh: {{vertices: {CUBE}}}, pos: [0.4, 0, 0.2]}}}}}}
        expect:
          - {{at: 0.4s, that: "abs(cube.pos[2] - 0.05) < 0.003 and abs(tetra.pos[2]) < 0.003"}}
        """))
    world = load_world(tmp_path / "mesh.yaml")
    world.tick(200)
    assert abs(world.get("cube.pos")[2] - 0.05) < 3e-3 and abs(world.get("tetra.pos")[2]) < 3e-3
    world.close()
    (tmp_path / "bad.yaml").write_text(textwrap.dedent(f"""\
        name: bad
        world: {{step: 2ms, core: {engine}}}
        scene:
          - mesh: {{name: a, mesh: parts/none.obj}}
          - box: {{name: b, size: [0.1, 0.1, 0.1], scale: 2}}
        """))
    with pytest.raises(ScenarioError) as err:
        load_world(tmp_path / "bad.yaml")
    text = str(err.value)
    assert "bad.yaml:4" in text and "none.obj" in text and "not found" in text, text
    assert "bad.yaml:5" in text and "only a mesh takes 'scale'" in text, text


def test_a_mesh_spec_keeps_numbers_not_the_file(tmp_path):
    obj = tmp_path / "tetra.obj"
    obj.write_text(TETRA_OBJ)
    spec = BodySpec("t", "mesh", mesh=obj)
    obj.unlink()  # read once, when the spec is made
    assert isinstance(spec.mesh, Mesh) and len(spec.mesh.vertices) == 4 and len(spec.mesh.faces) == 4
    assert spec.scale == (1.0, 1.0, 1.0) and spec.size == ()
    assert BodySpec("t", "mesh", mesh=spec.mesh.plain()) == spec
    world = world_of("mujoco")
    with pytest.raises(DynabrainError, match="add_body"):
        world.add_body(name="t", shape="mesh", mesh=str(obj))
    world.close()


@ENGINES
def test_a_mesh_bar_on_a_hinge_swings_as_the_box_it_is(engine):
    """Mass, centre of mass (away from the body's origin, at the hinge) and inertia come from the hull."""
    bar = [[x, y, z] for x in (0, 0.3) for y in (-0.02, 0.02) for z in (-0.02, 0.02)]
    hinge = {"kind": "hinge", "name": "h", "axis": (0.0, 1.0, 0.0)}
    arms = [BodySpec("arm", "mesh", mesh={"vertices": bar}, pos=(0, 0, 1), mass=0.5, joint=JointSpec(**hinge)),
            BodySpec("arm", "box", (0.3, 0.04, 0.04), pos=(0.15, 0, 1), mass=0.5,
                     joint=JointSpec(**hinge, anchor=(-0.15, 0.0, 0.0)))]
    swings = []
    for arm in arms:
        world = World("swing", step="2ms", history=10, core=CORES[engine]("core", SceneSpec(bodies=(arm,))))
        world.tick(100)
        swings.append(world.get("core.h.q"))
        world.close()
    assert swings[0] > 0.5 and swings[0] == pytest.approx(swings[1], abs=1e-6), swings
