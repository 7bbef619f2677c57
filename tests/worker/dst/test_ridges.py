"""Node rows on horizontal ridges and valleys: the topology mesh's surgery, checked on the mesh itself
(the slices they make possible are checked in test_pipeline and test_report)."""

from __future__ import annotations

import numpy as np
import pytest

from tests.conftest import build_part, write_step
from worker.dst import constants as C
from worker.dst.meshops import edge_defects, signed_volume
from worker.dst.ridges import add_ridge_rows
from worker.dst.step_io import read_step
from worker.dst.topomesh import build_topomesh

CLEARANCE = 1e-4
TOP = 4.1 + CLEARANCE  # the ridge's height in every part below


def _mesh(tmp_path, kind: str, nurbs: bool):
    part = read_step(
        write_step(build_part(kind, clearance=CLEARANCE), tmp_path / f"{kind}.step", nurbs=nurbs)
    )
    return build_topomesh(part.solids[0], deflection=0.01, angular=C.TOPO_ANGULAR_RAD, merge_tol=1e-8)


@pytest.mark.parametrize("nurbs", [False, True])
@pytest.mark.parametrize("kind", ["through_hole", "lying_cylinder", "flat_torus"])
def test_a_ridge_row_keeps_the_mesh_closed_and_every_node_exact(tmp_path, kind, nurbs):
    """Split along the ridge (a plane 0.1 um below it): the ridge then has nodes (new ones, or those
    of a seam edge lying on it: the analytic lying cylinder's); the mesh is still a closed,
    consistently oriented manifold; the new nodes lie on the ridge (its exact height) and on the
    surface at their (u, v) in every triangle; split boundary edges still map to their B-rep edge,
    whose curve passes through both ends of each piece."""
    mesh = _mesh(tmp_path, kind, nurbs)
    n0, volume0 = mesh.n_nodes, signed_volume(mesh.xyz, mesh.tris)
    add_ridge_rows(mesh, np.array([1.1, 4.1]))
    on_ridge = np.abs(mesh.xyz[:, 2] - TOP) < 1e-9
    assert on_ridge.sum() >= 2
    assert edge_defects(mesh.tris, mesh.n_nodes) == (0, 0)
    assert np.array_equal(np.unique(mesh.tris), np.arange(mesh.n_nodes))
    new = np.arange(n0, mesh.n_nodes)
    np.testing.assert_allclose(mesh.xyz[new, 2], TOP, atol=1e-9)
    # the surface at each corner's (u, v) is the node
    for t in np.flatnonzero(np.isin(mesh.tris, new).any(axis=1)).tolist():
        fe = mesh.faces[int(mesh.tri_face[t])]
        for node, (u, v) in zip(mesh.tris[t].tolist(), mesh.tri_uv[t].tolist(), strict=True):
            assert np.linalg.norm(np.subtract(fe.point(u, v), mesh.xyz[node])) < 1e-7
    for (a, b), ei in mesh.edge_of.items():
        if a >= n0 or b >= n0:
            ev = mesh.edges[ei]
            for node in (a, b):
                s = ev.parameter_of(tuple(mesh.xyz[node]))
                q = ev.ad.Value(s)
                assert np.linalg.norm(np.subtract((q.X(), q.Y(), q.Z()), mesh.xyz[node])) < 1e-7
    # nodes moved onto the surface from chords at most a deflection off it: a sliver of volume
    assert abs(signed_volume(mesh.xyz, mesh.tris) - volume0) < 0.1


def test_no_plane_beside_the_ridge_leaves_the_mesh_alone(tmp_path):
    """Planes farther from the ridge than the band (two deflections) change nothing (the same mesh
    gets a row with a plane 0.1 um below the ridge: the first test)."""
    mesh = _mesh(tmp_path, "through_hole", False)
    tris = mesh.tris.copy()
    assert add_ridge_rows(mesh, np.array([4.0, 4.2])) == 0
    assert np.array_equal(mesh.tris, tris)
