"""A fast, dependency-free procedural city: box buildings on flat ground (SPEC §6).

:class:`ProceduralCity` implements :class:`rflscm.sim.backend.SceneBackend` for unit
tests and quick scenarios.  The scene is deterministic given its seed: axis-aligned
box buildings (concrete) on a flat ground plane at z = 0 (medium-dry ground).
``trace`` finds, vectorised over receivers:

* the direct path — line of sight, or through buildings with a penetration loss
  (walls crossed × per-wall loss + interior loss per metre, TR 38.901 §7.4.3);
* the ground reflection (image method), also penetrating when blocked;
* specular wall reflections of order 1 (and 2 with ``max_reflections=2``) by the
  image method; reflected paths must be unobstructed;

each with the free-space amplitude (λ / 4πd)² over the unfolded length d and
Fresnel power reflection coefficients of ITU-R P.2040 materials.  There is no
diffraction, so deep shadows are lit only by penetration.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import pandas as pd

from rflscm.antenna import SPEED_OF_LIGHT
from rflscm.errors import ConfigError
from rflscm.sim.backend import PATH_COLUMNS, empty_path_table
from rflscm.sim.grid_index import CellGrid

ASPRS_GROUND, ASPRS_BUILDING = 2, 6
_EPS_M = 1e-3  # a segment must run this far inside a box to count as blocked [m]
_SEGMENTS_PER_CHUNK = 16_384  # segments tested against the box index at once
_PAIRS_PER_CHUNK = 1_000_000  # (wall sequence, receiver) candidates traced at once
_MAX_GRID_CELLS_PER_SIDE = 1024  # the index cells grow beyond the median building side to stay within this


# ---- materials (ITU-R P.2040-1 Table 3) -----------------------------------------------------------
@dataclass(frozen=True)
class Material:
    """ITU-R P.2040 material: ε_r' = a·f^b, σ = c·f^d [S/m], f in GHz (P.2040-1 eqs. (28), (29))."""

    name: str
    a: float
    b: float
    c: float
    d: float

    def permittivity(self, freq_hz: float) -> complex:
        """Complex relative permittivity η = ε_r' − j σ/(ε₀ω) = ε_r' − j 17.98 σ/f_GHz (P.2040-1 eq. (9b)).

        Real ε_r' and conductivity σ [S/m] from the material's (a, b, c, d) at ``freq_hz`` [Hz].
        """
        f_ghz = freq_hz / 1e9
        return complex(self.a * f_ghz**self.b, -17.98 * self.c * f_ghz**self.d / f_ghz)


MATERIALS: dict[str, Material] = {
    m.name: m
    for m in (
        Material("concrete", 5.24, 0.0, 0.0462, 0.7822),
        Material("brick", 3.91, 0.0, 0.0238, 0.16),
        Material("glass", 6.31, 0.0, 0.0036, 1.3394),
        Material("wood", 1.99, 0.0, 0.0047, 1.0718),
        Material("medium_dry_ground", 15.0, -0.1, 0.035, 1.63),
        Material("very_dry_ground", 3.0, 0.0, 0.00015, 2.52),
        Material("wet_ground", 30.0, -0.4, 0.15, 1.30),
    )
}


def fresnel_coefficients(cos_theta: np.ndarray, eta: complex) -> tuple[np.ndarray, np.ndarray]:
    """Fresnel reflection coefficients ``(R_TE, R_TM)`` (complex, shape of ``cos_theta``).

    ``cos_theta`` is the cosine of the incidence angle from the surface normal and
    ``eta`` the complex relative permittivity (non-magnetic medium; ITU-R P.2040-1 eq. (31)).
    """
    cos_t = np.clip(np.abs(np.asarray(cos_theta, dtype=np.float64)), 0.0, 1.0)
    root = np.sqrt(eta - (1.0 - cos_t**2) + 0j)
    r_te = (cos_t - root) / (cos_t + root)
    r_tm = (eta * cos_t - root) / (eta * cos_t + root)
    return r_te, r_tm


def reflection_power(k_in: np.ndarray, normal: np.ndarray, eta: complex) -> np.ndarray:
    """Power reflection coefficient ``[...]`` of a vertically polarised wave.

    ``k_in [..., 3]``: unit propagation direction onto the surface; ``normal [..., 3]``:
    unit surface normal.  The vertical field is split into its TE (perpendicular to the
    plane of incidence) and TM parts: |Γ|² = f_TE |R_TE|² + (1 − f_TE) |R_TM|².  The
    ground (horizontal) is pure TM, a wall seen horizontally pure TE.
    """
    cos_t = np.abs(np.sum(k_in * normal, axis=-1))
    r_te, r_tm = fresnel_coefficients(cos_t, eta)
    e_vert = np.array([0.0, 0.0, 1.0]) - k_in[..., 2:3] * k_in  # vertical field ⟂ k
    s_perp = np.cross(k_in, normal)  # normal of the plane of incidence
    num = np.sum(e_vert * s_perp, axis=-1) ** 2
    den = np.sum(e_vert**2, axis=-1) * np.sum(s_perp**2, axis=-1)
    f_te = np.where(den > 1e-12, num / np.maximum(den, 1e-300), 0.5)
    return f_te * np.abs(r_te) ** 2 + (1.0 - f_te) * np.abs(r_tm) ** 2


def wall_loss_db(freq_hz: float) -> float:
    """Penetration loss of one concrete wall [dB], TR 38.901 Table 7.4.3-1: 5 + 4 f_GHz."""
    return 5.0 + 4.0 * freq_hz / 1e9


# ---- segment / box geometry -------------------------------------------------------------------------
def segment_box_overlap(
    p0: np.ndarray, p1: np.ndarray, lo: np.ndarray, hi: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Slab test of segments against axis-aligned boxes.

    Args:
        p0, p1: segment ends ``[num_seg, 3]`` [m].
        lo, hi: box corners ``[num_boxes, 3]`` [m].

    Returns:
        ``(t_in, t_out)`` ``[num_seg, num_boxes]``: the segment parameters (0…1) where it
        enters and leaves each box; the segment crosses box b where ``t_out > t_in``.
    """
    return _slab(p0[:, None], (p1 - p0)[:, None, :], lo[None], hi[None])


def _slab(p0: np.ndarray, d: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(t_in, t_out)`` of segments ``p0 → p0 + d`` against boxes ``lo … hi`` (all ``[..., 3]``, broadcast):
    :func:`segment_box_overlap` for every pair, or for listed (segment, box) pairs with the same arithmetic."""
    with np.errstate(divide="ignore", invalid="ignore"):
        inv = 1.0 / d
        t0 = (lo - p0) * inv
        t1 = (hi - p0) * inv
    parallel = np.abs(d) < 1e-12
    inside = (p0 >= lo) & (p0 <= hi)
    t_lo = np.where(parallel, np.where(inside, -np.inf, np.inf), np.minimum(t0, t1))
    t_hi = np.where(parallel, np.where(inside, np.inf, -np.inf), np.maximum(t0, t1))
    t_in = np.maximum(t_lo.max(axis=-1), 0.0)
    t_out = np.minimum(t_hi.min(axis=-1), 1.0)
    return t_in, t_out


def _chunks(n: int, size: int):
    for start in range(0, n, size):
        yield slice(start, min(start + size, n))


@dataclass(frozen=True)
class _Walls:
    """Vertical wall rectangles of the boxes, ``[num_walls]`` each."""

    axis: np.ndarray  # 0: wall ⟂ x, 1: wall ⟂ y
    coord: np.ndarray  # wall plane position along `axis` [m]
    sign: np.ndarray  # outward normal = sign · e_axis
    u_lo: np.ndarray  # extent along the other horizontal axis [m]
    u_hi: np.ndarray
    height: np.ndarray  # top z [m]
    box: np.ndarray  # owning box

    @classmethod
    def of_boxes(cls, lo: np.ndarray, hi: np.ndarray) -> _Walls:
        rows = []
        for b in range(len(lo)):
            for axis in (0, 1):
                other = 1 - axis
                for sign, coord in ((-1.0, lo[b, axis]), (1.0, hi[b, axis])):
                    rows.append((axis, coord, sign, lo[b, other], hi[b, other], hi[b, 2], b))
        arr = np.array(rows, dtype=np.float64).reshape(-1, 7)
        return cls(arr[:, 0].astype(int), arr[:, 1], arr[:, 2], arr[:, 3], arr[:, 4], arr[:, 5], arr[:, 6].astype(int))

    def __len__(self) -> int:
        return len(self.coord)

    def normals(self, idx: np.ndarray) -> np.ndarray:
        n = np.zeros((len(idx), 3))
        n[np.arange(len(idx)), self.axis[idx]] = self.sign[idx]
        return n

    def mirror(self, points: np.ndarray, idx: np.ndarray) -> np.ndarray:
        """Mirror images ``[len(idx), 3]`` of ``points [len(idx), 3]`` across walls ``idx``."""
        out = points.copy()
        rows = np.arange(len(idx))
        out[rows, self.axis[idx]] = 2.0 * self.coord[idx] - points[rows, self.axis[idx]]
        return out


# ---- the scene ----------------------------------------------------------------------------------------
PROCEDURAL_SCENES: dict[str, dict] = {
    "city": {},
    "small": {"size_m": 200.0, "num_buildings": 10},
    "ground": {"num_buildings": 0},
    "free_space": {"num_buildings": 0, "ground_reflection": False},
}
"""Named presets of :class:`ProceduralCity` keyword arguments (``rflscm simulate --scene``)."""
DEFAULT_SIZE_M = 400.0
DEFAULT_NUM_BUILDINGS = 40


def grown_scene_options(scene: str, num_sites: int, base_sites: int) -> dict[str, float | int]:
    """``size_m`` and ``num_buildings`` of preset ``scene`` grown from ``base_sites`` to ``num_sites`` at the
    preset's density: the area and the building count in proportion to the sites (side × √(N / base)).
    Empty (the preset as it is) up to ``base_sites``."""
    if scene not in PROCEDURAL_SCENES:
        raise ConfigError(f"unknown procedural scene {scene!r}; valid: {', '.join(PROCEDURAL_SCENES)}.")
    if num_sites <= base_sites:
        return {}
    factor = num_sites / base_sites
    preset = {"size_m": DEFAULT_SIZE_M, "num_buildings": DEFAULT_NUM_BUILDINGS, **PROCEDURAL_SCENES[scene]}
    return {
        "size_m": float(preset["size_m"]) * math.sqrt(factor),
        "num_buildings": round(preset["num_buildings"] * factor),
    }


class ProceduralCity:
    """Box buildings on flat ground, traced with LOS/penetration, ground and wall reflections.

    Args:
        seed: building layout seed (the same seed gives the same city).
        size_m: side of the square scene centred on the origin [m].
        num_buildings: buildings placed (fewer if they do not fit; 0 = no buildings).
        footprint_m: (min, max) building side [m].
        height_m: (min, max) building height [m].
        street_m: minimum gap between buildings [m].
        ground_reflection: trace the ground-reflected path.
        max_reflections: 0, 1 or 2 orders of specular wall reflections (order 2: street canyons).
        max_canyon_m: widest street across which double wall bounces are traced [m].
        penetration: let blocked direct/ground paths through walls with a loss (else drop them).
        interior_loss_db_per_m: loss inside a building (TR 38.901 §7.4.3.1: 0.5 dB/m).
        wall_material, ground_material: keys of :data:`MATERIALS`.
    """

    name = "procedural"

    def __init__(
        self,
        seed: int = 0,
        size_m: float = DEFAULT_SIZE_M,
        num_buildings: int = DEFAULT_NUM_BUILDINGS,
        footprint_m: tuple[float, float] = (15.0, 45.0),
        height_m: tuple[float, float] = (10.0, 35.0),
        street_m: float = 12.0,
        ground_reflection: bool = True,
        max_reflections: int = 1,
        max_canyon_m: float = 80.0,
        penetration: bool = True,
        interior_loss_db_per_m: float = 0.5,
        wall_material: str = "concrete",
        ground_material: str = "medium_dry_ground",
    ) -> None:
        for key, mat in (("wall_material", wall_material), ("ground_material", ground_material)):
            if mat not in MATERIALS:
                raise ConfigError(f"`{key}` must be one of {', '.join(MATERIALS)} (got {mat!r}).")
        if max_reflections not in (0, 1, 2):
            raise ConfigError(f"`max_reflections` must be 0, 1 or 2 (got {max_reflections!r}).")
        if size_m <= 0 or num_buildings < 0 or footprint_m[0] <= 0 or footprint_m[1] < footprint_m[0]:
            raise ConfigError(
                f"procedural city needs size_m > 0, num_buildings >= 0 and 0 < footprint min <= max "
                f"(got {size_m}, {num_buildings}, {footprint_m})."
            )
        if height_m[0] <= 0 or height_m[1] < height_m[0]:
            raise ConfigError(f"`height_m` must be (min, max) with 0 < min <= max (got {height_m}).")
        self.seed = int(seed)
        self.size_m = float(size_m)
        self.ground_reflection = bool(ground_reflection)
        self.max_reflections = int(max_reflections)
        self.max_canyon_m = float(max_canyon_m)
        self.penetration = bool(penetration)
        self.interior_loss_db_per_m = float(interior_loss_db_per_m)
        self.wall_material = MATERIALS[wall_material]
        self.ground_material = MATERIALS[ground_material]
        self._set_boxes(
            *_place_buildings(
                np.random.default_rng(self.seed), self.size_m, int(num_buildings), footprint_m, height_m, street_m
            )
        )

    def _set_boxes(self, box_lo: np.ndarray, box_hi: np.ndarray) -> None:
        """The buildings, their walls and the x/y grid index of both (:mod:`rflscm.sim.grid_index`)."""
        self.box_lo = np.asarray(box_lo, dtype=np.float64).reshape(-1, 3)
        self.box_hi = np.asarray(box_hi, dtype=np.float64).reshape(-1, 3)
        self._walls = _Walls.of_boxes(self.box_lo, self.box_hi)
        w = self._walls
        self._wall_of = np.full((len(self.box_lo), 2, 2), -1, dtype=np.int64)  # [box, axis, outward sign > 0]
        self._wall_of[w.box, w.axis, (w.sign > 0).astype(int)] = np.arange(len(w))
        if len(self.box_lo):
            side = float(np.median(self.box_hi[:, :2] - self.box_lo[:, :2]))
            self._cell_m = _cell_size(self.box_lo[:, :2], self.box_hi[:, :2], side)
            self._boxes = CellGrid(self.box_lo[:, :2], self.box_hi[:, :2], self._cell_m)

    @classmethod
    def from_scene(cls, scene: str, seed: int = 0, **overrides) -> ProceduralCity:
        """A preset of :data:`PROCEDURAL_SCENES` with keyword ``overrides``."""
        if scene not in PROCEDURAL_SCENES:
            raise ConfigError(f"unknown procedural scene {scene!r}; valid: {', '.join(PROCEDURAL_SCENES)}.")
        return cls(seed=seed, **{**PROCEDURAL_SCENES[scene], **overrides})

    @classmethod
    def with_buildings(cls, box_lo: np.ndarray, box_hi: np.ndarray, **options) -> ProceduralCity:
        """A scene with the given boxes ``lo [n, 3]``, ``hi [n, 3]`` [m] (z from 0) instead of random ones."""
        city = cls(num_buildings=0, **options)
        city._set_boxes(box_lo, box_hi)
        return city

    @property
    def num_buildings(self) -> int:
        return len(self.box_lo)

    # ---- SceneBackend: scene queries --------------------------------------------------------------
    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        half = self.size_m / 2
        top = float(self.box_hi[:, 2].max()) if self.num_buildings else 0.0
        return np.array([-half, -half, 0.0]), np.array([half, half, top])

    def rooftops(self) -> np.ndarray:
        """Roof centres ``[num_buildings, 3]`` (z = roof height) [m]."""
        centre = 0.5 * (self.box_lo + self.box_hi)
        return np.column_stack([centre[:, :2], self.box_hi[:, 2]])

    def ground_height(self, xy: np.ndarray) -> np.ndarray:
        return np.zeros(len(np.asarray(xy).reshape(-1, 2)))

    def is_outdoor(self, xy: np.ndarray) -> np.ndarray:
        xy = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
        out = np.ones(len(xy), dtype=bool)
        if not self.num_buildings:
            return out
        point, box = self._boxes.items_of(*self._boxes.point_cells(xy))
        inside = np.all((xy[point] >= self.box_lo[box, :2]) & (xy[point] <= self.box_hi[box, :2]), axis=1)
        out[point[inside]] = False
        return out

    def sample_point_cloud(self, points_per_m2: float, noise_std_m: float, seed: int) -> tuple[np.ndarray, np.ndarray]:
        """Uniform random points on the outdoor ground, roofs and walls, plus Gaussian noise [m]."""
        if not points_per_m2 > 0 or not noise_std_m >= 0:
            raise ConfigError(
                f"`points_per_m2` must be > 0 and `noise_std_m` >= 0 (got {points_per_m2}, {noise_std_m})."
            )
        rng = np.random.default_rng(seed)
        half = self.size_m / 2
        ground = rng.uniform(-half, half, (rng.poisson(points_per_m2 * self.size_m**2), 2))
        ground = ground[self.is_outdoor(ground)]
        ground = np.column_stack([ground, np.zeros(len(ground))])
        parts, classes = [ground], [np.full(len(ground), ASPRS_GROUND)]
        size = self.box_hi - self.box_lo
        faces = []  # (origin, edge u, edge v) of roofs and walls
        for b in range(self.num_buildings):
            lo, hi, (dx, dy, dz) = self.box_lo[b], self.box_hi[b], size[b]
            faces.append((np.array([lo[0], lo[1], hi[2]]), np.array([dx, 0, 0]), np.array([0, dy, 0])))
            for x in (lo[0], hi[0]):
                faces.append((np.array([x, lo[1], 0.0]), np.array([0, dy, 0]), np.array([0, 0, dz])))
            for y in (lo[1], hi[1]):
                faces.append((np.array([lo[0], y, 0.0]), np.array([dx, 0, 0]), np.array([0, 0, dz])))
        for origin, eu, ev in faces:
            n = rng.poisson(points_per_m2 * np.linalg.norm(eu) * np.linalg.norm(ev))
            uv = rng.random((n, 2))
            parts.append(origin + uv[:, :1] * eu + uv[:, 1:] * ev)
            classes.append(np.full(n, ASPRS_BUILDING))
        xyz = np.concatenate(parts)
        return xyz + rng.normal(0.0, noise_std_m, xyz.shape), np.concatenate(classes).astype(np.uint8)

    # ---- SceneBackend: tracing --------------------------------------------------------------------
    def trace(self, tx_position: np.ndarray, rx_positions: np.ndarray, freq_hz: float, seed: int = 0) -> pd.DataFrame:
        """Paths from ``tx_position [3]`` to ``rx_positions [num_rx, 3]`` at ``freq_hz`` [Hz].

        Deterministic (``seed`` is accepted for the protocol and unused).  Returns a path
        table (:mod:`rflscm.sim.backend`) sorted by receiver and delay.
        """
        tx = np.asarray(tx_position, dtype=np.float64).reshape(3)
        rx = np.asarray(rx_positions, dtype=np.float64).reshape(-1, 3)
        if not freq_hz > 0:
            raise ConfigError(f"`freq_hz` must be > 0 (got {freq_hz}).")
        wavelength = SPEED_OF_LIGHT / freq_hz
        tables = [empty_path_table(), self._direct(tx, rx, freq_hz, wavelength)]
        if self.ground_reflection:
            tables.append(self._ground(tx, rx, freq_hz, wavelength))
        for order in range(1, self.max_reflections + 1):
            if self.num_buildings:
                tables.append(self._walls_order(tx, rx, freq_hz, wavelength, order))
        table = pd.concat([t for t in tables if len(t)] or tables[:1], ignore_index=True).astype(PATH_COLUMNS)
        return table.sort_values(["rx_index", "delay_s"], kind="stable", ignore_index=True)

    def penetration_loss_db(self, p0: np.ndarray, p1: np.ndarray, freq_hz: float) -> np.ndarray:
        """Loss ``[num_seg]`` [dB] of segments ``p0 → p1`` ``[num_seg, 3]`` through the buildings:
        walls crossed × :func:`wall_loss_db` + interior length × ``interior_loss_db_per_m``.

        Only the boxes the grid index lists for a segment are tested; the per-box lengths are summed as a
        sum over every box in box order would (exactly: see :func:`_box_order_sums`)."""
        if not self.num_buildings or len(p0) == 0:
            return np.zeros(len(p0))
        length = np.linalg.norm(p1 - p0, axis=-1)
        loss = np.zeros(len(p0))
        for sl in _chunks(len(p0), _SEGMENTS_PER_CHUNK):
            seg, box, t_in, t_out = self._overlaps(p0[sl], p1[sl], unique=True)
            inside_m = np.maximum(t_out - t_in, 0.0) * length[sl][seg]
            crossed = inside_m > _EPS_M
            walls = crossed * ((t_in > 1e-9).astype(float) + (t_out < 1 - 1e-9))
            num = sl.stop - sl.start
            wall_count = np.bincount(seg, weights=walls, minlength=num)  # whole numbers: exact in any order
            inside = _box_order_sums(seg, box, inside_m, num, self.num_buildings)
            loss[sl] = wall_count * wall_loss_db(freq_hz) + inside * self.interior_loss_db_per_m
        return loss

    def _blocked(self, p0: np.ndarray, p1: np.ndarray) -> np.ndarray:
        """True ``[num_seg]`` where the segment runs through a building."""
        if not self.num_buildings or len(p0) == 0:
            return np.zeros(len(p0), dtype=bool)
        length = np.linalg.norm(p1 - p0, axis=-1)
        out = np.zeros(len(p0), dtype=bool)
        for sl in _chunks(len(p0), _SEGMENTS_PER_CHUNK):
            seg, _, t_in, t_out = self._overlaps(p0[sl], p1[sl], unique=False)
            hit = (t_out - t_in) * length[sl][seg] > _EPS_M
            out[sl.start + seg[hit]] = True
        return out

    def _overlaps(
        self, p0: np.ndarray, p1: np.ndarray, unique: bool
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """``(segment, box, t_in, t_out)`` of :func:`segment_box_overlap` for the (segment, box) pairs whose
        x/y grid cells meet (every pair that overlaps at all, and some that do not); ``unique``: each pair
        once, sorted by segment then box (else a box spanning several cells of a segment comes again)."""
        seg, cell = self._boxes.segment_cells(p0, p1)
        seg, box = self._boxes.unique_items(seg, cell) if unique else self._boxes.items_of(seg, cell)
        t_in, t_out = _slab(p0[seg], (p1 - p0)[seg], self.box_lo[box], self.box_hi[box])
        return seg, box, t_in, t_out

    def _table(self, rx_index, power, first_hop, length, labels) -> pd.DataFrame:
        direction = first_hop / np.linalg.norm(first_hop, axis=-1, keepdims=True)
        return pd.DataFrame(
            {
                "rx_index": rx_index.astype(np.int64),
                "power_lin": power,
                "aod_el_rad": np.arcsin(np.clip(direction[:, 2], -1.0, 1.0)),
                "aod_az_rad": np.arctan2(direction[:, 1], direction[:, 0]),
                "delay_s": length / SPEED_OF_LIGHT,
                "interactions": labels,
            }
        )

    def _direct(self, tx, rx, freq_hz, wavelength) -> pd.DataFrame:
        txs = np.broadcast_to(tx, rx.shape)
        length = np.linalg.norm(rx - tx, axis=-1)
        loss_db = self.penetration_loss_db(txs, rx, freq_hz)
        keep = (loss_db == 0) | self.penetration
        power = (wavelength / (4 * np.pi * length)) ** 2 * 10.0 ** (-loss_db / 10.0)  # Friis
        labels = np.where(loss_db > 0, "T", "LOS")
        idx = np.flatnonzero(keep & (length > 0))
        return self._table(idx, power[idx], (rx - tx)[idx], length[idx], labels[idx])

    def _ground(self, tx, rx, freq_hz, wavelength) -> pd.DataFrame:
        h_t, h_r = tx[2], rx[:, 2]
        ok = (h_t > 0) & (h_r > 0)
        frac = h_t / (h_t + h_r)  # reflection point along the horizontal projection
        point = tx + frac[:, None] * (rx - tx)
        point[:, 2] = 0.0
        image = np.array([tx[0], tx[1], -tx[2]])
        length = np.linalg.norm(rx - image, axis=-1)
        k_in = (point - tx) / np.maximum(np.linalg.norm(point - tx, axis=-1, keepdims=True), 1e-12)
        gamma2 = reflection_power(k_in, np.array([0.0, 0.0, 1.0]), self.ground_material.permittivity(freq_hz))
        txs = np.broadcast_to(tx, rx.shape)
        loss_db = self.penetration_loss_db(txs, point, freq_hz) + self.penetration_loss_db(point, rx, freq_hz)
        keep = ok & ((loss_db == 0) | self.penetration)
        power = (wavelength / (4 * np.pi * length)) ** 2 * gamma2 * 10.0 ** (-loss_db / 10.0)
        labels = np.where(loss_db > 0, "RT", "R")
        idx = np.flatnonzero(keep)
        return self._table(idx, power[idx], (point - tx)[idx], length[idx], labels[idx])

    def _wall_sequences(self, order: int) -> np.ndarray:
        """Candidate wall sequences ``[num_seq, order]`` for the image method, sorted.

        Order 2 keeps the street-canyon double bounces: pairs of parallel walls of different
        buildings that face each other across at most ``max_canyon_m`` with overlapping extents
        (found through the grid index: the boxes in front of a wall, within the canyon width).
        """
        w = self._walls
        n = len(w)
        if order == 1:
            return np.arange(n)[:, None]
        if n == 0:
            return np.zeros((0, 2), dtype=np.int64)
        far = w.coord + w.sign * self.max_canyon_m
        span = np.stack([np.minimum(w.coord, far), np.maximum(w.coord, far)], axis=1)  # along the normal
        along = np.stack([w.u_lo, w.u_hi], axis=1)
        lo = np.where(
            w.axis[:, None] == 0, np.stack([span[:, 0], along[:, 0]], 1), np.stack([along[:, 0], span[:, 0]], 1)
        )
        hi = np.where(
            w.axis[:, None] == 0, np.stack([span[:, 1], along[:, 1]], 1), np.stack([along[:, 1], span[:, 1]], 1)
        )
        a, box = self._boxes.unique_items(*self._boxes.rect_cells(lo, hi))
        b = self._wall_of[box, w.axis[a], (w.sign[a] < 0).astype(int)]  # box's wall facing back at wall a
        gap = w.sign[a] * (w.coord[b] - w.coord[a])  # b lies this far in front of a
        facing = (w.axis[a] == w.axis[b]) & (w.sign[a] == -w.sign[b]) & (gap > 0) & (gap <= self.max_canyon_m)
        overlap = np.minimum(w.u_hi[a], w.u_hi[b]) - np.maximum(w.u_lo[a], w.u_lo[b]) > 0
        keep = facing & overlap & (w.box[a] != w.box[b])
        key = np.unique(a[keep] * n + b[keep])
        return np.stack([key // n, key % n], axis=1)

    def _walls_order(self, tx, rx, freq_hz, wavelength, order: int) -> pd.DataFrame:
        """Specular reflections off ``order`` walls (image method), unobstructed legs only.

        The receivers of a wall sequence are those the grid index of the receivers lists in the wedge of its
        last image through its last wall (a superset of those whose reflection point falls on that wall)."""
        w, seqs = self._walls, self._wall_sequences(order)
        first = seqs[:, 0]
        seqs = seqs[w.sign[first] * (tx[w.axis[first]] - w.coord[first]) > 1e-6]  # tx in front of wall 1
        eta = self.wall_material.permittivity(freq_hz)
        out = [empty_path_table()]
        if len(rx) == 0 or len(seqs) == 0:
            return out[0]
        receivers = CellGrid(rx[:, :2], rx[:, :2], _cell_size(rx[:, :2], rx[:, :2], self._cell_m))
        images = [np.broadcast_to(tx, (len(seqs), 3))]
        for j in range(order):
            images.append(w.mirror(images[-1], seqs[:, j]))
        for sl in _chunks(len(seqs), 4096):
            last = seqs[sl, -1]
            k, cell = receivers.wedge_cells(
                images[-1][sl], w.axis[last], w.coord[last], w.sign[last], w.u_lo[last], w.u_hi[last], margin_m=1e-6
            )
            s_idx, r_idx = receivers.unique_items(k, cell)  # sorted by sequence, then receiver
            s_idx += sl.start
            last = seqs[s_idx, -1]
            front = w.sign[last] * (rx[r_idx, w.axis[last]] - w.coord[last])
            s_idx, r_idx = s_idx[front > 1e-6], r_idx[front > 1e-6]  # receiver in front of the last wall
            for part in _chunks(len(s_idx), _PAIRS_PER_CHUNK):
                out.append(self._reflect_pairs(tx, rx, seqs, images, s_idx[part], r_idx[part], eta, wavelength))
        return pd.concat([t for t in out if len(t)] or out, ignore_index=True)

    def _reflect_pairs(self, tx, rx, seqs, images, s_idx, r_idx, eta, wavelength) -> pd.DataFrame:
        """Reflections for the candidate (wall sequence ``s_idx``, receiver ``r_idx``) pairs: ``seqs [num_seq,
        order]`` with their images ``images[j] [num_seq, 3]`` (``images[0]`` the transmitter)."""
        w, order = self._walls, seqs.shape[1]
        hops = [rx[r_idx]]  # hops from the receiver backwards: P_order+1 = rx, P_order, …, P_1
        for j in range(order - 1, -1, -1):
            wall, image, target = seqs[s_idx, j], images[j + 1][s_idx], hops[-1]
            rows = np.arange(len(wall))
            a_img, a_tgt = image[rows, w.axis[wall]], target[rows, w.axis[wall]]
            ok = w.sign[wall] * (a_tgt - w.coord[wall]) > 1e-6  # target in front of this wall
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
        hops = [np.broadcast_to(tx, (len(s_idx), 3)), *hops[::-1]]  # tx, P_1, …, P_order, rx
        blocked = np.zeros(len(s_idx), dtype=bool)
        gamma2 = np.ones(len(s_idx))
        for j in range(len(hops) - 1):  # a leg is tested only where no earlier leg is blocked
            open_ = np.flatnonzero(~blocked)
            blocked[open_] = self._blocked(hops[j][open_], hops[j + 1][open_])
        for j in range(order):
            k_in = hops[j + 1] - hops[j]
            k_in /= np.linalg.norm(k_in, axis=-1, keepdims=True)
            gamma2 *= reflection_power(k_in, w.normals(seqs[s_idx, j]), eta)
        length = np.linalg.norm(rx[r_idx] - images[-1][s_idx], axis=-1)
        keep = ~blocked
        power = (wavelength / (4 * np.pi * length)) ** 2 * gamma2
        labels = np.full(len(s_idx), "R" * order)
        return self._table(r_idx[keep], power[keep], (hops[1] - hops[0])[keep], length[keep], labels[keep])


def _cell_size(lo: np.ndarray, hi: np.ndarray, side_m: float) -> float:
    """Side of the grid index's cells [m]: ``side_m`` (the median building side), larger where the items'
    extent would need more than :data:`_MAX_GRID_CELLS_PER_SIDE` cells along x or y."""
    extent = float((hi.max(axis=0) - lo.min(axis=0)).max()) if len(lo) else 0.0
    return max(side_m, extent / _MAX_GRID_CELLS_PER_SIDE, 1e-3)


def _box_order_sums(seg: np.ndarray, box: np.ndarray, value: np.ndarray, num_seg: int, num_boxes: int) -> np.ndarray:
    """Per segment, the sum ``[num_seg]`` of ``value`` over its listed boxes, equal bit for bit to the sum
    over a row of every box in box order, zeros where not listed (what the whole-scene slab test summed).

    Adding zeros is exact and a sum of at most two non-zero terms does not depend on the order, so segments
    with ≤ 2 non-zero terms are summed directly; the others are scattered into rows of zeros in box order and
    summed as rows, as numpy summed them (its pairwise summation groups terms by position)."""
    nonzero = value != 0
    count = np.bincount(seg[nonzero], minlength=num_seg)
    out = np.bincount(seg[nonzero], weights=value[nonzero], minlength=num_seg)
    many = np.flatnonzero(count > 2)
    if len(many):
        row_of = np.full(num_seg, -1)
        row_of[many] = np.arange(len(many))
        sel = np.flatnonzero(nonzero & (row_of[seg] >= 0))
        for part in _chunks(len(many), max(1, 2_000_000 // max(num_boxes, 1))):
            in_part = sel[(row_of[seg[sel]] >= part.start) & (row_of[seg[sel]] < part.stop)]
            dense = np.zeros((part.stop - part.start, num_boxes))
            dense[row_of[seg[in_part]] - part.start, box[in_part]] = value[in_part]
            out[many[part]] = dense.sum(-1)
    return out


def _place_buildings(rng, size_m, num, footprint_m, height_m, street_m) -> tuple[np.ndarray, np.ndarray]:
    """Random non-overlapping boxes ``(lo [n, 3], hi [n, 3])`` at least ``street_m`` apart."""
    half = size_m / 2
    lo_list: list[np.ndarray] = []
    hi_list: list[np.ndarray] = []
    for _ in range(50 * num):
        if len(lo_list) == num:
            break
        w, d = rng.uniform(*footprint_m, size=2)
        h = rng.uniform(*height_m)
        if w >= size_m or d >= size_m:
            continue
        x0 = rng.uniform(-half, half - w)
        y0 = rng.uniform(-half, half - d)
        lo, hi = np.array([x0, y0, 0.0]), np.array([x0 + w, y0 + d, h])
        if lo_list:
            los, his = np.array(lo_list), np.array(hi_list)
            apart = (lo[:2] >= his[:, :2] + street_m) | (hi[:2] <= los[:, :2] - street_m)
            if not apart.any(axis=1).all():
                continue
        lo_list.append(lo)
        hi_list.append(hi)
    if not lo_list:
        return np.zeros((0, 3)), np.zeros((0, 3))
    return np.array(lo_list), np.array(hi_list)
