"""The paper's §6 simulation as ROS 2 messages (for the tests, the docs' example and demos).

:func:`sim_messages` turns a :class:`mcsm_client.scenario.Scenario` into the messages a robot
front end would publish to ``mcsm ros2``: iteration k's odometry as the relative pose
``x{k} -> x{k+1}`` on the constraint topic and each sighting as the landmark ``l{j}`` seen from
``x{k+1}`` on the landmark topic, all stamped ``(k + 1) * period``. The odometry's ``(dx, dy,
dθ)`` covariance becomes the ROS 6x6 (x, y and rotation about Z; yaw only, so the same in
ROS's and mcsm's charts); a sighting's ``(x, y)`` covariance the translation block (z exact).
:func:`build` makes one message with any message library (``mcsm.viz.rosmsg``'s ``make``).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import mcsm.viz.rosmsg as rosmsg
import numpy as np
import numpy.typing as npt

from mcsm_client.sampling import pose_from_planar
from mcsm_client.scenario import Scenario, landmark_frame, pose_frame

Array = npt.NDArray[np.float64]

CONSTRAINT_TOPIC = "/mcsm/constraints"
LANDMARK_TOPIC = "/mcsm/landmarks"

__all__ = ["SimMessage", "build", "sim_messages"]


@dataclass(frozen=True)
class SimMessage:
    """One ``nav_msgs/Odometry`` to publish: topic, stamp, frames, pose and ROS covariance."""

    topic: str
    stamp_ns: int
    frame_id: str
    child_frame_id: str
    mean: Array = field(repr=False)  # mcsm 7-vector
    cov: Array = field(repr=False)  # ROS 6x6


def sim_messages(scenario: Scenario, n_iterations: int | None = None,
                 period_ns: int = 100_000_000) -> list[SimMessage]:
    """The scenario's readings (up to ``n_iterations``) as messages, in publishing order."""
    t_end = scenario.n_iterations if n_iterations is None else min(n_iterations,
                                                                   scenario.n_iterations)
    odo6 = np.zeros((6, 6))
    idx = np.array([0, 1, 5])
    odo6[np.ix_(idx, idx)] = scenario.config.odometry_cov
    laser6 = np.zeros((6, 6))
    laser6[:2, :2] = scenario.config.laser_cov
    out = []
    for k in range(t_end):
        t = (k + 1) * period_ns
        out.append(SimMessage(CONSTRAINT_TOPIC, t, pose_frame(k), pose_frame(k + 1),
                              pose_from_planar(scenario.odometry[k]), odo6))
        for j, (x, y) in scenario.observations[k]:
            out.append(SimMessage(LANDMARK_TOPIC, t, pose_frame(k + 1), landmark_frame(j),
                                  np.array([x, y, 0.0, 1.0, 0.0, 0.0, 0.0]), laser6))
    return out


def build(make: rosmsg.Make, m: SimMessage) -> Any:
    """The ``nav_msgs/Odometry`` of one :class:`SimMessage`."""
    return rosmsg.odometry(make, m.stamp_ns, m.frame_id, m.child_frame_id, m.mean, m.cov)
