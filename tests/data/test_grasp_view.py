"""The grasp in the view comes from what the episode logs: the object in hand where the
fingers closed on it, none where they closed on nothing or far from every object, and
the TCP's force as an arrow where a cell measures it; read back with Rerun's reader."""

import numpy as np
import pytest
from rerun.experimental import RrdReader

from tests.data.conftest import STATE_NAMES, make_meta
from twinrl_data import schema
from twinrl_data.grasp_view import ARROW_M_PER_N, held_objects
from twinrl_data.view import save_rrd

OPENING = STATE_NAMES.index("gripper.opening")
TCP = slice(STATE_NAMES.index("tcp.x"), STATE_NAMES.index("tcp.z") + 1)
STEPS = 12


def _grasp(openings: list[float], cube_at=(0.4, -0.2, 0.02), wrench=False) -> schema.Episode:
    """The TCP at the cube from step 0, closed from step 3 on, the fingers at
    ``openings`` (m); the cube rides the TCP up from step 8."""
    tcp = np.tile([0.4, -0.2, 0.02], (STEPS, 1))
    tcp[8:, 2] += 0.02 * np.arange(1, STEPS - 7)
    state = np.zeros((STEPS, len(STATE_NAMES)), np.float32)
    state[:, TCP], state[:, OPENING], state[:, 15] = tcp, openings, 1.0
    cube = np.tile([*cube_at, 1, 0, 0, 0], (STEPS, 1)).astype(np.float32)
    if np.allclose(cube_at, tcp[0]):
        cube[8:, :3] = tcp[8:]
    action = np.zeros((STEPS, 7), np.float32)
    action[3:, 6] = 1.0
    data = {
        schema.STATE: state,
        schema.ENVIRONMENT_STATE: cube,
        schema.ACTION: action,
        schema.JOINT_TARGET: np.zeros((STEPS, 6), np.float32),
        schema.REWARD: np.zeros(STEPS, np.float32),
        schema.DONE: np.arange(STEPS) == STEPS - 1,
        schema.SUCCESS: np.zeros(STEPS, bool),
        schema.INTERVENTION: np.zeros(STEPS, bool),
    }
    meta = make_meta()
    if wrench:
        data[schema.WRENCH] = np.tile([0, 0, -20.0, 0, 0, 0], (STEPS, 1)).astype(np.float32)
        meta.names[schema.WRENCH] = list(schema.WRENCH_NAMES)
    return schema.Episode(meta, data)


ON_THE_CUBE = [0.08] * 4 + [0.06, 0.04] + [0.03] * 6  # stopped on it from step 7
ON_NOTHING = [0.08] * 4 + [0.05, 0.02] + [0.0] * 6


@pytest.mark.parametrize(
    ("openings", "cube_at", "held"),
    [
        (ON_THE_CUBE, (0.4, -0.2, 0.02), list(range(7, STEPS))),
        (ON_NOTHING, (0.4, -0.2, 0.02), []),  # closed on nothing
        (ON_THE_CUBE, (0.6, -0.2, 0.02), []),  # on something, but not the cube
    ],
)
def test_an_object_is_in_hand_where_the_fingers_stopped_on_it(openings, cube_at, held):
    np.testing.assert_array_equal(
        np.flatnonzero(held_objects(_grasp(openings, cube_at))["cube"]), held
    )


def test_the_view_marks_the_held_object_and_draws_the_tcp_force(tmp_path):
    chunks = {}
    path = save_rrd([_grasp(ON_THE_CUBE, wrench=True)], tmp_path / "grasp.rrd")
    for chunk in RrdReader(path).store().stream().to_chunks():
        chunks.setdefault(chunk.entity_path, []).append(chunk.to_record_batch())
    (marker,) = chunks["/world/twin_twin_demo/objects/cube/in_hand"]
    shown = [len(p or []) for p in marker.column("Points3D:positions").to_pylist()]
    assert shown == [0] * 7 + [1] * 5  # marked from the step the fingers stopped on it
    assert set(marker.column("Points3D:labels").to_pylist()[-1]) == {"in hand"}
    (force,) = chunks["/world/twin_twin_demo/tcp_force"]
    vectors = np.array([v[0] for v in force.column("Arrows3D:vectors").to_pylist()])
    np.testing.assert_allclose(vectors, np.tile([0, 0, -20 * ARROW_M_PER_N], (STEPS, 1)))
    origins = np.array([v[0] for v in force.column("Arrows3D:origins").to_pylist()])
    np.testing.assert_allclose(origins[-1], [0.4, -0.2, 0.02 + 0.02 * 4], atol=1e-6)
    assert "/signals/force/z/twin_twin_demo" in chunks
    assert "/signals/grasp/opening/twin_twin_demo" in chunks
