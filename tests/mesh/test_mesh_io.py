"""read_mesh / write_mesh through meshio: round trips, cell selection, errors."""

import sys

import jax.numpy as jnp
import numpy as np
import pytest

from geomjax import Mesh, icosphere, read_mesh, tetrahedralized_box, write_mesh

meshio = pytest.importorskip("meshio")


@pytest.mark.parametrize("suffix", [".vtu", ".vtk"])
def test_round_trip_keeps_points_cells_and_data(tmp_path, suffix):
    sphere = icosphere(2)
    rng = np.random.default_rng(0)
    mesh = Mesh(sphere.points, sphere.cells,
                point_data={"height": sphere.points[:, 2], "velocity": jnp.asarray(rng.normal(size=(162, 3)))},
                cell_data={"region": jnp.arange(320, dtype=jnp.int32)})
    path = tmp_path / f"sphere{suffix}"
    write_mesh(path, mesh)
    back = read_mesh(path)
    np.testing.assert_array_equal(back.points, mesh.points)
    np.testing.assert_array_equal(back.cells, mesh.cells)
    assert back.points.dtype == jnp.float64
    np.testing.assert_array_equal(back.point_data["height"], mesh.point_data["height"])
    np.testing.assert_array_equal(back.point_data["velocity"], mesh.point_data["velocity"])
    np.testing.assert_array_equal(back.cell_data["region"], np.arange(320))


def test_round_trip_of_tetrahedra_and_float32(tmp_path):
    box = tetrahedralized_box(2, 2, 2, dtype=jnp.float32)
    write_mesh(tmp_path / "box.vtu", box)
    back = read_mesh(str(tmp_path / "box.vtu"), dtype=jnp.float32)
    assert back.points.dtype == jnp.float32 and back.n_manifold_dims == 3
    np.testing.assert_array_equal(back.points, box.points)
    np.testing.assert_array_equal(back.cells, box.cells)


def test_read_selects_the_highest_dimensional_simplices(tmp_path):
    box = tetrahedralized_box(1, 1, 1)
    points = np.asarray(box.points)
    tets = np.asarray(box.cells)
    source = meshio.Mesh(
        points,
        [("vertex", np.array([[0]])), ("tetra", tets[:3]), ("triangle", np.array([[0, 1, 2]])), ("tetra", tets[3:])],
        cell_data={"part": [np.array([9]), np.zeros(3), np.array([7.0]), np.ones(3)]},
    )
    source.write(tmp_path / "mixed.vtu")
    back = read_mesh(tmp_path / "mixed.vtu")
    np.testing.assert_array_equal(back.cells, tets)
    np.testing.assert_array_equal(back.cell_data["part"], [0, 0, 0, 1, 1, 1])


def test_read_errors(tmp_path):
    quads = meshio.Mesh(np.zeros((4, 3)), [("quad", np.array([[0, 1, 2, 3]])), ("triangle", np.array([[0, 1, 2]]))])
    quads.write(tmp_path / "quads.vtu")
    with pytest.raises(ValueError, match="non-simplex cells"):
        read_mesh(tmp_path / "quads.vtu")
    vertices = meshio.Mesh(np.zeros((2, 3)), [("vertex", np.array([[0], [1]]))])
    vertices.write(tmp_path / "vertices.vtu")
    with pytest.raises(ValueError, match="no line, triangle or tetra cells"):
        read_mesh(tmp_path / "vertices.vtu")
    broken = meshio.Mesh(np.zeros((3, 3)), [("triangle", np.array([[0, 1, 5]]))])
    broken.write(tmp_path / "broken.vtu")
    with pytest.raises(ValueError, match="index range"):
        read_mesh(tmp_path / "broken.vtu")


def test_write_errors(tmp_path):
    with pytest.raises(TypeError, match="geomjax.Mesh"):
        write_mesh(tmp_path / "x.vtu", np.zeros((3, 3)))
    nested = Mesh(jnp.zeros((4, 3)), np.array([[0, 1, 2]]), point_data={"a": {"b": jnp.zeros(4)}})
    with pytest.raises(ValueError, match="flat point_data"):
        write_mesh(tmp_path / "x.vtu", nested)


def test_missing_meshio_names_the_extra(monkeypatch, tmp_path):
    monkeypatch.setitem(sys.modules, "meshio", None)
    with pytest.raises(ImportError, match=r"geomjax\[io\]"):
        read_mesh(tmp_path / "x.vtu")
    with pytest.raises(ImportError, match=r"geomjax\[io\]"):
        write_mesh(tmp_path / "x.vtu", icosphere(0))
