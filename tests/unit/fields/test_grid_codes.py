"""Per-grid codes: exact look-up on table grids, interpolation between them, checkpoint resizing."""

from __future__ import annotations

import torch

from rflscm.fields.grid_codes import GridCodes


def _codes() -> GridCodes:
    torch.manual_seed(0)
    positions = torch.tensor([[0.0, 0.0, 1.5], [10.0, 0.0, 1.5], [0.0, 10.0, 1.5], [10.0, 10.0, 1.5], [50.0, 50.0, 1.5]])
    table = GridCodes(positions, dim=3)
    with torch.no_grad():
        table.codes.copy_(torch.randn(5, 3))
    return table


def test_a_table_grid_gets_its_own_code() -> None:
    table = _codes()
    out = table(table.positions[[3, 0, 4]])
    assert torch.allclose(out, table.codes[[3, 0, 4]], atol=1e-5)


def test_a_point_between_grids_gets_a_convex_mix_of_its_neighbours() -> None:
    table = _codes()
    centre = table(torch.tensor([[5.0, 5.0, 1.5]]))[0]  # equidistant from the first four
    assert torch.allclose(centre, table.codes[:4].mean(0), atol=1e-5)
    near = table(torch.tensor([[1.0, 0.0, 1.5]]))[0]  # much nearer grid 0 than any other
    index, weight = table.weights(torch.tensor([[1.0, 0.0, 1.5]]))
    assert int(index[0, weight[0].argmax()]) == 0 and abs(float(weight.sum()) - 1.0) < 1e-6 and bool((weight >= 0).all())
    assert torch.allclose(near, (table.codes[index[0]] * weight[0, :, None]).sum(0))


def test_gradients_reach_only_the_codes_used() -> None:
    table = _codes()
    table(table.positions[[1]]).sum().backward()
    grad = table.codes.grad.abs().sum(1)
    assert grad[1] > 0 and float(grad[[0, 2, 3, 4]].max()) < 1e-6 * float(grad[1])


def test_loading_resizes_the_table() -> None:
    table = _codes()
    fresh = GridCodes(torch.zeros(1, 3), dim=3)
    fresh.load_state_dict(table.state_dict())
    assert fresh.codes.shape == (5, 3) and torch.equal(fresh(table.positions), table(table.positions))
