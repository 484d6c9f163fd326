"""Deprecated alias of :mod:`icefab.core` (kept for one release).

``icefab.types`` shadowed the standard library's ``types`` module for scripts run from
inside the package folder; the data types now live in ``icefab.core`` and the path class
is ``icefab.core.Toolpath`` (``Path`` remains an alias of it).
"""

from __future__ import annotations

import warnings

from icefab.core import *  # noqa: F401,F403
from icefab.core import (MATERIALS, ROLES, HeightMap, Layer, LayerPaths, Material, Mesh,  # noqa: F401
                         Path, Region, Role, Stack, Toolpath, Toolpaths, Trajectory,
                         ValveProgram, signed_area)

warnings.warn("icefab.types is deprecated; import from icefab.core (Path is now Toolpath)",
              DeprecationWarning, stacklevel=2)
