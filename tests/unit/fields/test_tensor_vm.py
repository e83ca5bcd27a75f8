"""The VM tensor (paper eq. (20)): values at grid points, interpolation, upsampling."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from rflscm.fields import TensorVM, resolution_for
from rflscm.fields.tensor_vm import LINE_AXES, PLANE_AXES

LO, HI = torch.tensor([-10.0, 0.0, 0.0]), torch.tensor([30.0, 20.0, 12.0])


def reference_value(field: TensorVM, point: np.ndarray) -> np.ndarray:
    """Σ_m Σ_r v(p_a) M(p_u, p_v) b — interpolated with numpy, written independently."""
    lo, hi, res = field.box_lo.numpy(), field.box_hi.numpy(), field.resolution
    coord = (point - lo) / (hi - lo) * (np.array(res) - 1)  # fractional grid index per axis

    def lin(values: np.ndarray, c: float) -> np.ndarray:  # values [R, n]
        return np.array([np.interp(c, np.arange(values.shape[1]), v) for v in values])

    comps = []
    for m in range(3):
        a, (u, v) = LINE_AXES[m], PLANE_AXES[m]
        line = field.lines[m].detach().numpy()[0, :, :, 0]  # [R, res_a]
        plane = field.planes[m].detach().numpy()[0]  # [R, res_v, res_u]
        along_v = np.stack([lin(plane[:, :, j], coord[v]) for j in range(plane.shape[2])], axis=1)  # [R, res_u]
        comps.append(lin(line, coord[a]) * lin(along_v, coord[u]))
    comp = np.stack(comps)  # [3, R]
    basis = field.basis.detach().numpy()
    if field.basis_kind == "per_channel":
        return (comp.reshape(3, field.out_dim, field.rank).sum(-1) * basis).sum(0)
    return comp.reshape(-1) @ basis


@pytest.mark.parametrize("basis", ["per_component", "per_channel"])
def test_matches_independent_interpolation(basis: str) -> None:
    field = TensorVM(LO, HI, (5, 4, 3), rank=3, out_dim=4, basis=basis, init_scale=1.0)
    rng = np.random.default_rng(0)
    pts = rng.uniform(LO.numpy(), HI.numpy(), (20, 3)).astype(np.float32)
    got = field(torch.from_numpy(pts)).detach().numpy()
    ref = np.stack([reference_value(field, p.astype(np.float64)) for p in pts])
    np.testing.assert_allclose(got, ref, rtol=1e-4, atol=1e-5)


def test_upsampling_keeps_values_at_grid_points() -> None:
    field = TensorVM(LO, HI, (5, 4, 3), rank=2, out_dim=3, basis="per_component", init_scale=1.0)
    points = field.grid_points().reshape(-1, 3)
    before = field(points).detach()
    field.upsample((9, 7, 5))  # 2·old − 1: every old grid point is a new grid point
    assert field.resolution == (9, 7, 5) and field.planes[2].shape == (1, 2, 7, 9)
    after = field(points).detach()
    assert torch.allclose(before, after, atol=1e-5)
    # and the new tensor is the linear interpolant: a midpoint is the mean of its neighbours along x
    mid = points[:1] + torch.tensor([[5.0, 0.0, 0.0]])  # half an old cell (old spacing 10 m along x)
    ends = torch.cat([points[:1], points[:1] + torch.tensor([[10.0, 0.0, 0.0]])])
    assert torch.allclose(field(mid).detach()[0], field(ends).detach().mean(0), atol=1e-5)


def test_resolution_for_voxel_size() -> None:
    assert resolution_for(LO, HI, 5.0, 100) == (9, 5, 3)
    assert resolution_for(LO, HI, 0.01, 64) == (64, 64, 64)


def test_per_channel_basis_keeps_channels_on_separate_factors() -> None:
    field = TensorVM(LO, HI, (5, 4, 3), rank=2, out_dim=3, basis="per_channel")
    field(torch.rand(40, 3) * (HI - LO) + LO)[:, 1].sum().backward()
    grads = field.lines[0].grad[0, :, :, 0]  # [R·D, res]: components 2..3 belong to channel 1
    assert grads[2:4].abs().sum() > 0 and grads[:2].abs().sum() == 0 and grads[4:].abs().sum() == 0


def test_gradients_reach_all_factors() -> None:
    field = TensorVM(LO, HI, (5, 4, 3), rank=2, out_dim=3, basis="per_component")
    field(torch.rand(50, 3) * (HI - LO) + LO).square().sum().backward()
    for p in field.parameters():
        assert p.grad is not None and p.grad.abs().sum() > 0
