"""Figures people would rather look at than read: references, tracking, training curves, fidelity.

Every function writes a PNG atomically and returns its path; matplotlib runs headless (Agg).
"""

from __future__ import annotations

import matplotlib

matplotlib.use("Agg")

JOINT_NAMES = ("boom", "arm", "bucket", "swing")
