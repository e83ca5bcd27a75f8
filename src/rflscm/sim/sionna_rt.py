"""Sionna RT 2.x backend (SPEC §6): the city scenes that ship with Sionna RT.

The scene meshes are rasterised once into ground/roof height maps, so that
``ground_height``/``is_outdoor`` are array look-ups; ``trace`` runs Sionna's
``PathSolver`` (shoot-and-bounce + image method) with isotropic antennas.
Needs the ``rt`` extra; on CPU, Dr.Jit's LLVM backend needs LLVM >= 17 (Debian:
``libllvm19``), and ``DRJIT_LIBLLVM_PATH`` is pointed at it when unset.
"""

from __future__ import annotations

import glob
import importlib.util
import os
from collections.abc import Callable
from pathlib import Path
from types import ModuleType

import numpy as np
import pandas as pd
from scipy import ndimage

from rflscm.errors import ConfigError, DataError
from rflscm.sim.backend import PATH_COLUMNS, empty_path_table

INSTALL_HINT = (
    "install the ray-tracing extra with `pip install -e .[rt]` and, for the CPU "
    "(LLVM) backend, `apt-get install -y libllvm19`"
)
GROUND_NAMES = ("ground", "terrain", "plane", "floor")
"""An object whose name contains one of these (any case) is ground; all others are buildings."""
_GROUND_REGEX = "(?i)" + "|".join(GROUND_NAMES)
_VARIANTS = {"cpu": "llvm_ad_mono_polarized", "cuda": "cuda_ad_mono_polarized"}
_LLVM_GLOBS = ("/usr/lib/*/libLLVM-19.so*", "/usr/lib/llvm-19/lib/libLLVM*.so*")
_DETERMINISTIC_LANES = 30_000_000  # ~1 GB of Sionna's deterministic candidate buffer
# Sionna's InteractionType bit codes -> path-table letters (rflscm.sim.backend).
_INTERACTION_LETTERS = {1: "R", 2: "S", 4: "T", 8: "D"}
ASPRS_GROUND, ASPRS_BUILDING = 2, 6


def _sionna_scene_dir() -> Path | None:
    """Folder of Sionna RT's built-in scenes, found without importing Sionna."""
    spec = importlib.util.find_spec("sionna")
    if spec is None or not spec.submodule_search_locations:
        return None
    return Path(next(iter(spec.submodule_search_locations))) / "rt" / "scenes"


def available_scenes() -> list[str]:
    """Names of the scenes that ship with the installed Sionna RT (``munich``, ``etoile``, ...)."""
    scene_dir = _sionna_scene_dir()
    if scene_dir is None:
        raise ConfigError(f"The Sionna RT backend needs `sionna-rt`: {INSTALL_HINT}.")
    return sorted(d.name for d in scene_dir.iterdir() if (d / f"{d.name}.xml").is_file())


def _scene_file(scene: str) -> Path:
    """Built-in scene name or path to a Mitsuba XML scene -> the XML file."""
    if scene.endswith(".xml"):
        if not Path(scene).is_file():
            raise DataError(f"Scene file {scene!r} does not exist.")
        return Path(scene)
    names = available_scenes()
    if scene not in names:
        raise ConfigError(
            f"Unknown Sionna scene {scene!r}; built-in scenes are: {', '.join(names)} "
            "(or give the path of a Mitsuba .xml scene)."
        )
    folder = _sionna_scene_dir()
    assert folder is not None  # available_scenes() found it
    return folder / scene / f"{scene}.xml"


def _import_sionna(device: str) -> tuple[ModuleType, ModuleType]:
    """Import Mitsuba and Sionna RT on the variant for ``device`` ("cpu", "cuda", "auto")."""
    if device not in ("cpu", "cuda", "auto"):
        raise ConfigError(f"`device` must be 'auto', 'cpu' or 'cuda' (got {device!r}).")
    if "DRJIT_LIBLLVM_PATH" not in os.environ:
        found = sorted(p for g in _LLVM_GLOBS for p in glob.glob(g))
        if found:
            os.environ["DRJIT_LIBLLVM_PATH"] = found[0]
    try:
        import mitsuba as mi
    except ImportError as err:
        raise ConfigError(f"The Sionna RT backend needs `sionna-rt`: {INSTALL_HINT}.") from err
    wanted = [_VARIANTS["cuda"], _VARIANTS["cpu"]] if device == "auto" else [_VARIANTS[device]]
    if mi.variant() not in wanted:
        try:
            mi.set_variant(*wanted)
        except (ImportError, AttributeError, RuntimeError) as err:
            msg = f"Mitsuba variant {wanted} unavailable ({err}): {INSTALL_HINT}."
            raise ConfigError(msg) from err
    if mi.variant() == _VARIANTS["cpu"]:
        _check_llvm()
    import sionna.rt as rt

    return mi, rt


def _check_llvm() -> None:
    """Dr.Jit on LLVM < 17 aborts the process on scene load: refuse it beforehand."""
    import drjit as dr

    version = tuple(dr.detail.llvm_version())
    if version < (17,):
        raise ConfigError(
            f"Dr.Jit loaded LLVM {'.'.join(map(str, version))} but needs >= 17: {INSTALL_HINT}, "
            "or point DRJIT_LIBLLVM_PATH at libLLVM-19.so."
        )


def _scene_triangles(rt_scene) -> tuple[np.ndarray, np.ndarray]:
    """All mesh triangles ``[num_tri, 3, 3]`` [m] and whether each is ground ``[num_tri]``."""
    tris, ground = [], []
    for name, obj in rt_scene.objects.items():
        mesh = obj.mi_mesh
        vertices = np.asarray(mesh.vertex_positions_buffer(), dtype=np.float64).reshape(-1, 3)
        faces = np.asarray(mesh.faces_buffer(), dtype=np.int64).reshape(-1, 3)
        tris.append(vertices[faces])
        is_ground = any(k in name.lower() for k in GROUND_NAMES)
        ground.append(np.full(len(faces), is_ground))
    if not tris:
        raise DataError("The scene has no meshes.")
    return np.concatenate(tris), np.concatenate(ground)


def _cells_under(p: np.ndarray, shape: tuple[int, int]) -> tuple[np.ndarray, ...]:
    """Enumerate (triangle, cell) pairs of each triangle's cell bounding box.

    ``p`` ``[num_tri, 3, 2]`` are vertex xy in cell units (cell centres on integers).
    Returns ``(tri_id, iy, ix)``, each ``[num_pairs]``.
    """
    lo = np.maximum(np.ceil(p.min(axis=1)), 0).astype(np.int64)
    hi = np.minimum(np.floor(p.max(axis=1)), np.array(shape[::-1]) - 1).astype(np.int64)
    size = np.maximum(hi - lo + 1, 0)  # [num_tri, 2]  (x, y)
    count = size[:, 0] * size[:, 1]
    tri_id = np.repeat(np.arange(len(p)), count)
    local = np.arange(count.sum()) - np.repeat(np.cumsum(count) - count, count)
    ix = lo[tri_id, 0] + local % size[tri_id, 0]
    iy = lo[tri_id, 1] + local // size[tri_id, 0]
    return tri_id, iy, ix


def _rasterize_max_z(tri: np.ndarray, origin: np.ndarray, cell_m: float, shape: tuple[int, int]) -> np.ndarray:
    """Highest surface ``z`` [m] over each cell centre, ``[ny, nx]``; NaN where none.

    ``tri`` ``[num_tri, 3, 3]``; cell ``(iy, ix)`` is centred at ``origin + cell_m * (ix, iy)``.
    Vertical triangles (walls) have no footprint and are skipped.
    """
    out = np.full(shape[0] * shape[1], -np.inf)
    p = (tri[:, :, :2] - origin) / cell_m
    e1, e2 = p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]
    det = e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0]
    keep = np.flatnonzero(np.abs(det) > 1e-9)
    bbox_cells = np.prod(np.ptp(p[keep], axis=1) + 1, axis=1)
    for chunk in np.split(keep, np.flatnonzero(np.diff(np.cumsum(bbox_cells) // 2_000_000)) + 1):
        t, iy, ix = _cells_under(p[chunk], shape)
        t = chunk[t]
        d = np.stack([ix, iy], axis=1) - p[t, 0]
        u = (d[:, 0] * e2[t, 1] - d[:, 1] * e2[t, 0]) / det[t]
        v = (e1[t, 0] * d[:, 1] - e1[t, 1] * d[:, 0]) / det[t]
        inside = (u >= -1e-9) & (v >= -1e-9) & (u + v <= 1 + 1e-9)
        z = tri[t, 0, 2] + u * (tri[t, 1, 2] - tri[t, 0, 2]) + v * (tri[t, 2, 2] - tri[t, 0, 2])
        np.maximum.at(out, (iy * shape[1] + ix)[inside], z[inside])
    out[np.isinf(out)] = np.nan
    return out.reshape(shape)


def _fill_nearest(grid: np.ndarray, default: float) -> np.ndarray:
    """Replace NaN cells by the nearest finite cell (``default`` if there is none)."""
    missing = np.isnan(grid)
    if missing.all():
        return np.full_like(grid, default)
    idx = ndimage.distance_transform_edt(missing, return_distances=False, return_indices=True)
    return grid[tuple(idx)]


def _roof_candidates(
    roof_z: np.ndarray, building: np.ndarray, cell_m: float, margin_m: float, flat_tol_m: float
) -> np.ndarray:
    """One cell ``(iy, ix)`` per flat roof area, ``[num, 2]``: the point farthest from its edges.

    A cell qualifies when it is at least ``margin_m`` inside its building and the roof
    varies by at most ``flat_tol_m`` over the surrounding 3x3 cells.
    """
    z = np.where(building, roof_z, np.nan)
    z_hi = ndimage.maximum_filter(np.nan_to_num(z, nan=np.inf), size=3)
    z_lo = ndimage.minimum_filter(np.nan_to_num(z, nan=-np.inf), size=3)
    inner = ndimage.distance_transform_edt(building) * cell_m >= margin_m
    ok = inner & (z_hi - z_lo <= flat_tol_m)
    labels, num = ndimage.label(ok)
    if num == 0:
        return np.zeros((0, 2), dtype=np.int64)
    depth = ndimage.distance_transform_edt(ok)
    centres = ndimage.maximum_position(depth, labels, np.arange(1, num + 1))
    return np.asarray(centres, dtype=np.int64)


def _interaction_strings(codes: np.ndarray) -> np.ndarray:
    """Sionna interaction codes ``[num_paths, max_depth]`` -> "LOS", "RD", ... ``[num_paths]``."""
    if codes.shape[1] == 0:
        return np.full(len(codes), "LOS", dtype=object)
    uniq, inverse = np.unique(codes, axis=0, return_inverse=True)
    names = np.array(
        ["".join(_INTERACTION_LETTERS.get(int(c), "?") for c in row if c) or "LOS" for row in uniq],
        dtype=object,
    )
    return names[inverse.reshape(-1)]


def paths_to_table(paths, rx_offset: int = 0) -> pd.DataFrame:
    """Convert a Sionna ``Paths`` (one single-antenna transmitter, synthetic arrays)
    to a path table; rows are the valid paths with non-zero power."""
    a_re, a_im = (np.asarray(x, dtype=np.float64) for x in paths.a)
    power = (a_re**2 + a_im**2).sum(axis=(1, 2, 3))  # [num_rx, num_paths], sum over rx pol.
    valid = np.asarray(paths.valid)[:, 0, :] & (power > 0)  # [num_rx, num_paths]
    rx, k = np.nonzero(valid)
    if len(rx) == 0:
        return empty_path_table()
    theta_t = np.asarray(paths.theta_t, dtype=np.float64)[:, 0, :][rx, k]
    codes = np.asarray(paths.interactions)[:, :, 0, :][:, rx, k].T  # [num_valid, max_depth]
    table = pd.DataFrame(
        {
            "rx_index": rx.astype(np.int64) + rx_offset,
            "power_lin": power[rx, k],
            "aod_el_rad": np.pi / 2 - theta_t,  # theta_t is the zenith angle
            "aod_az_rad": np.asarray(paths.phi_t, dtype=np.float64)[:, 0, :][rx, k],
            "delay_s": np.asarray(paths.tau, dtype=np.float64)[:, 0, :][rx, k],
            "interactions": _interaction_strings(codes),
        }
    )
    return table.astype(PATH_COLUMNS)


def _as_points(array: np.ndarray, dim: int, what: str) -> np.ndarray:
    """``array`` as finite float64 ``[num_points, dim]``, or a DataError naming ``what``."""
    points = np.asarray(array, dtype=np.float64)
    if points.ndim != 2 or points.shape[1] != dim or not np.isfinite(points).all():
        raise DataError(f"`{what}` must be a finite array of shape [num_points, {dim}] (got {points.shape}).")
    return points


class SionnaSceneBackend:
    """A Sionna RT scene and its path solver, behind :class:`~rflscm.sim.backend.SceneBackend`.

    Args:
        scene: name of a built-in scene (see :func:`available_scenes`) or path of a
            Mitsuba ``.xml`` scene. Objects named like ground/terrain/plane/floor are
            ground; every other object is a building.
        max_depth: maximum number of interactions per path (>= 2 for double reflections).
        diffraction: trace first-order edge/wedge diffraction (letter D).
        refraction: trace transmission through walls (letter T).
        diffuse_reflection: trace diffuse scattering (letter S; slow and noisy).
        samples_per_src: rays shot from the transmitter per trace.
        max_num_paths_per_src: cap on path candidates per transmitter.
        rx_batch_size: receivers traced per solver call (bounds memory).
        deterministic: use Sionna's deterministic candidate generator, so that a seed
            gives bit-identical paths. It needs ~35 B per (ray, depth, receiver), so
            batches shrink to ~1 GB (15 receivers at 10^6 rays) and CPU time grows ~1.5x;
            the default generator loses or gains about one path in a thousand per run.
        cell_m: resolution of the ground/roof height maps [m].
        min_building_height_m: a cell is inside a building when the building
            surface over it is this much above the ground [m].
        roof_margin_m: roof candidates are at least this far from roof edges [m].
        device: "cpu" (Dr.Jit LLVM), "cuda" or "auto" (CUDA when available).
    """

    def __init__(
        self,
        scene: str = "munich",
        max_depth: int = 2,
        diffraction: bool = True,
        refraction: bool = False,
        diffuse_reflection: bool = False,
        samples_per_src: int = 1_000_000,
        max_num_paths_per_src: int = 1_000_000,
        rx_batch_size: int = 1000,
        deterministic: bool = False,
        cell_m: float = 1.0,
        min_building_height_m: float = 2.0,
        roof_margin_m: float = 3.0,
        device: str = "cpu",
    ) -> None:
        counts = dict(
            samples_per_src=samples_per_src,
            rx_batch_size=rx_batch_size,
            max_num_paths_per_src=max_num_paths_per_src,
            max_depth=max_depth,
        )
        for key, value in counts.items():
            if int(value) != value or value < 1:
                raise ConfigError(f"`{key}` must be a positive integer (got {value!r}).")
        if not cell_m > 0:
            raise ConfigError(f"`cell_m` must be > 0 (got {cell_m}).")
        self._mi, self._rt = _import_sionna(device)
        path = _scene_file(scene)
        self.name = path.stem if scene.endswith(".xml") else scene
        self._solver_args = dict(
            max_depth=int(max_depth),
            samples_per_src=int(samples_per_src),
            max_num_paths_per_src=int(max_num_paths_per_src),
            los=True,
            specular_reflection=True,
            diffuse_reflection=bool(diffuse_reflection),
            refraction=bool(refraction),
            diffraction=bool(diffraction),
            synthetic_array=True,
        )
        self.rx_batch_size = int(rx_batch_size)
        if deterministic:
            lanes = int(max_depth) * int(samples_per_src)
            self.rx_batch_size = min(self.rx_batch_size, max(1, _DETERMINISTIC_LANES // lanes))
        self._scene = self._rt.load_scene(str(path), merge_shapes=True, merge_shapes_exclude_regex=_GROUND_REGEX)
        # Isotropic elements; vertical at the site, V + H at the receiver so that
        # summing |a|^2 over the receive ports collects the power of every polarization.
        iso = dict(num_rows=1, num_cols=1, pattern="iso")
        self._scene.tx_array = self._rt.PlanarArray(**iso, polarization="V")
        self._scene.rx_array = self._rt.PlanarArray(**iso, polarization="VH")
        self._solver = self._rt.PathSolver(deterministic=bool(deterministic))
        self._tri, self._tri_ground = _scene_triangles(self._scene)
        self._build_height_maps(cell_m, min_building_height_m, roof_margin_m)

    def _build_height_maps(self, cell_m: float, min_height_m: float, margin_m: float) -> None:
        lo, hi = self.bounds()
        self._cell_m = cell_m
        self._origin = lo[:2] + cell_m / 2  # centre of cell (0, 0)
        shape = tuple(np.floor((hi[1::-1] - lo[1::-1]) / cell_m).astype(int) + 1)  # (ny, nx)
        ground = _rasterize_max_z(self._tri[self._tri_ground], self._origin, cell_m, shape)
        self._ground_z = _fill_nearest(ground, default=float(lo[2]))  # [ny, nx]
        top = _rasterize_max_z(self._tri[~self._tri_ground], self._origin, cell_m, shape)
        with np.errstate(invalid="ignore"):
            self._building = top - self._ground_z >= min_height_m  # [ny, nx]; NaN -> False
        self._roof_z = np.where(self._building, top, np.nan)
        self._roof_cells = _roof_candidates(self._roof_z, self._building, cell_m, margin_m, 0.5)

    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """Axis-aligned box ``(lo[3], hi[3])`` of all meshes [m]."""
        flat = self._tri.reshape(-1, 3)
        return flat.min(axis=0), flat.max(axis=0)

    def rooftops(self) -> np.ndarray:
        """One point per flat roof area, farthest from its edges: ``[num_candidates, 3]``
        with z = roof surface height [m] (add the mast height before tracing)."""
        iy, ix = self._roof_cells.T
        xy = self._origin + self._cell_m * np.stack([ix, iy], axis=1)
        return np.column_stack([xy, self._roof_z[iy, ix]])

    def _cell_coords(self, xy: np.ndarray) -> np.ndarray:
        """Fractional (row, column) ``[2, num_points]`` of ``xy [num_points, 2]`` in the maps."""
        return ((_as_points(xy, 2, "xy") - self._origin) / self._cell_m).T[::-1]

    def ground_height(self, xy: np.ndarray) -> np.ndarray:
        """Ground height [m] ``[num_points]`` at ``xy [num_points, 2]`` (bilinear interpolation)."""
        rc = self._cell_coords(xy)
        return ndimage.map_coordinates(self._ground_z, rc, order=1, mode="nearest")

    def is_outdoor(self, xy: np.ndarray) -> np.ndarray:
        """True ``[num_points]`` where ``xy [num_points, 2]`` is not inside a building footprint."""
        rc = np.rint(self._cell_coords(xy)).astype(np.int64)
        shape = np.array(self._building.shape)[:, None]
        inside = ((rc >= 0) & (rc < shape)).all(axis=0)
        rc = np.clip(rc, 0, shape - 1)
        return ~(self._building[rc[0], rc[1]] & inside)

    def sample_point_cloud(self, points_per_m2: float, noise_std_m: float, seed: int) -> tuple[np.ndarray, np.ndarray]:
        """Area-weighted random points on the mesh surfaces plus Gaussian noise [m].

        Surfaces no scanner can see are skipped: ground inside building footprints
        and horizontal building faces within 0.5 m of the ground (building floors).
        Returns ``(xyz [num_points, 3] float64, classification [num_points] uint8)``,
        ASPRS class 2 (ground) / 6 (building).
        """
        if not points_per_m2 > 0 or not noise_std_m >= 0:
            got = f"got {points_per_m2}, {noise_std_m}"
            raise ConfigError(f"Point cloud needs `points_per_m2` > 0, `noise_std_m` >= 0 ({got}).")
        tri, rng = self._tri, np.random.default_rng(seed)
        normal = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
        area = 0.5 * np.linalg.norm(normal, axis=1)
        centroid = tri.mean(axis=1)
        floor = (np.abs(normal[:, 2]) > 0.9 * 2 * area) & (centroid[:, 2] < self.ground_height(centroid[:, :2]) + 0.5)
        area = np.where(floor & ~self._tri_ground, 0.0, area)
        t = rng.choice(len(tri), size=int(round(points_per_m2 * area.sum())), p=area / area.sum())
        u, v = rng.random((2, len(t)))
        flip = u + v > 1
        u[flip], v[flip] = 1 - u[flip], 1 - v[flip]
        xyz = tri[t, 0] + u[:, None] * (tri[t, 1] - tri[t, 0])
        xyz += v[:, None] * (tri[t, 2] - tri[t, 0])
        cls = np.where(self._tri_ground[t], ASPRS_GROUND, ASPRS_BUILDING).astype(np.uint8)
        keep = (cls == ASPRS_BUILDING) | self.is_outdoor(xyz[:, :2])
        xyz, cls = xyz[keep], cls[keep]
        return xyz + rng.normal(0.0, noise_std_m, xyz.shape), cls

    def trace(
        self,
        tx_position: np.ndarray,
        rx_positions: np.ndarray,
        freq_hz: float,
        seed: int,
        *,
        progress: Callable[[int, int], None] | None = None,
    ) -> pd.DataFrame:
        """Trace paths from ``tx_position[3]`` to each row of ``rx_positions[num_rx, 3]`` [m].

        Isotropic antennas at both ends; ``freq_hz`` [Hz] sets the materials and
        wavelength; ``seed`` fixes the rays shot (bit-exact repeats need
        ``deterministic=True``). Receivers are traced in batches of ``rx_batch_size``; after each,
        ``progress(num_done, num_rx)`` is called. Returns a path table
        (:mod:`rflscm.sim.backend`) sorted by receiver and delay; azimuths in (-pi, pi].
        """
        tx = _as_points(np.reshape(tx_position, (1, -1)), 3, "tx_position")[0]
        rx = _as_points(rx_positions, 3, "rx_positions")
        if not freq_hz > 0:
            raise ConfigError(f"`freq_hz` must be > 0 (got {freq_hz}).")
        if int(seed) != seed or seed < 0:
            raise ConfigError(f"`seed` must be a non-negative integer (got {seed!r}).")
        scene, mi = self._scene, self._mi
        scene.frequency = float(freq_hz)
        self._remove_devices()
        scene.add(self._rt.Transmitter("tx", position=mi.Point3f(*map(float, tx))))
        tables = []
        try:
            for start in range(0, len(rx), self.rx_batch_size):
                batch = rx[start : start + self.rx_batch_size]
                tables.append(self._trace_batch(batch, start, int(seed)))
                if progress is not None:
                    progress(min(start + self.rx_batch_size, len(rx)), len(rx))
        finally:
            self._remove_devices()
        tables = [t for t in tables if len(t)]
        table = pd.concat(tables, ignore_index=True) if tables else empty_path_table()
        return table.sort_values(["rx_index", "delay_s"], kind="stable", ignore_index=True)

    def _trace_batch(self, rx: np.ndarray, offset: int, seed: int) -> pd.DataFrame:
        """Trace one batch of receivers ``rx [num_batch, 3]`` whose first index is ``offset``."""
        mi, names = self._mi, [f"rx{i}" for i in range(len(rx))]
        for name, pos in zip(names, rx.tolist()):
            self._scene.add(self._rt.Receiver(name, position=mi.Point3f(*pos)))
        paths = self._solver(self._scene, seed=seed, **self._solver_args)
        table = paths_to_table(paths, rx_offset=offset)
        self._scene.remove(names)
        return table

    def _remove_devices(self) -> None:
        self._scene.remove([*self._scene.transmitters, *self._scene.receivers])
