"""The body-tree walks the guard, the emulator, the planner and the cell check share."""

from twinrl_sim.body_tree import ancestors, subtree
from twinrl_sim.build import compile_scene
from twinrl_sim.layout import MOUNT_BODY
from twinrl_sim.tasks import make_task


def test_the_robot_holds_its_links_and_tool_and_the_flange_hangs_from_the_mount():
    cell = compile_scene(make_task("pick_place").scene)
    model, layout = cell.model, cell.layout
    mount, flange = model.body(MOUNT_BODY).id, model.body(layout.flange_body).id
    table = model.body(layout.table_body).id
    robot = subtree(model, mount)
    tool = subtree(model, flange)
    assert mount in robot and flange in robot and tool <= robot
    assert table not in robot and 0 not in robot
    assert model.geom(layout.table_geom).bodyid[0] not in tool
    chain = ancestors(model, flange)
    assert {mount, flange} <= chain and 0 not in chain and table not in chain
    # Every body on the chain is above the flange: the robot's subtree of each holds it.
    assert all(flange in subtree(model, body) for body in chain)
    assert ancestors(model, mount) & tool == set()
