"""What the robot touches, in the Rerun view: the twin's contacts of each logged step.

No cell measures contacts, so they come from the cell's model
(:meth:`twinrl_data.view.CellModel.contacts`: the twin's collision geometry posed by the
logged joints, gripper opening and object poses). Each step's contacts are points in 3D
under ``world/<label>/contacts``, labelled with the two bodies (a finger on the banana, a
link on the table), and each pair that ever touches has a plot under
``signals/contacts/<label>``, 1 while it does. A finger that lands on an object's top
before the close, or the arm grazing the table, shows where it happens.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import rerun as rr

from twinrl_data.timeline import step_times


@dataclass(frozen=True)
class Contact:
    """Where one of the robot's bodies touches another body at one step."""

    position: np.ndarray  # xyz, base frame
    robot: str  # the robot's body (a link, a finger)
    other: str  # the body it touches (an object, the table)
    distance: float  # m between the surfaces (negative: they overlap)

    @property
    def label(self) -> str:
        """The two bodies, as the view names the contact: ``robot / other``."""
        return f"{self.robot} / {self.other}"


CONTACT_COLOR = [255, 40, 120]
CONTACT_RADIUS = 0.006  # m


def log_contacts(
    steps: list[list[Contact]], fps: float, label: str, recording: rr.RecordingStream
) -> bool:
    """Log the robot's contacts at every step (``steps``: each step's, from the cell's
    model; see the module docstring); whether any step had one."""
    if not any(steps):
        return False
    times = step_times(len(steps), fps)
    positions = [c.position for step in steps for c in step]
    names = [c.label for step in steps for c in step]
    rr.send_columns(
        f"world/{label}/contacts",
        indexes=times,
        columns=rr.Points3D.columns(
            positions=np.array(positions),
            labels=names,
            radii=np.full(len(positions), CONTACT_RADIUS),
            colors=np.tile(CONTACT_COLOR, (len(positions), 1)),
        ).partition([len(step) for step in steps]),
        recording=recording,
    )
    pairs = [{c.label for c in step} for step in steps]
    for pair in sorted(set(names)):
        path = f"signals/contacts/{label}/{pair.replace(' / ', '-')}"
        rr.log(path, rr.SeriesLines(names=pair), static=True, recording=recording)
        touching = [float(pair in step) for step in pairs]
        rr.send_columns(
            path, indexes=times, columns=rr.Scalars.columns(scalars=touching), recording=recording
        )
    return True
