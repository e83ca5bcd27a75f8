"""Point clouds: PLY / LAS / LAZ / NPY round trips and bad files."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from rflscm.data import PointCloud, read_point_cloud, write_point_cloud
from rflscm.errors import DataError


def _cloud(num_points: int = 500) -> PointCloud:
    rng = np.random.default_rng(7)
    xyz = rng.uniform([-300, -200, -2], [400, 250, 60], size=(num_points, 3))
    classes = rng.choice(np.array([0, 1, 2, 6, 200], dtype=np.uint8), size=num_points)
    return PointCloud(xyz, classes)


@pytest.mark.parametrize("suffix", [".ply", ".npy"])
def test_exact_round_trip(tmp_path: Path, suffix: str) -> None:
    pc = _cloud()
    write_point_cloud(pc, tmp_path / f"pc{suffix}")
    back = read_point_cloud(tmp_path / f"pc{suffix}")
    assert back == pc
    assert back.xyz.dtype == np.float64 and back.classification.dtype == np.uint8


@pytest.mark.parametrize("suffix", [".las", ".laz"])
def test_las_round_trip_to_scale_precision(tmp_path: Path, suffix: str) -> None:
    pc = _cloud()
    write_point_cloud(pc, tmp_path / f"pc{suffix}")
    back = read_point_cloud(tmp_path / f"pc{suffix}")
    assert np.abs(back.xyz - pc.xyz).max() <= 0.0005 + 1e-9  # scale 0.001 m, rounded
    np.testing.assert_array_equal(back.classification, pc.classification)  # 8-bit classes survive (200)
    # a second round trip is exact: values already on the 1 mm lattice
    write_point_cloud(back, tmp_path / f"again{suffix}")
    assert read_point_cloud(tmp_path / f"again{suffix}") == back


def test_laz_is_compressed(tmp_path: Path) -> None:
    pc = _cloud(5000)
    write_point_cloud(pc, tmp_path / "pc.las")
    write_point_cloud(pc, tmp_path / "pc.laz")
    assert (tmp_path / "pc.laz").stat().st_size < 0.8 * (tmp_path / "pc.las").stat().st_size


def test_npy_without_classes_and_ply_without_classification(tmp_path: Path) -> None:
    xyz = np.array([[0.0, 1.0, 2.0], [3.0, 4.0, 5.5]])
    np.save(tmp_path / "p.npy", xyz)
    pc = read_point_cloud(tmp_path / "p.npy")
    np.testing.assert_array_equal(pc.xyz, xyz)
    np.testing.assert_array_equal(pc.classification, [0, 0])
    from plyfile import PlyData, PlyElement

    vertex = np.array([(1.0, 2.0, 3.0)], dtype=[("x", "f4"), ("y", "f4"), ("z", "f4")])
    PlyData([PlyElement.describe(vertex, "vertex")], text=True).write(str(tmp_path / "p.ply"))
    pc = read_point_cloud(tmp_path / "p.ply")
    np.testing.assert_array_equal(pc.xyz, [[1.0, 2.0, 3.0]])
    assert pc.class_counts() == {0: 1}


def test_bad_point_clouds(tmp_path: Path) -> None:
    np.save(tmp_path / "empty.npy", np.zeros((0, 3)))
    with pytest.raises(DataError, match=r"empty\.npy has no points"):
        read_point_cloud(tmp_path / "empty.npy")
    np.save(tmp_path / "flat.npy", np.zeros((4, 2)))
    with pytest.raises(DataError, match=r"flat\.npy: array of shape \(4, 2\)"):
        read_point_cloud(tmp_path / "flat.npy")
    np.save(tmp_path / "nan.npy", np.array([[0.0, 0, 0], [1.0, np.nan, 0]]))
    with pytest.raises(DataError, match=r"nan\.npy point 2: coordinates .* are not finite"):
        read_point_cloud(tmp_path / "nan.npy")
    np.save(tmp_path / "cls.npy", np.array([[0.0, 0, 0, 2], [1.0, 1, 0, 2.5]]))
    with pytest.raises(DataError, match=r"cls\.npy point 2: classification 2\.5 is not an ASPRS class"):
        read_point_cloud(tmp_path / "cls.npy")
    (tmp_path / "pc.xyz").write_text("0 0 0\n")
    with pytest.raises(DataError, match=r"unsupported point cloud format '\.xyz'"):
        read_point_cloud(tmp_path / "pc.xyz")
    (tmp_path / "junk.las").write_bytes(b"\x00" * 64)
    with pytest.raises(DataError, match=r"junk\.las: not a readable LAS point cloud"):
        read_point_cloud(tmp_path / "junk.las")
