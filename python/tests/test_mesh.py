"""Meshes: numpy round trips, files in every format, errors as exceptions."""

import meshio
import numpy as np
import pytest

import deform


def test_arrays_round_trip(small_beam):
    m = deform.Mesh(small_beam.vertices, small_beam.tets)
    assert np.array_equal(m.vertices, small_beam.vertices)
    assert np.array_equal(m.tets, small_beam.tets)
    assert m.tets.dtype == np.int64 and m.vertices.dtype == np.float64
    assert m.vertices.shape == (m.num_vertices, 3) and m.tets.shape == (m.num_tets, 4)
    # Any integer dtype and Fortran order are taken.
    m2 = deform.Mesh(np.asfortranarray(small_beam.vertices), small_beam.tets.astype(np.uint16))
    assert np.array_equal(m2.tets, small_beam.tets)
    # The beam is [0, 1] x [0, 0.25] x [0, 0.25].
    assert np.isclose(m.volumes.sum(), 0.0625)
    assert (m.volumes > 0).all()


def test_boundary_faces_are_oriented_outward(small_beam):
    v, f = small_beam.vertices, small_beam.boundary_faces
    centre = v.mean(axis=0)
    normals = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])
    outward = ((v[f].mean(axis=1) - centre) * normals).sum(axis=1)
    assert (outward > 0).all()
    # Closed surface: the divergence theorem gives the volume.
    volume = (v[f[:, 0]] * normals).sum() / 6.0
    assert np.isclose(volume, 0.0625)


@pytest.mark.parametrize("ext", [".msh", ".vtu"])
def test_meshio_reads_what_mesh_write_writes(tmp_path, small_beam, ext):
    path = tmp_path / f"beam{ext}"
    small_beam.write(path)
    if ext == ".msh":
        back = deform.read_mesh(path)
        assert np.array_equal(back.tets, small_beam.tets)
        assert np.allclose(back.vertices, small_beam.vertices, rtol=0, atol=1e-15)
    m = meshio.read(path)
    assert np.allclose(m.points, small_beam.vertices)
    assert np.array_equal(m.cells_dict["tetra"], small_beam.tets)


def test_tetgen_round_trip(tmp_path, small_beam):
    small_beam.write(tmp_path / "beam.node")
    back = deform.read_mesh(tmp_path / "beam.node")
    assert np.array_equal(back.tets, small_beam.tets)


def test_bad_meshes_raise(tmp_path):
    tet = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]], float)
    with pytest.raises(ValueError, match="shape"):
        deform.Mesh(tet[:, :2], [[0, 1, 2, 3]])
    with pytest.raises(deform.MeshError, match="vertex 4"):
        deform.Mesh(tet, [[0, 1, 2, 4]])
    with pytest.raises(deform.MeshError, match="negative"):
        deform.Mesh(tet, [[0, 1, 2, -1]])
    bad = tet.copy()
    bad[1, 0] = np.nan
    with pytest.raises(deform.MeshError):
        deform.Mesh(bad, [[0, 1, 2, 3]])
    # A degenerate element is refused; an inverted one is reoriented.
    flat = tet.copy()
    flat[3] = [0.5, 0.5, 0.0]
    with pytest.raises(deform.MeshError, match="element 0"):
        deform.Mesh(flat, [[0, 1, 2, 3]])
    assert deform.Mesh(tet, [[0, 2, 1, 3]]).volumes[0] > 0
    with pytest.raises(OSError):
        deform.read_mesh(tmp_path / "missing.msh")
    garbage = tmp_path / "garbage.msh"
    garbage.write_text("$MeshFormat\nnot a version\n")
    with pytest.raises(deform.MeshError, match="garbage.msh"):
        deform.read_mesh(garbage)
    with pytest.raises(deform.MeshError):
        deform.beam(0)
