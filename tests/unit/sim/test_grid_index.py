"""The grid index of the procedural tracer against the whole-scene brute force (issue 29).

``BruteCity`` is the tracer as it was before the index (every segment against every box, every wall against
every receiver, order-2 canyons from the n × n pairs of walls), kept here as the reference only.  Random cities
snap their boxes, transmitters and receivers to a coarse lattice so that segments run along faces, start on
walls and graze corners: losses, blocked flags, outdoor flags, wall sequences and whole path tables must be
equal bit for bit.
"""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from rflscm.sim.backend import empty_path_table
from rflscm.sim.grid_index import CellGrid
from rflscm.sim.procedural import (
    _EPS_M,
    ProceduralCity,
    _box_order_sums,
    grown_scene_options,
    reflection_power,
    segment_box_overlap,
    wall_loss_db,
)


class BruteCity(ProceduralCity):
    """The pre-index tracer: dense over every box and every receiver."""

    def is_outdoor(self, xy):
        xy = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
        inside = (xy[:, None] >= self.box_lo[None, :, :2]) & (xy[:, None] <= self.box_hi[None, :, :2])
        return np.asarray(~inside.all(axis=-1).any(axis=-1))

    def penetration_loss_db(self, p0, p1, freq_hz):
        if not self.num_buildings or len(p0) == 0:
            return np.zeros(len(p0))
        length = np.linalg.norm(p1 - p0, axis=-1)
        t_in, t_out = segment_box_overlap(p0, p1, self.box_lo, self.box_hi)
        inside_m = np.maximum(t_out - t_in, 0.0) * length[:, None]
        crossed = inside_m > _EPS_M
        walls = crossed * ((t_in > 1e-9).astype(float) + (t_out < 1 - 1e-9))
        return walls.sum(-1) * wall_loss_db(freq_hz) + inside_m.sum(-1) * self.interior_loss_db_per_m

    def _blocked(self, p0, p1):
        if not self.num_buildings or len(p0) == 0:
            return np.zeros(len(p0), dtype=bool)
        length = np.linalg.norm(p1 - p0, axis=-1)
        t_in, t_out = segment_box_overlap(p0, p1, self.box_lo, self.box_hi)
        return ((t_out - t_in) * length[:, None] > _EPS_M).any(-1)

    def _wall_sequences(self, order):
        w = self._walls
        n = len(w)
        if order == 1:
            return np.arange(n)[:, None]
        grid_a, grid_b = np.meshgrid(np.arange(n), np.arange(n), indexing="ij")
        a, b = grid_a.ravel(), grid_b.ravel()
        gap = w.sign[a] * (w.coord[b] - w.coord[a])
        facing = (w.axis[a] == w.axis[b]) & (w.sign[a] == -w.sign[b]) & (gap > 0) & (gap <= self.max_canyon_m)
        overlap = np.minimum(w.u_hi[a], w.u_hi[b]) - np.maximum(w.u_lo[a], w.u_lo[b]) > 0
        keep = facing & overlap & (w.box[a] != w.box[b])
        return np.stack([a[keep], b[keep]], axis=1)

    def _walls_order(self, tx, rx, freq_hz, wavelength, order):
        w, seqs = self._walls, self._wall_sequences(order)
        first = seqs[:, 0]
        seqs = seqs[w.sign[first] * (tx[w.axis[first]] - w.coord[first]) > 1e-6]
        eta = self.wall_material.permittivity(freq_hz)
        out = [empty_path_table(), self._reflect_chunk(tx, rx, seqs, eta, wavelength)]
        return pd.concat([t for t in out if len(t)] or out, ignore_index=True)

    def _reflect_chunk(self, tx, rx, seqs, eta, wavelength):
        w, order = self._walls, seqs.shape[1]
        images = [np.broadcast_to(tx, (len(seqs), 3))]
        for j in range(order):
            images.append(w.mirror(images[-1], seqs[:, j]))
        last = seqs[:, -1]
        front = w.sign[last][:, None] * (
            rx[None, :, 0] * (w.axis[last] == 0)[:, None]
            + rx[None, :, 1] * (w.axis[last] == 1)[:, None]
            - w.coord[last][:, None]
        )
        s_idx, r_idx = np.nonzero(front > 1e-6)
        hops = [rx[r_idx]]
        for j in range(order - 1, -1, -1):
            wall, image, target = seqs[s_idx, j], images[j + 1][s_idx], hops[-1]
            rows = np.arange(len(wall))
            a_img, a_tgt = image[rows, w.axis[wall]], target[rows, w.axis[wall]]
            ok = w.sign[wall] * (a_tgt - w.coord[wall]) > 1e-6
            with np.errstate(divide="ignore", invalid="ignore"):
                t = (w.coord[wall] - a_img) / (a_tgt - a_img)
            p = image + t[:, None] * (target - image)
            u = p[rows, 1 - w.axis[wall]]
            ok &= (t > 0) & (t < 1) & (u >= w.u_lo[wall]) & (u <= w.u_hi[wall])
            ok &= (p[:, 2] >= 0) & (p[:, 2] <= w.height[wall])
            s_idx, r_idx = s_idx[ok], r_idx[ok]
            hops = [h[ok] for h in hops] + [p[ok]]
        if len(s_idx) == 0:
            return empty_path_table()
        hops = [np.broadcast_to(tx, (len(s_idx), 3)), *hops[::-1]]
        blocked = np.zeros(len(s_idx), dtype=bool)
        gamma2 = np.ones(len(s_idx))
        for j in range(len(hops) - 1):
            blocked |= self._blocked(hops[j], hops[j + 1])
        for j in range(order):
            k_in = hops[j + 1] - hops[j]
            k_in /= np.linalg.norm(k_in, axis=-1, keepdims=True)
            gamma2 *= reflection_power(k_in, w.normals(seqs[s_idx, j]), eta)
        length = np.linalg.norm(rx[r_idx] - images[-1][s_idx], axis=-1)
        keep = ~blocked
        power = (wavelength / (4 * np.pi * length)) ** 2 * gamma2
        labels = np.full(len(s_idx), "R" * order)
        return self._table(r_idx[keep], power[keep], (hops[1] - hops[0])[keep], length[keep], labels[keep])


def random_boxes(rng: np.random.Generator, num: int, lattice: float) -> tuple[np.ndarray, np.ndarray]:
    """Boxes on a ``lattice`` [m] (shared faces, touching and overlapping boxes), some zero-size."""
    lo = np.round(rng.uniform(-120, 100, (num, 3)) / lattice) * lattice
    lo[:, 2] = 0.0
    size = np.round(rng.uniform(0, 40, (num, 3)) / lattice) * lattice
    size[:, 2] = np.round(rng.uniform(4, 30, num))
    return lo, lo + size


def random_points(rng: np.random.Generator, num: int, lattice: float, z: tuple[float, float]) -> np.ndarray:
    xy = rng.uniform(-150, 150, (num, 2))
    snap = rng.random(num) < 0.4
    xy[snap] = np.round(xy[snap] / lattice) * lattice
    return np.column_stack([xy, rng.uniform(*z, num)])


def pair(seed: int, num_boxes: int, **options) -> tuple[ProceduralCity, BruteCity, np.random.Generator]:
    rng = np.random.default_rng(seed)
    lo, hi = random_boxes(rng, num_boxes, lattice=float(rng.choice([1.0, 5.0, 10.0])))
    return ProceduralCity.with_buildings(lo, hi, **options), BruteCity.with_buildings(lo, hi, **options), rng


@pytest.mark.filterwarnings("ignore:invalid value encountered in multiply")  # zero-length segments: 0 · inf
@settings(max_examples=40, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), num_boxes=st.integers(0, 60))
def test_segments_losses_and_outdoor_equal_the_brute_force(seed: int, num_boxes: int) -> None:
    city, brute, rng = pair(seed, num_boxes)
    p0 = random_points(rng, 300, 5.0, (0.0, 40.0))
    p1 = random_points(rng, 300, 5.0, (0.0, 40.0))
    same = rng.random(300) < 0.1  # zero-length and axis-aligned segments
    p1[same] = p0[same]
    along_y = rng.random(300) < 0.15
    p1[along_y, 0] = p0[along_y, 0]
    along_x = rng.random(300) < 0.15
    p1[along_x, 1:] = p0[along_x, 1:]
    for freq in (3.5e9, 2.1e9):
        np.testing.assert_array_equal(city.penetration_loss_db(p0, p1, freq), brute.penetration_loss_db(p0, p1, freq))
    np.testing.assert_array_equal(city._blocked(p0, p1), brute._blocked(p0, p1))
    xy = np.concatenate([p0[:, :2], city.box_lo[:, :2], city.box_hi[:, :2]])
    np.testing.assert_array_equal(city.is_outdoor(xy), brute.is_outdoor(xy))
    np.testing.assert_array_equal(city._wall_sequences(2), brute._wall_sequences(2))


@settings(max_examples=25, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), num_boxes=st.integers(1, 40), order=st.sampled_from([1, 2]))
def test_path_tables_equal_the_brute_force(seed: int, num_boxes: int, order: int) -> None:
    city, brute, rng = pair(seed, num_boxes, max_reflections=order, max_canyon_m=float(rng_canyon(seed)))
    rx = random_points(rng, 200, 5.0, (1.5, 1.5))
    tx = random_points(rng, 1, 5.0, (2.0, 45.0))[0]
    for freq in (3.5e9, 2.1e9):
        got, want = city.trace(tx, rx, freq), brute.trace(tx, rx, freq)
        assert len(want) > 0
        pd.testing.assert_frame_equal(got, want, check_exact=True)


def rng_canyon(seed: int) -> float:
    return float(np.random.default_rng(seed + 1).choice([20.0, 80.0, 200.0]))


@pytest.mark.parametrize("sites", [7, 19])
def test_grown_city_traces_equal_the_brute_force(sites: int) -> None:
    """The shipped density (7 sites) and a grown city, order 2 included, from a central roof."""
    options = grown_scene_options("city", sites, 7)
    city, brute = ProceduralCity(seed=0, **options), BruteCity(seed=0, **options)
    rng = np.random.default_rng(1)
    rx = np.column_stack([rng.uniform(-200, 200, (600, 2)), np.full(600, 1.5)])
    rx = rx[city.is_outdoor(rx[:, :2])]
    roofs = city.rooftops()
    tx = roofs[np.argmin(np.hypot(roofs[:, 0], roofs[:, 1]))] + np.array([0.0, 0.0, 3.0])
    for order in (1, 2):
        city.max_reflections = brute.max_reflections = order
        got = city.trace(tx, rx, 3.5e9)
        pd.testing.assert_frame_equal(got, brute.trace(tx, rx, 3.5e9), check_exact=True)
        assert {"LOS", "T", "R", "RT", "R" * order} <= set(got["interactions"])


def test_box_order_sums_equal_row_sums_over_every_box() -> None:
    """Sparse values summed as numpy sums whole rows (pairwise, by position), in chunks of rows too."""
    rng = np.random.default_rng(0)
    num_seg, num_boxes = 500, 3000  # 2 000 000 // 3 000 = 666 rows a chunk: several chunks
    dense = np.where(rng.random((num_seg, num_boxes)) < 0.01, rng.random((num_seg, num_boxes)) * 1e3, 0.0)
    dense[:50] = 0.0
    dense[50:100, :] = 0.0
    dense[50:100, 7] = 1.0 / 3.0  # one term
    seg, box = np.nonzero(dense > 0)
    # listed boxes the segment does not enter: zeros
    extra_seg, extra_box = rng.integers(0, num_seg, 200), rng.integers(0, num_boxes, 200)
    free = dense[extra_seg, extra_box] == 0
    seg = np.concatenate([seg, extra_seg[free]])
    box = np.concatenate([box, extra_box[free]])
    value = dense[seg, box]
    got = _box_order_sums(seg, box, value, num_seg, num_boxes)
    np.testing.assert_array_equal(got, dense.sum(-1))
    assert (np.count_nonzero(dense, axis=1) > 2).sum() > 100


def test_cell_grid_queries_list_every_touching_item() -> None:
    """Segments, rectangles and points against random rectangles: every item that meets the query is listed."""
    rng = np.random.default_rng(3)
    lo = rng.uniform(-100, 100, (80, 2))
    hi = lo + rng.uniform(0, 20, (80, 2))
    grid = CellGrid(lo, hi, 7.0)
    a, b = rng.uniform(-130, 130, (400, 2)), rng.uniform(-130, 130, (400, 2))
    b[:40, 0] = a[:40, 0]  # along y
    b[40:80, 1] = a[40:80, 1]  # along x
    seg, item = grid.unique_items(*grid.segment_cells(a, b))
    listed = np.zeros((400, 80), dtype=bool)
    listed[seg, item] = True
    a3, b3 = np.column_stack([a, np.zeros(400)]), np.column_stack([b, np.zeros(400)])
    t_in, t_out = segment_box_overlap(
        a3, b3, np.column_stack([lo, np.full(80, -1.0)]), np.column_stack([hi, np.full(80, 1.0)])
    )
    touch = t_out >= t_in
    assert touch.sum() > 100 and not (touch & ~listed).any()
    assert listed.sum() < 0.5 * listed.size  # the index prunes
    r_lo, r_hi = rng.uniform(-120, 100, (100, 2)), None
    r_hi = r_lo + rng.uniform(0, 30, (100, 2))
    rect, item = grid.unique_items(*grid.rect_cells(r_lo, r_hi))
    listed = np.zeros((100, 80), dtype=bool)
    listed[rect, item] = True
    meets = np.all((r_lo[:, None] <= hi[None]) & (r_hi[:, None] >= lo[None]), axis=-1)
    assert meets.sum() > 20 and not (meets & ~listed).any()
    point, item = grid.items_of(*grid.point_cells(a))
    listed = np.zeros((400, 80), dtype=bool)
    listed[point, item] = True
    inside = np.all((a[:, None] >= lo[None]) & (a[:, None] <= hi[None]), axis=-1)
    assert inside.sum() > 5 and not (inside & ~listed).any()


def test_wedge_cells_list_every_point_whose_line_crosses_the_wall() -> None:
    rng = np.random.default_rng(4)
    pts = rng.uniform(-200, 200, (3000, 2))
    grid = CellGrid(pts, pts, 9.0)
    num = 300
    axis = rng.integers(0, 2, num)
    sign = rng.choice([-1.0, 1.0], num)
    coord = rng.uniform(-150, 150, num)
    u_lo = rng.uniform(-150, 150, num)
    u_hi = u_lo + rng.uniform(0, 40, num)
    image = rng.uniform(-250, 250, (num, 2))
    image[np.arange(num), axis] = coord - sign * rng.uniform(1e-3, 100, num)  # behind the wall
    image[np.arange(10), axis[:10]] = coord[:10] + sign[:10] * 5.0  # in front: no wedge
    k, item = grid.unique_items(*grid.wedge_cells(image, axis, coord, sign, u_lo, u_hi, margin_m=1e-6))
    listed = np.zeros((num, len(pts)), dtype=bool)
    listed[k, item] = True
    rows = np.arange(num)[:, None]
    p_a, p_u = pts[None, :, 0], pts[None, :, 1]
    p_a = np.where(axis[:, None] == 0, pts[None, :, 0], pts[None, :, 1])
    p_u = np.where(axis[:, None] == 0, pts[None, :, 1], pts[None, :, 0])
    i_a, i_u = image[rows[:, 0], axis][:, None], image[rows[:, 0], 1 - axis][:, None]
    front = sign[:, None] * (p_a - coord[:, None]) > 0
    with np.errstate(divide="ignore", invalid="ignore"):
        t = (coord[:, None] - i_a) / (p_a - i_a)
    u = i_u + t * (p_u - i_u)
    valid = front & (t > 0) & (t < 1) & (u >= u_lo[:, None]) & (u <= u_hi[:, None])
    assert valid.sum() > 1000 and not (valid & ~listed).any()
    assert not listed[:10].any()
    assert listed.sum() < 0.5 * front.sum()  # the wedge prunes
