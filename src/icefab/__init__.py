"""icefab: CAD mesh to robotic rapid-freeze-prototyping builds.

Public API (see README): ``load_mesh``, ``place_mesh``, ``Job``, ``load_job``, ``slice_mesh``,
``add_scaffold``, ``plan_paths``, ``plan_motion``, ``plan_valves``, and the feedback and
simulation entry points. Names are imported lazily so ``import icefab`` stays cheap.
"""

from __future__ import annotations

import importlib
import logging
from typing import Any

from icefab import _kernel_cache

# before any kernel is loaded from numba's cache: a cached kernel may hold an edited
# module's old code (icefab._kernel_cache)
_kernel_cache.check()

__version__ = "0.1.0"

logging.getLogger(__name__).addHandler(logging.NullHandler())

# public name -> module that defines it
_LAZY = {
    # (numpy and the settings load when first used: 'import icefab' is cheap, so the
    # 'icefab' command can catch a Ctrl-C while its modules load, icefab.__main__.run)
    "Job": "icefab.config",
    "load_job": "icefab.config",
    "IcefabError": "icefab.errors",
    **{name: "icefab.core" for name in ("HeightMap", "Layer", "LayerPaths", "Mesh", "Path",
                                        "Region", "Stack", "Toolpath", "Toolpaths",
                                        "Trajectory", "ValveProgram")},
    "load_mesh": "icefab.mesh",
    "load_meshes": "icefab.mesh",
    "prepare_parts": "icefab.mesh",
    "place_mesh": "icefab.mesh",
    "slice_mesh": "icefab.slicing",
    "save_stack": "icefab.slicing",
    "load_stack": "icefab.slicing",
    "add_scaffold": "icefab.regions",
    "plan_paths": "icefab.paths",
    "plan_motion": "icefab.motion",
    "plan_valves": "icefab.flow",
    "smf_update": "icefab.feedback",
    "tune_gains": "icefab.feedback",
    "simulate_build": "icefab.sim",
    "demo_mug": "icefab.demo",
}


def __getattr__(name: str) -> Any:
    module = _LAZY.get(name)
    if module is None:
        raise AttributeError(f"module 'icefab' has no attribute {name!r}")
    return getattr(importlib.import_module(module), name)


__all__ = list(_LAZY)
