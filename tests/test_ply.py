"""PLY export/import in the Inria 3DGS layout: exact round trips and foreign files."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays
from plyfile import PlyData, PlyElement

from brave6d.core.errors import DataError
from brave6d.training.model import GaussianModel
from brave6d.training.ply import SH_C0, SplatData, inria_attribute_names, read_ply, trim_sh, write_ply

INRIA_ORDER = (["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"]
               + [f"f_rest_{i}" for i in range(45)]
               + ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"])

f32 = st.floats(width=32, allow_nan=False, allow_infinity=True, allow_subnormal=True)


def random_splat(n: int, degree: int = 3, seed: int = 0) -> SplatData:
    rng = np.random.default_rng(seed)
    k = (degree + 1) ** 2 - 1

    def r(*shape: int) -> np.ndarray:
        return rng.standard_normal(shape).astype(np.float32)

    return SplatData(r(n, 3), r(n, 1, 3), r(n, k, 3), r(n), r(n, 3), r(n, 4))


def bits(a: np.ndarray) -> np.ndarray:
    return np.ascontiguousarray(a, dtype=np.float32).view(np.uint32)


def assert_bitwise(a: SplatData, b: SplatData) -> None:
    for name in ("means", "sh0", "shN", "opacities", "scales", "quats"):
        x, y = getattr(a, name), getattr(b, name)
        assert x.shape == y.shape, name
        assert np.array_equal(bits(x), bits(y)), name


@settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(n=st.integers(1, 12), data=st.data())
def test_roundtrip_is_bitwise_exact(tmp_path: Path, n: int, data: st.DataObject) -> None:
    def arr(*shape: int) -> np.ndarray:
        return data.draw(arrays(np.float32, shape, elements=f32))

    splat = SplatData(arr(n, 3), arr(n, 1, 3), arr(n, 15, 3), arr(n), arr(n, 3), arr(n, 4))
    path = write_ply(tmp_path / "pc.ply", splat)
    assert_bitwise(splat, read_ply(path))


def test_nan_payloads_survive(tmp_path: Path) -> None:
    splat = random_splat(3)
    splat.opacities[1] = np.float32("nan")
    splat.scales[2, 0] = -np.inf
    assert_bitwise(splat, read_ply(write_ply(tmp_path / "pc.ply", splat)))


def test_plyfile_reads_inria_names_in_order(tmp_path: Path) -> None:
    splat = random_splat(5)
    ply = PlyData.read(str(write_ply(tmp_path / "pc.ply", splat)))
    vertex = ply["vertex"]
    assert [p.name for p in vertex.properties] == INRIA_ORDER == inria_attribute_names()
    assert all(vertex.data.dtype[name] == np.dtype("<f4") for name in INRIA_ORDER)
    assert not ply.text and ply.byte_order == "<"
    # values under the Inria names: f_rest is channel-major, normals are zero
    assert np.array_equal(vertex["x"], splat.means[:, 0])
    assert np.array_equal(vertex["f_dc_2"], splat.sh0[:, 0, 2])
    assert np.array_equal(vertex["f_rest_0"], splat.shN[:, 0, 0])  # red, coefficient 1
    assert np.array_equal(vertex["f_rest_1"], splat.shN[:, 1, 0])  # red, coefficient 2
    assert np.array_equal(vertex["f_rest_15"], splat.shN[:, 0, 1])  # green, coefficient 1
    assert np.array_equal(vertex["f_rest_44"], splat.shN[:, 14, 2])
    assert np.array_equal(vertex["opacity"], splat.opacities)
    assert np.array_equal(vertex["rot_0"], splat.quats[:, 0])
    assert not np.any(vertex["nx"])


def test_lower_degree_model_is_padded_to_45_and_trims_back(tmp_path: Path) -> None:
    splat = random_splat(4, degree=1)
    path = write_ply(tmp_path / "pc.ply", splat)
    names = [p.name for p in PlyData.read(str(path))["vertex"].properties]
    assert names == INRIA_ORDER
    back = read_ply(path)
    assert back.sh_degree == 3
    assert not back.shN[:, 3:].any()
    assert_bitwise(splat, trim_sh(back, 1))


def _foreign_ply(path: Path, n: int, n_rest: int, extra: dict[str, str], order_shuffle: bool = False) -> dict:
    rng = np.random.default_rng(1)
    names = ["x", "y", "z", "f_dc_0", "f_dc_1", "f_dc_2"] + [f"f_rest_{i}" for i in range(n_rest)] + \
        ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"]
    fields = [(nm, "<f4") for nm in names] + [(nm, dt) for nm, dt in extra.items()]
    if order_shuffle:
        fields = fields[::-1]
    v = np.empty(n, dtype=fields)
    values = {}
    for nm, dt in fields:
        values[nm] = (rng.standard_normal(n) * 10).astype(dt)
        v[nm] = values[nm]
    PlyData([PlyElement.describe(v, "vertex")]).write(str(path))
    return values


def test_reads_degree0_ply_with_extra_attributes(tmp_path: Path) -> None:
    values = _foreign_ply(tmp_path / "f.ply", 6, 0, {"red": "u1", "filter_3D": "<f4", "nx": "<f8"}, order_shuffle=True)
    s = read_ply(tmp_path / "f.ply")
    assert s.sh_degree == 0 and s.shN.shape == (6, 0, 3)
    assert np.array_equal(s.means[:, 1], values["y"])
    assert np.array_equal(s.quats[:, 3], values["rot_3"])
    model = GaussianModel.from_splat(s)
    assert model.sh_degree == 0 and model.num_gaussians == 6


def test_reads_degree1_ply(tmp_path: Path) -> None:
    values = _foreign_ply(tmp_path / "f.ply", 3, 9, {})
    s = read_ply(tmp_path / "f.ply")
    assert s.sh_degree == 1
    assert np.array_equal(s.shN[:, 2, 1], values["f_rest_5"])  # green block starts at 3


def test_bad_files_raise_data_error_naming_them(tmp_path: Path) -> None:
    with pytest.raises(DataError, match="missing.ply"):
        read_ply(tmp_path / "missing.ply")
    (tmp_path / "junk.ply").write_bytes(b"not a ply")
    with pytest.raises(DataError, match="junk.ply"):
        read_ply(tmp_path / "junk.ply")
    _foreign_ply(tmp_path / "odd.ply", 2, 7, {})
    with pytest.raises(DataError, match="f_rest"):
        read_ply(tmp_path / "odd.ply")
    v = np.zeros(2, dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4")])
    PlyData([PlyElement.describe(v, "vertex")]).write(str(tmp_path / "points.ply"))
    with pytest.raises(DataError, match="f_dc_0"):
        read_ply(tmp_path / "points.ply")


def test_model_roundtrip_through_ply(tmp_path: Path) -> None:
    model = GaussianModel.from_points(np.random.default_rng(0).random((20, 3)), np.full((20, 3), 0.25), sh_degree=3)
    back = GaussianModel.from_splat(read_ply(write_ply(tmp_path / "m.ply", model.to_splat())))
    for name, p in model.params.items():
        assert np.array_equal(bits(p.detach().numpy()), bits(back.params[name].detach().numpy())), name
    rgb = 0.5 + SH_C0 * back.params["sh0"].detach().numpy()[:, 0]
    assert np.allclose(rgb, 0.25, atol=1e-6)


def test_a_subset_keeps_every_per_gaussian_field() -> None:
    """Indices or a mask select the same Gaussians in every field, the mip 3D filter included
    (the report's latency section once dropped it by copying the fields one by one)."""
    import dataclasses

    rng = np.random.default_rng(0)
    n = 7
    splat = SplatData(rng.normal(size=(n, 3)).astype(np.float32), rng.normal(size=(n, 1, 3)).astype(np.float32),
                      rng.normal(size=(n, 3, 3)).astype(np.float32), rng.normal(size=n).astype(np.float32),
                      rng.normal(size=(n, 3)).astype(np.float32), rng.normal(size=(n, 4)).astype(np.float32),
                      filter_3d=rng.random(n).astype(np.float32))
    keep = np.array([5, 1, 2])
    mask = np.zeros(n, bool)
    mask[keep] = True
    for picked, rows in ((splat.subset(keep), keep), (splat.subset(mask), np.sort(keep))):
        for f in dataclasses.fields(SplatData):
            np.testing.assert_array_equal(getattr(picked, f.name), getattr(splat, f.name)[rows], err_msg=f.name)
    assert dataclasses.replace(splat, filter_3d=None).subset(keep).filter_3d is None
