"""The agent's action set, declared once below everything that uses it: the simulator (what a
step does, the pose graph's edges) and the models (the policy's width) both read it here.

The indices are the ones every pose graph, checkpoint and SAVN/MJOLNIR offline folder uses: the
five movement actions first (a pose graph has one edge per movement action), ``Done`` last.
"""

from __future__ import annotations

ACTIONS: tuple[str, ...] = ("MoveAhead", "RotateLeft", "RotateRight", "LookUp", "LookDown", "Done")
MOVE_AHEAD, ROTATE_LEFT, ROTATE_RIGHT, LOOK_UP, LOOK_DOWN, DONE = range(6)
N_MOVEMENT_ACTIONS = 5
NUM_ACTIONS = len(ACTIONS)
