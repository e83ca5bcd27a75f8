"""Ray sampling, sparse sample storage and query joins."""

from __future__ import annotations

import numpy as np
import torch

from rflscm.render import (
    RaySamples,
    build_ray_samples,
    gather_samples,
    join_queries,
    num_samples_for,
    ray_points,
    select_samples,
)


def test_ray_points_follow_paper_eq9() -> None:
    origin = torch.tensor([1.0, 2.0, 30.0])
    direction = torch.tensor([[0.6, 0.0, -0.8]])
    pts = ray_points(origin, direction[:, None, :], torch.arange(3), 4.0)
    assert torch.allclose(pts[0], torch.tensor([[1.0, 2.0, 30.0], [3.4, 2.0, 26.8], [5.8, 2.0, 23.6]]))


def test_num_samples_reach_farthest_corner() -> None:
    q = num_samples_for(
        torch.tensor([0.0, 0.0, 0.0]), torch.tensor([30.0, 40.0, 0.0]), torch.tensor([[0.0, 0.0, 0.0]]), 4.0
    )
    assert (q - 1) * 4.0 >= 50.0 > (q - 2) * 4.0


def test_select_keeps_live_samples_and_one_neighbour_each_side() -> None:
    phi = torch.tensor([[0.0, 0.0, 0.5, 0.0, 0.0, 0.0, 1.0], [0.0] * 7, [0.2] + [0.0] * 6])
    s = select_samples(phi)
    assert s.offsets.tolist() == [0, 5, 5, 7]
    assert s.index.tolist() == [1, 2, 3, 5, 6, 0, 1]
    assert torch.allclose(s.phi, torch.tensor([0.0, 0.5, 0.0, 0.0, 1.0, 0.2, 0.0]))
    assert s.live_counts().tolist() == [2, 0, 1]


def test_gather_matches_a_loop() -> None:
    s = select_samples((torch.rand(6, 9) > 0.6) * torch.rand(6, 9))
    rays = torch.tensor([4, 0, 4, 2])
    p = gather_samples(s, rays)
    expect_ray, expect_index = [], []
    for b, r in enumerate(rays.tolist()):
        idx = s.index[s.offsets[r] : s.offsets[r + 1]].tolist()
        expect_ray += [b] * len(idx)
        expect_index += idx
    assert p.ray.tolist() == expect_ray and p.index.tolist() == expect_index
    for b in range(len(rays)):
        sel = (p.ray == b).nonzero().squeeze(1)
        if sel.numel():
            assert p.first[sel].tolist() == [True] + [False] * (sel.numel() - 1)
            assert p.last[sel].tolist() == [False] * (sel.numel() - 1) + [True]


def test_join_pairs_each_query_with_its_rays_samples() -> None:
    sample_ray = torch.tensor([0, 0, 2, 2, 2, 3])
    query_ray = torch.tensor([2, 0, 1, 2, 3])
    q, s = join_queries(query_ray, sample_ray, num_rays=4)
    pairs = sorted(zip(q.tolist(), s.tolist()))
    expect = sorted(
        (qi, si) for qi, r in enumerate(query_ray.tolist()) for si, sr in enumerate(sample_ray.tolist()) if sr == r
    )
    assert pairs == expect


def test_build_without_prior_keeps_everything() -> None:
    s = build_ray_samples(torch.zeros(3), torch.eye(3), 5, 2.0, None)
    assert s.offsets.tolist() == [0, 5, 10, 15] and bool((s.phi == 1).all())


def test_build_with_prior_and_concat() -> None:
    def phi_fn(p: torch.Tensor) -> torch.Tensor:  # a dense slab at 10 ≤ x ≤ 12
        return ((p[:, 0] >= 10) & (p[:, 0] <= 12)).float()

    dirs = torch.tensor([[1.0, 0.0, 0.0], [-1.0, 0.0, 0.0]])
    s = build_ray_samples(torch.zeros(3), dirs, 10, 2.0, phi_fn, max_points=7)  # chunked
    assert s.offsets.tolist() == [0, 4, 4]
    assert s.index.tolist() == [4, 5, 6, 7] and s.phi.tolist() == [0.0, 1.0, 1.0, 0.0]
    both = RaySamples.concat([s, s])
    assert both.offsets.tolist() == [0, 4, 4, 8, 8] and both.index.numel() == 8
    np.testing.assert_array_equal(both.live_counts().numpy(), [2, 0, 2, 0])


def test_spread_places_rays_among_empty_ones() -> None:
    """The renderer stores samples only for the directions a cell sees (issue 29): ``spread`` puts them at their
    ray ids, every other ray empty, and gathering a placed ray gives its samples back."""
    s = build_ray_samples(torch.zeros(3), torch.eye(3), 4, 2.0, None)  # 3 rays × 4 samples
    wide = s.spread(torch.tensor([1, 4, 5]), 7)
    assert wide.offsets.tolist() == [0, 0, 4, 4, 4, 8, 12, 12]
    np.testing.assert_array_equal(wide.live_counts().numpy(), [0, 4, 0, 0, 4, 4, 0])
    packed = gather_samples(wide, torch.tensor([4, 0]))
    assert packed.ray.tolist() == [0, 0, 0, 0] and packed.index.tolist() == [0, 1, 2, 3]
