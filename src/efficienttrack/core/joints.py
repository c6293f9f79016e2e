"""The machine's joints and control period: every joint name, count, limit and the 20 Hz period, defined once.

Joint order everywhere: boom, arm, bucket, swing. Angles are radians inside the package; the swing
wraps at ±π (:func:`efficienttrack.core.angles.wrap`).
"""

from __future__ import annotations

import math

JOINT_NAMES = ("boom", "arm", "bucket", "swing")
"""Joint names, in the package's one joint order."""
N_JOINTS = len(JOINT_NAMES)
"""Joints per machine (4)."""
SWING = JOINT_NAMES.index("swing")
"""Index of the swing, the joint that wraps at ±π."""
OBS_DIM = 2 * N_JOINTS
"""Observation channels: [q rad, q̇ rad/s] (8)."""
DT = 0.05
"""Control period of the XE75 and of every reference and record, s (20 Hz)."""
CONTROL_RATE_HZ = 1.0 / DT
"""Control steps per second, to turn a step count into interaction time."""
MAX_ABS_ANGLE = 2 * math.pi
"""Angles beyond ±2π rad are taken for degrees (or garbage) and refused wherever they are read."""
MAX_ABS_VELOCITY = 20.0
"""Joint speeds beyond ±20 rad/s (about 3 turns a second) are no excavator's and refused wherever records are read;
the XE75's logs stay below 3 rad/s."""
PWM_SCALE = 1000.0
"""The valve commands' range, ±1000 PWM; the open loop's actions and the plant model's inputs are PWM / 1000."""
ENV_FUTURE = 20
"""F of the environments' observation by default, the paper's (:data:`efficienttrack.envs.core.FUTURE`); an agent that
reads their flat observation (``AdjustmentPolicy.predict``) splits it with it."""
MAX_HORIZON = 400
"""Longest horizon, history or future a config or an environment may ask for: 20 s at 20 Hz (the paper: 20 steps)."""
