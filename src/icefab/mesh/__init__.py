"""Mesh import, diagnostics and part set-up (thesis 3.1, Table 3-1).

This is the only package of icefab that parses mesh files. Everything returns an indexed
:class:`~icefab.core.Mesh` (``vertices (n, 3) float64 mm``, ``faces (m, 3) int64``).

One module per concern (trimesh's ``exchange/`` is the model):

* :mod:`icefab.mesh.load` — format sniffing (by content; the extension is only a hint),
  the loader table :data:`~icefab.mesh.load.LOADERS`, :func:`load_mesh`,
  :func:`read_mesh`, :func:`load_meshes`;
* :mod:`icefab.mesh.stl`, :mod:`icefab.mesh.obj`, :mod:`icefab.mesh.ply` — one reader per
  format (and :func:`write_stl`); :mod:`icefab.mesh._text` — the compiled ASCII scanning
  they share;
* :mod:`icefab.mesh.topology` — welding, edges, duplicate faces, facet measures;
* :mod:`icefab.mesh.repair` — :class:`MeshReport`, :func:`check_mesh`, :func:`clean_mesh`;
* :mod:`icefab.mesh.holes` — closing the holes of open surfaces in 3D before slicing:
  :func:`~icefab.mesh.holes.close_holes`;
* :mod:`icefab.mesh.setup` — part placement: :func:`transform`, :func:`place_mesh`,
  :func:`prepare_parts`.

Everything public is importable from ``icefab.mesh`` as before the split.
"""

from __future__ import annotations

from icefab.mesh.load import LOADERS, load_mesh, load_meshes, merge_meshes, read_mesh
from icefab.mesh.repair import MeshReport, check_mesh, clean_mesh, mesh_volume
from icefab.mesh.setup import (part_fraction_range, place_mesh, prepare_parts,
                                rotation_matrix, transform)
from icefab.mesh.stl import write_stl
from icefab.mesh.topology import edge_buckets, weld_vertices

__all__ = ["MeshReport", "load_mesh", "read_mesh", "load_meshes", "check_mesh",
           "weld_vertices", "clean_mesh", "transform", "place_mesh", "prepare_parts",
           "part_fraction_range", "merge_meshes", "mesh_volume", "write_stl",
           "rotation_matrix", "edge_buckets", "LOADERS"]
