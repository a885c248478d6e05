"""Pictures in a scene spec: the table's top, an object's look, the backdrop, each shown
where the spec says (rendered and read back), and bad ones refused in one line."""

from __future__ import annotations

from pathlib import Path

import mujoco
import numpy as np
import pytest
from PIL import Image

from twinrl_sim.build import UNSEEN_GROUP, compile_scene
from twinrl_sim.cubemap import cube_directions, cube_lookup
from twinrl_sim.errors import TwinError
from twinrl_sim.spec import SpecError, load_spec, parse_spec, resolve_files

RED, GREEN, BLUE = (230, 30, 30), (30, 230, 30), (30, 30, 230)


def _render(model: mujoco.MjModel, lookat, distance, azimuth, elevation, size=101):
    data = mujoco.MjData(model)
    mujoco.mj_forward(model, data)
    camera = mujoco.MjvCamera()
    camera.lookat[:] = lookat
    camera.distance, camera.azimuth, camera.elevation = distance, azimuth, elevation
    with mujoco.Renderer(model, size, size) as renderer:
        renderer.update_scene(data, camera)
        return renderer.render()


def _dominant(pixel: np.ndarray) -> int:
    return int(np.argmax(pixel))


def test_cube_lookup_finds_each_texel_of_its_own_directions():
    size = 6
    cube = np.arange(6 * size * size).reshape(6 * size, size, 1)
    found = cube_lookup(cube, cube_directions(size)).ravel()
    assert np.array_equal(found, np.arange(6 * size * size))


def test_the_tables_picture_lies_with_its_columns_along_x_and_first_row_at_plus_y(tmp_path):
    picture = np.zeros((40, 80, 3), np.uint8)
    picture[:, 40:] = RED  # the +x half
    picture[:20, :40] = GREEN  # the -x, +y quarter
    picture[20:, :40] = BLUE  # the -x, -y quarter
    Image.fromarray(picture).save(tmp_path / "top.png")
    table = {"image": "top.png", "size": [0.8, 0.4], "center": [0.5, 0.0], "yaw": 0.3}
    spec = resolve_files(parse_spec({"name": "t", "table": table}), tmp_path)
    model = compile_scene(spec).model
    image = _render(model, [0.5, 0.0, 0.0], 1.2, 90.0, -90.0)  # from above: +y up, +x right
    yaw = 0.3
    for local, colour in (((0.25, 0.0), 0), ((-0.25, 0.12), 1), ((-0.25, -0.12), 2)):
        world = np.array([0.5, 0.0]) + [
            np.cos(yaw) * local[0] - np.sin(yaw) * local[1],
            np.sin(yaw) * local[0] + np.cos(yaw) * local[1],
        ]
        pixel_size = 2 * 1.2 * np.tan(np.radians(45 / 2)) / 101
        column = round(50 + (world[0] - 0.5) / pixel_size)
        row = round(50 - world[1] / pixel_size)
        assert _dominant(image[row, column]) == colour, (local, image[row, column])


def test_the_backdrop_shows_each_face_where_it_looks(tmp_path):
    size = 16
    directions = cube_directions(size)
    backdrop = np.zeros((6, size, size, 3), np.uint8)
    for axis in range(3):  # each axis's + face in its colour, - faces dark
        backdrop[2 * axis, ..., axis] = 230
    backdrop[directions[..., 2] > 0.9] = (230, 230, 230)  # straight up is white
    Image.fromarray(backdrop.reshape(6 * size, size, 3)).save(tmp_path / "room.png")
    spec = resolve_files(parse_spec({"name": "t", "backdrop": "room.png"}), tmp_path)
    model = compile_scene(spec).model
    high = [0.5, 0.0, 1.5]  # above the arm: only the backdrop in view
    assert _dominant(_render(model, high, 0.01, 0.0, 0.0)[50, 50]) == 0  # looking +x: red
    assert _dominant(_render(model, high, 0.01, 90.0, 0.0)[50, 50]) == 1  # +y: green
    assert _render(model, high, 0.01, 0.0, 89.0)[50, 50].min() > 200  # up: white
    floor = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_GEOM, "floor")
    assert model.geom_group[floor] == UNSEEN_GROUP  # the backdrop shows the floor


CUBE_FACES = (
    (1, 3, 4), (1, 4, 2), (5, 6, 8), (5, 8, 7), (1, 2, 6), (1, 6, 5),
    (3, 7, 8), (3, 8, 4), (1, 5, 7), (1, 7, 3), (2, 4, 8), (2, 8, 6),
)  # fmt: skip


def test_an_objects_look_is_worn_by_its_surface_and_its_parts_collide_unseen(tmp_path):
    corners = [(x, y, z) for x in (-0.03, 0.03) for y in (-0.03, 0.03) for z in (-0.03, 0.03)]
    lines = [f"v {x} {y} {z}" for x, y, z in corners]
    lines += [f"vt {u} {v}" for u in (0, 1) for v in (0, 1)]
    lines += [f"f {a}/1 {b}/2 {c}/4" for a, b, c in CUBE_FACES]
    (tmp_path / "cube.obj").write_text("\n".join(lines) + "\n")
    Image.fromarray(np.full((8, 8, 3), GREEN, np.uint8)).save(tmp_path / "look.png")
    block = {
        "name": "block",
        "role": "manipulated",
        "mass": 0.1,
        "pos": [0.5, 0.0, 0.03],
        "rgba": [0.9, 0.1, 0.1, 1.0],
        "look": "look.png",
        "geoms": [
            {"type": "box", "size": [0.03, 0.03, 0.03]},
            {"type": "mesh", "file": "cube.obj", "contact": False},
        ],
    }
    spec = resolve_files(parse_spec({"name": "t", "objects": [block]}), tmp_path)
    model = compile_scene(spec).model
    part = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_GEOM, "block_geom0")
    surface = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_GEOM, "block_geom1")
    assert model.geom_group[part] == UNSEEN_GROUP and model.geom_contype[part] != 0
    assert model.geom_matid[surface] >= 0
    top = _render(model, [0.5, 0.0, 0.03], 0.5, 90.0, -90.0)[50, 50]
    assert _dominant(top) == 1  # the green look, not the red colour


def test_bad_pictures_are_refused_in_one_line(tmp_path):
    with pytest.raises(TwinError, match="no 'contact: false' mesh"):
        parse_spec(
            {
                "name": "t",
                "objects": [
                    {
                        "name": "a",
                        "role": "target",
                        "look": "a.png",
                        "geoms": [{"type": "box", "size": [0.02, 0.02, 0.02]}],
                    }
                ],
            }
        )
    spec_path = tmp_path / "scene.yaml"
    spec_path.write_text("name: t\ntable:\n  image: missing.png\n")
    with pytest.raises(SpecError, match=r"table.image: .*missing.png does not exist"):
        load_spec(spec_path)
    Image.fromarray(np.zeros((10, 10, 3), np.uint8)).save(tmp_path / "square.png")
    spec = resolve_files(parse_spec({"name": "t", "backdrop": "square.png"}), Path(tmp_path))
    with pytest.raises(SpecError, match="six square faces"):
        compile_scene(spec)
