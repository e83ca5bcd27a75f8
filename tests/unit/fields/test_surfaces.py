"""Surface orientation from a point cloud: normals of planes, the structure grid and the specularity."""

from __future__ import annotations

import numpy as np
import torch

from rflscm.fields.surfaces import SurfaceOrientation, point_normals, specularity, structure_grid


def wall(n: int = 2000, seed: int = 0) -> np.ndarray:
    """Points on the plane x = 4 (a wall facing ±x), 20 m × 10 m."""
    rng = np.random.default_rng(seed)
    return np.column_stack([np.full(n, 4.0), rng.uniform(-10, 10, n), rng.uniform(0, 10, n)])


def test_normals_of_a_plane_are_its_normal() -> None:
    normals = point_normals(wall())
    assert np.allclose(np.abs(normals[:, 0]), 1.0, atol=1e-6)


def test_structure_grid_is_n_n_transposed_on_the_wall_and_zero_in_the_air() -> None:
    lo, hi, shape = np.array([-10.0, -10.0, 0.0]), np.array([10.0, 10.0, 10.0]), (11, 11, 6)
    grid = structure_grid(wall(), lo, hi, shape)
    on_wall = grid[7, 5, 2]  # x = 4 → index 7 (2 m spacing)
    assert np.allclose(on_wall, [1, 0, 0, 0, 0, 0], atol=1e-5)
    assert np.all(grid[0] == 0)  # x = −10: no points
    surfaces = SurfaceOrientation(torch.from_numpy(grid), torch.from_numpy(lo), torch.from_numpy(hi))
    assert np.array_equal(surfaces.grid_numpy(), grid)
    t = surfaces(torch.tensor([[4.0, 0.0, 4.0], [-8.0, 0.0, 4.0]]))
    assert torch.allclose(t[0], torch.tensor([1.0, 0, 0, 0, 0, 0]), atol=1e-5) and torch.all(t[1] == 0)


def test_specularity_is_squared_cosine_to_the_normal() -> None:
    t = torch.tensor([[1.0, 0, 0, 0, 0, 0]]).expand(3, 6)  # n = ±x
    h = torch.nn.functional.normalize(torch.tensor([[1.0, 0, 0], [0.0, 1, 0], [-1.0, 1, 0]]), dim=-1)
    assert torch.allclose(specularity(t, h), torch.tensor([1.0, 0.0, 0.5]), atol=1e-6)
    # a tilted plane: T = n nᵀ for n = (1, 1, 0)/√2, components in (xx, yy, zz, xy, xz, yz) order
    tilted = torch.tensor([[0.5, 0.5, 0.0, 0.5, 0.0, 0.0]])
    assert torch.allclose(specularity(tilted, h[2:]), torch.tensor([0.0]), atol=1e-6)
    assert torch.allclose(
        specularity(tilted, torch.nn.functional.normalize(torch.tensor([[1.0, 1, 0]]), dim=-1)), torch.tensor([1.0])
    )
