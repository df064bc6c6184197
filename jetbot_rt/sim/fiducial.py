"""A printed fiducial marker in the simulated room, for ``jetbot-rt calibrate --backend sim``.

The page (``jetbot_rt/data/aruco-4x4-id7.png``: the marker and one white cell around it) is
a textured vertical quad, standing on the floor in front of the robot and facing it, as a
sheet of paper taped to a box is on a desk. Only the calibration places it: the tasks' scenes
never have it, and ``JetbotWorld.reset`` (a rebuilt scene) removes it.
"""

from __future__ import annotations

import math
from pathlib import Path

from jetbot_rt.sim.backend import SimRobot
from jetbot_rt.sim.pybullet_import import import_pybullet

p = import_pybullet()

PAGE_CELLS = 8
"""The PNG's width in marker cells: 6 for the marker (its black border included), 2 white."""
MARKER_CELLS = 6
PAGE_PNG = Path(__file__).resolve().parents[1] / "data" / "aruco-4x4-id7.png"


def place_marker(robot: SimRobot, distance: float, marker_size: float,
                 centre_height: float) -> None:
    """Stand the page ``distance`` m ahead of the robot's axle, on its heading, its marker's
    black square ``marker_size`` m wide with its centre ``centre_height`` m above the floor."""
    world = robot.world
    client = world.client
    x, y, yaw = world.robot_pose()
    cx, cy = x + distance * math.cos(yaw), y + distance * math.sin(yaw)
    half = marker_size * PAGE_CELLS / MARKER_CELLS / 2
    # The quad's plane faces the robot: its local +x runs to the robot's right as seen from
    # the robot (the image's left-to-right), its +z up.
    right = (math.sin(yaw), -math.cos(yaw))
    corners = [(-half, -half), (half, -half), (half, half), (-half, half)]
    vertices = [[right[0] * u, right[1] * u, v] for u, v in corners]
    uvs = [[0, 0], [1, 0], [1, 1], [0, 1]]
    # both windings, so that the page is drawn whichever way the renderer culls
    indices = [0, 1, 2, 0, 2, 3, 0, 2, 1, 0, 3, 2]
    visual = p.createVisualShape(p.GEOM_MESH, vertices=vertices, indices=indices, uvs=uvs,
                                 normals=[[-math.cos(yaw), -math.sin(yaw), 0]] * 4,
                                 physicsClientId=client)
    body = p.createMultiBody(0, -1, visual, (cx, cy, centre_height), physicsClientId=client)
    texture = p.loadTexture(str(PAGE_PNG), physicsClientId=client)
    p.changeVisualShape(body, -1, textureUniqueId=texture, rgbaColor=(1, 1, 1, 1),
                        physicsClientId=client)
    robot.step(0.0)  # nothing moves; the camera's next frame shows the page
