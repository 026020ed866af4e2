"""The registry of robot models: what the cell knows of each arm it can emulate, plan for and draw.

A RobotModel holds the published parameters (DH, masses, centres of mass, joint
limits) and the emulator's drive tuning; cell.models.mjcf builds the MuJoCo
model from them, so one record is the one source of truth for an arm: the
emulator simulates it, the controller plans with its limits and kinematics, the
data plane brakes with its decelerations, the recorder and camera draw it.

Every call site takes the model from the robot's own `model` key
(`CellConfig.robot(...).model`); a name not registered here is a config error.
Add a model with `register(RobotModel(...))` in a module imported below (or a
user's module imported before the config is loaded).  This module imports no
MuJoCo: the config checks names against it.
"""

from __future__ import annotations

from cell.models import ur  # noqa: F401  (the UR e-Series register themselves)
from cell.models.registry import MODELS, Drive, RobotModel, get, register

__all__ = ["MODELS", "Drive", "RobotModel", "get", "register"]
