"""Gravity in the nav frame (NED: down is +z), the one value the filter, the simulator and
the importers use."""

from __future__ import annotations

import numpy as np

G_M_S2 = 9.80665  # standard gravity
G_NAV_M_S2 = np.array([0.0, 0.0, G_M_S2])
G_NAV_M_S2.setflags(write=False)
