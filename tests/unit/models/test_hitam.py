"""HiTAM bookkeeping: coarse directions and columns, top-K expansion at grid edges, α schedule."""

from __future__ import annotations

import torch

from rflscm.geometry import AngleGrid
from rflscm.models.rflscm.hitam import HiTAM, scatter_fine

GRID = AngleGrid(num_el=7, num_az=8, el_min_deg=-60.0, el_step_deg=20.0)  # β = 3: blocks 3,3,1 × 3,3,2


def test_topk_expands_to_the_right_fine_bins_with_partial_edge_blocks() -> None:
    h = HiTAM(GRID, beta=3, top_k=2)
    assert h.num_coarse == 9 and h.num_fine_slots == 18
    power = torch.zeros(2, 9)
    power[0, 8] = 5.0  # corner block (I=2, J=2): fine row 6, columns 6, 7 → 2 valid bins
    power[0, 4] = 3.0  # inner block (I=1, J=1): rows 3–5, columns 3–5
    power[0, 0] = 1.0  # third: not selected
    power[1, 2] = 2.0  # block (I=0, J=2): rows 0–2, columns 6–7 → 6 valid bins
    power[1, 6] = 1.5  # block (I=2, J=0): row 6, columns 0–2 → 3 valid bins
    bins, valid = h.expand(power)
    got0 = set(bins[0][valid[0]].tolist())
    assert got0 == {6 * 8 + 6, 6 * 8 + 7} | {i * 8 + j for i in (3, 4, 5) for j in (3, 4, 5)}
    got1 = set(bins[1][valid[1]].tolist())
    assert got1 == {i * 8 + j for i in (0, 1, 2) for j in (6, 7)} | {6 * 8 + j for j in (0, 1, 2)}
    assert int(valid[0].sum()) == 11 and int(valid[1].sum()) == 9


def test_topk_selects_exactly_the_largest_coarse_bins() -> None:
    h = HiTAM(AngleGrid(), beta=3, top_k=32)
    power = torch.rand(4, h.num_coarse)
    bins, valid = h.expand(power)
    parents = h.mapping.parent_of()[bins[valid]]
    for b in range(4):
        chosen = set(h.mapping.parent_of()[bins[b][valid[b]]].tolist())
        assert chosen == set(torch.topk(power[b], 32).indices.tolist())
    assert parents.numel() == int(valid.sum())


def test_ranked_blocks_continue_the_selection_and_spread_keeps_each_blocks_power() -> None:
    h = HiTAM(GRID, beta=3, top_k=2)
    power = torch.tensor([[4.0, 3.0, 0.5, 2.0, 0, 0, 0, 1.0, 0]])
    order = h.ranked(power, 5)
    assert order[0].tolist() == [0, 1, 3, 7, 2]  # strongest first; the first K_C are Ω′'s blocks
    bins, _ = h.expand(power)
    parent = h.mapping.parent_of()
    assert set(parent[bins[0]].tolist()) == {0, 1}
    fine, values, valid = h.spread(power, order[:, 2:])
    assert fine.shape == values.shape == valid.shape == (1, 3 * 9)
    assert set(parent[fine[0][valid[0]]].tolist()) == {3, 7, 2}
    for block in (3, 7, 2):  # each block's power spread evenly over its valid bins, nothing on invalid slots
        mine = valid[0] & (parent[fine[0]] == block)
        assert torch.isclose(values[0][mine].sum(), power[0, block])
        assert torch.allclose(values[0][mine], values[0][mine][0].expand(int(mine.sum())))
    assert float(values[0][~valid[0]].abs().sum()) == 0.0


def test_coarse_columns_and_directions_are_block_means_and_centres() -> None:
    h = HiTAM(GRID, beta=3, top_k=2)
    a = torch.rand(2, 5, GRID.num_bins)
    cols = h.coarse_columns(a)
    assert cols.shape == (2, 5, 9)
    dirs = h.coarse_directions()
    assert torch.allclose(dirs.norm(dim=-1), torch.ones(9))
    fine = GRID.directions()
    # block (2, 2) is fine bins (6, 6) and (6, 7)
    assert torch.allclose(cols[..., 8], 0.5 * (a[..., 6 * 8 + 6] + a[..., 6 * 8 + 7]))
    assert torch.allclose(cols[..., 4], a[..., [i * 8 + j for i in (3, 4, 5) for j in (3, 4, 5)]].mean(-1))
    centre = fine[6 * 8 + 6] + fine[6 * 8 + 7]
    assert torch.allclose(dirs[8], centre / centre.norm(), atol=1e-6)


def test_block_columns_make_spread_power_consistent() -> None:
    """A⁽¹⁾ x_J equals the fine prediction when x_J is spread evenly over the block's bins."""
    h = HiTAM(GRID, beta=3, top_k=9)
    a = torch.rand(3, GRID.num_bins, dtype=torch.float64)
    x_coarse = torch.rand(9, dtype=torch.float64)
    share = h.valid / h.valid.sum(-1, keepdim=True)
    x_fine = scatter_fine(
        (x_coarse[:, None] * share).reshape(1, -1).double(),
        h.children.reshape(1, -1),
        torch.ones(1, 81, dtype=torch.bool),
        GRID.num_bins,
    )[0]
    assert torch.allclose(h.coarse_columns(a) @ x_coarse, a @ x_fine)


def test_alpha_schedule() -> None:
    h = HiTAM(GRID, beta=3, top_k=2, warmup_steps=10, ramp_steps=4)
    assert [h.alpha(s) for s in (0, 9, 10, 11, 13, 50)] == [0.0, 0.0, 0.25, 0.5, 1.0, 1.0]
    assert HiTAM(GRID, 3, 2, warmup_steps=0, ramp_steps=0).alpha(0) == 1.0


def test_scatter_fine_ignores_invalid_slots() -> None:
    out = scatter_fine(
        torch.tensor([[1.0, 2.0, 3.0]]), torch.tensor([[4, 0, 2]]), torch.tensor([[True, False, True]]), 6
    )
    assert out.tolist() == [[0.0, 0.0, 3.0, 0.0, 1.0, 0.0]]
