"""The one mesh-PLY reader and writer (``brave6d.annotation.read_ply_mesh`` / ``write_ply_mesh``) and the
stages' readers built on it: they return the same arrays on every mesh PLY the project ships."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import trimesh
from plyfile import PlyData, PlyElement

from brave6d.annotation import MeshData, load_mesh, read_ply_mesh, write_ply_mesh
from brave6d.core.errors import DataError
from brave6d.evaluation.agents import read_model_ply
from brave6d.evaluation.metrics import load_ply_mesh
from brave6d.serve.bundle import load_model_m

REPO = Path(__file__).resolve().parents[1]
SHIPPED = sorted((REPO / "data" / "demo" / "meshes").glob("*.ply")) + sorted(
    (REPO / "tests" / "fixtures").rglob("*.ply"))
CUBE_V = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0], [0, 0, 1], [1, 0, 1], [1, 1, 1], [0, 1, 1]],
                  dtype=np.float64)


def _plyfile_mesh(path: Path, vertices: np.ndarray, polygons: list[list[int]], text: bool = False,
                  byte_order: str = "<", face_list: str = "vertex_indices") -> Path:
    """A mesh PLY written by plyfile (an independent writer), polygons of any size."""
    vert = np.array([tuple(v) for v in vertices], dtype=[("x", "f4"), ("y", "f4"), ("z", "f4")])
    elements = [PlyElement.describe(vert, "vertex")]
    if polygons:
        face = np.empty(len(polygons), dtype=[(face_list, "O")])
        face[face_list] = [np.asarray(p, dtype=np.int32) for p in polygons]
        elements.append(PlyElement.describe(face, "face"))
    PlyData(elements, text=text, byte_order=byte_order).write(str(path))
    return path


def test_project_ships_mesh_plys_to_compare() -> None:
    assert len(SHIPPED) >= 8  # the demo's six meshes and the 3D-DAT fixture's two


@pytest.mark.parametrize("path", SHIPPED, ids=lambda p: p.name)
def test_every_reader_returns_trimeshs_arrays_on_the_shipped_meshes(path: Path) -> None:
    reference = trimesh.load(str(path), process=False)
    v_ref = np.asarray(reference.vertices, dtype=np.float64)
    f_ref = np.asarray(reference.faces, dtype=np.int64)
    mesh = read_ply_mesh(path)
    np.testing.assert_array_equal(mesh.vertices, v_ref)
    np.testing.assert_array_equal(mesh.faces, f_ref)
    assert mesh.vertices.dtype == np.float64 and mesh.faces.dtype == np.int64
    for vertices, faces in (load_ply_mesh(path), read_model_ply(path.read_bytes())[:2]):
        np.testing.assert_array_equal(vertices, v_ref)
        np.testing.assert_array_equal(faces, f_ref)
    v_m, f_m = load_model_m(path)
    np.testing.assert_array_equal(v_m, v_ref / 1000.0)
    np.testing.assert_array_equal(f_m, f_ref)
    loaded = load_mesh(path)
    np.testing.assert_array_equal(loaded.vertices, v_ref)
    if getattr(reference.visual, "kind", None) == "vertex":
        np.testing.assert_array_equal(loaded.vertex_colors, np.asarray(reference.visual.vertex_colors)[:, :3])
    else:
        assert loaded.vertex_colors is None


def test_write_then_read_keeps_vertices_faces_normals_and_colours(tmp_path: Path) -> None:
    faces = np.array([[0, 2, 1], [0, 3, 2], [4, 5, 6], [4, 6, 7]], dtype=np.int64)
    colors = np.arange(24, dtype=np.uint8).reshape(8, 3)
    normals = np.tile([0.0, 0.0, 1.0], (8, 1))
    path = write_ply_mesh(tmp_path / "sub" / "m.ply", CUBE_V * 12.5, faces, normals, colors, comment="test model")
    mesh = read_ply_mesh(path)
    np.testing.assert_array_equal(mesh.vertices, CUBE_V * 12.5)
    np.testing.assert_array_equal(mesh.faces, faces)
    np.testing.assert_array_equal(mesh.vertex_colors, colors)
    ply = PlyData.read(str(path))
    assert ply.comments == ["test model"]
    np.testing.assert_array_equal(ply["vertex"].data["nz"], np.ones(8, dtype=np.float32))


@pytest.mark.parametrize("comment", [None, "BRAVE-6D bundle model (millimetres)"])
def test_written_bytes_equal_plyfiles_for_the_same_mesh(tmp_path: Path, comment: str | None) -> None:
    faces = np.array([[0, 2, 1], [0, 3, 2], [4, 5, 6]], dtype=np.int64)
    ours = write_ply_mesh(tmp_path / "ours.ply", CUBE_V, faces, comment=comment)
    vert = np.empty(8, dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4")])
    vert["x"], vert["y"], vert["z"] = CUBE_V.T
    face = np.empty(len(faces), dtype=[("vertex_indices", "<i4", (3,))])
    face["vertex_indices"] = faces
    theirs = tmp_path / "theirs.ply"
    PlyData([PlyElement.describe(vert, "vertex"), PlyElement.describe(face, "face")], text=False,
            comments=[comment] if comment else []).write(str(theirs))
    assert ours.read_bytes() == theirs.read_bytes()


@pytest.mark.parametrize("text,byte_order", [(True, "="), (False, ">"), (False, "<")])
def test_ascii_and_both_byte_orders_read_the_same_arrays(tmp_path: Path, text: bool, byte_order: str) -> None:
    rng = np.random.default_rng(4)
    vertices = rng.normal(size=(30, 3)).astype(np.float32).astype(np.float64)
    polygons = rng.integers(0, 30, size=(40, 3)).tolist()
    mesh = read_ply_mesh(_plyfile_mesh(tmp_path / "m.ply", vertices, polygons, text, byte_order))
    np.testing.assert_array_equal(mesh.vertices, vertices)
    np.testing.assert_array_equal(mesh.faces, np.asarray(polygons))


def test_polygons_are_fan_triangulated_in_file_order(tmp_path: Path) -> None:
    hexagon_v = np.array([[np.cos(a), np.sin(a), 2.0] for a in np.linspace(0, 2 * np.pi, 7)[:-1]])
    path = _plyfile_mesh(tmp_path / "poly.ply", np.vstack([CUBE_V, hexagon_v]),
                         [[0, 3, 2, 1], [4, 5, 6], list(range(8, 14))], face_list="vertex_index")
    np.testing.assert_array_equal(read_ply_mesh(path).faces, [[0, 3, 2], [0, 2, 1], [4, 5, 6], [8, 9, 10],
                                                                [8, 10, 11], [8, 11, 12], [8, 12, 13]])


def test_a_point_cloud_has_no_faces(tmp_path: Path) -> None:
    path = _plyfile_mesh(tmp_path / "points.ply", CUBE_V, [])
    assert read_ply_mesh(path).faces.shape == (0, 3)
    assert load_ply_mesh(path)[1] is None
    assert read_model_ply(path.read_bytes())[1] is None
    with pytest.raises(DataError, match="points.ply: the file holds no triangles"):
        load_mesh(path)


def test_bad_plys_raise_data_errors_naming_the_file(tmp_path: Path) -> None:
    good = _plyfile_mesh(tmp_path / "good.ply", CUBE_V, [[0, 1, 2]])
    with pytest.raises(DataError, match="missing.ply: mesh file not found"):
        read_ply_mesh(tmp_path / "missing.ply")
    truncated = tmp_path / "truncated.ply"
    truncated.write_bytes(good.read_bytes()[:-5])
    with pytest.raises(DataError, match="truncated.ply: cannot read the PLY mesh"):
        read_ply_mesh(truncated)
    with pytest.raises(DataError, match="object 3 from the server: cannot read the PLY mesh"):
        read_ply_mesh(b"not a ply", "object 3 from the server")
    with pytest.raises(DataError, match="the object model PLY: cannot read"):
        read_model_ply(b"ply\nformat nonsense\n")
    nan = _plyfile_mesh(tmp_path / "nan.ply", np.vstack([CUBE_V[:2], [[np.nan, 0, 0]]]), [[0, 1, 2]])
    with pytest.raises(DataError, match="nan.ply: vertices contain NaN or inf"):
        load_ply_mesh(nan)
    outside = _plyfile_mesh(tmp_path / "outside.ply", CUBE_V, [[0, 1, 8]])
    with pytest.raises(DataError, match=r"outside.ply: a face refers to a vertex outside 0\.\.7"):
        load_model_m(outside)
    line = _plyfile_mesh(tmp_path / "line.ply", CUBE_V, [[0, 1]])
    with pytest.raises(DataError, match="line.ply: a face has fewer than three vertices"):
        read_ply_mesh(line)
    no_list = _plyfile_mesh(tmp_path / "no_list.ply", CUBE_V, [[0, 1, 2]], face_list="corners")
    with pytest.raises(DataError, match="no_list.ply: the face element has no vertex_indices or vertex_index"):
        read_ply_mesh(no_list)


def test_mesh_data_scaled_changes_units_only() -> None:
    mesh = MeshData(CUBE_V, np.array([[0, 1, 2]]), None, "cube")
    scaled = mesh.scaled(1000.0)
    np.testing.assert_array_equal(scaled.vertices, CUBE_V * 1000.0)
    assert scaled.faces is mesh.faces and scaled.source == "cube"
