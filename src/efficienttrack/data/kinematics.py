"""Forward kinematics of the XE75 arm tip, for the end-effector (ETD) metrics.

The data README defines the tip as a chain of 4×4 homogeneous transforms (lengths in m):

    G = Ry(1.0)·Ry(boom)·T(0,0,3.6957)·Ry(1.5)·Ry(arm)·T(0,0,1.62233)·Ry(bucket)
    U = T(0,0,1.4)·Rz(swing),   A = T(0,−0.1,0)
    fk(q) = (inv(inv(A)·inv(U))·G)[:3, 3] = (U·A·G)[:3, 3]

The bucket rotation comes after the arm tip and does not move the point. Closed form, used
here: with p = (L1·sin(1+boom) + L2·sin(2.5+boom+arm), −0.1, L1·cos(1+boom) + L2·cos(2.5+boom+arm)),
fk(q) = Rz(swing)·p + (0, 0, 1.4).
"""

from __future__ import annotations

import numpy as np

BOOM_LENGTH = 3.6957
"""L1: boom pivot to arm pivot, m."""
ARM_LENGTH = 1.62233
"""L2: arm pivot to arm tip, m."""
BOOM_OFFSET = 1.0
"""Fixed rotation about y before the boom angle, rad."""
ARM_OFFSET = 1.5
"""Fixed rotation about y before the arm angle, rad."""
SWING_HEIGHT = 1.4
"""Height of the boom pivot plane above the swing origin, m."""
LATERAL_OFFSET = -0.1
"""y offset of the arm plane, m."""


def tip_position(q: np.ndarray) -> np.ndarray:
    """Arm-tip position of the XE75 for joint angles ``q``.

    Args:
        q: (..., 4) rad, joint angles (boom, arm, bucket, swing); the bucket does not move the tip.

    Returns:
        (..., 3) m, tip position (x, y, z) in the machine frame.
    """
    q = np.asarray(q, dtype=np.float64)
    boom, arm, swing = q[..., 0], q[..., 1], q[..., 3]
    reach = BOOM_LENGTH * np.sin(BOOM_OFFSET + boom) + ARM_LENGTH * np.sin(BOOM_OFFSET + ARM_OFFSET + boom + arm)
    height = BOOM_LENGTH * np.cos(BOOM_OFFSET + boom) + ARM_LENGTH * np.cos(BOOM_OFFSET + ARM_OFFSET + boom + arm)
    cos, sin = np.cos(swing), np.sin(swing)
    return np.stack(
        [cos * reach - sin * LATERAL_OFFSET, sin * reach + cos * LATERAL_OFFSET, height + SWING_HEIGHT],
        axis=-1,
    )
