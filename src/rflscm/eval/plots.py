"""Report figures (matplotlib, Agg backend): coverage maps, error histograms, per-cell bars, APS heat maps.

Every function takes plain arrays, writes one PNG and returns its path; nothing here knows about
models or protocols.
"""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")

import matplotlib.pyplot as plt
import numpy as np
from matplotlib.patches import Patch

from rflscm.geometry import AngleGrid
from rflscm.geometry.angles import internal_to_engineering

DPI = 110
COVERAGE_CMAP = "viridis"
ERROR_CMAP = "RdBu_r"


def _lattice(xy: np.ndarray) -> tuple[np.ndarray, np.ndarray, float] | None:
    """Column/row index of each point on a regular lattice and its spacing, or None if irregular."""
    if len(xy) < 2:
        return None
    steps = [np.diff(np.unique(np.round(xy[:, k], 3))) for k in (0, 1)]
    steps = [s[s > 1e-6] for s in steps]
    if not all(len(s) for s in steps):
        return None
    step = float(min(s.min() for s in steps))
    ij = np.round((xy - xy.min(0)) / step).astype(np.int64)
    if not np.allclose(ij * step + xy.min(0), xy, atol=0.05 * step) or ij.max() > 2000:
        return None
    return ij[:, 0], ij[:, 1], step


def _map(
    ax: plt.Axes, xy: np.ndarray, values: np.ndarray, vmin: float, vmax: float, cmap: str
) -> matplotlib.cm.ScalarMappable:
    """Draw values at grid centres: a raster on a regular lattice, square markers otherwise."""
    lattice = _lattice(xy)
    if lattice is not None:
        i, j, step = lattice
        image = np.full((j.max() + 1, i.max() + 1), np.nan)
        image[j, i] = values
        x0, y0 = xy.min(0) - step / 2
        extent = (x0, x0 + step * image.shape[1], y0, y0 + step * image.shape[0])
        return ax.imshow(image, origin="lower", extent=extent, vmin=vmin, vmax=vmax, cmap=cmap, interpolation="nearest")
    return ax.scatter(xy[:, 0], xy[:, 1], c=values, s=14, marker="s", vmin=vmin, vmax=vmax, cmap=cmap, linewidths=0)


def _sites(ax: plt.Axes, cells_xy: np.ndarray, azimuth_deg: np.ndarray, changed: np.ndarray, arrow_m: float) -> None:
    """Site triangles and one boresight arrow per cell (azimuth clockwise from north); changed cells in red."""
    sites = np.unique(np.round(cells_xy, 2), axis=0)
    ax.scatter(sites[:, 0], sites[:, 1], marker="^", s=60, c="white", edgecolors="black", linewidths=1.2, zorder=5)
    for (x, y), az, ch in zip(cells_xy, azimuth_deg, changed):
        dx, dy = arrow_m * np.sin(np.radians(az)), arrow_m * np.cos(np.radians(az))
        ax.annotate(
            "",
            (x + dx, y + dy),
            (x, y),
            arrowprops={"arrowstyle": "->", "color": "red" if ch else "black", "lw": 1.4},
            zorder=6,
        )


def coverage_maps(
    path: Path,
    grid_xy: np.ndarray,
    measured_dbm: np.ndarray,
    predicted_dbm: np.ndarray,
    cells_xy: np.ndarray,
    azimuth_deg: np.ndarray,
    changed: np.ndarray,
    title: str,
) -> Path:
    """Measured | predicted best-beam RSRP per grid on one colour scale, and predicted − measured.

    Args:
        grid_xy: ``[num_grids, 2]`` grid centres [m]; measured/predicted ``[num_grids]`` [dBm].
        cells_xy, azimuth_deg, changed: ``[num_cells]`` site positions [m], azimuths (clockwise from
            north) [deg] and changed flags, drawn as arrows (red = changed).
    """
    fig, axes = plt.subplots(1, 3, figsize=(17, 5.4), constrained_layout=True)
    both = np.concatenate([measured_dbm, predicted_dbm])
    both = both[np.isfinite(both)]
    vmin, vmax = (np.percentile(both, 1), np.percentile(both, 99)) if len(both) else (-120.0, -60.0)
    span = np.ptp(np.vstack([grid_xy, cells_xy]), axis=0).max() if len(grid_xy) else 100.0
    for ax, values, name in ((axes[0], measured_dbm, "measured"), (axes[1], predicted_dbm, "predicted")):
        mappable = _map(ax, grid_xy, values, vmin, vmax, COVERAGE_CMAP)
        ax.set_title(f"{name} best-beam RSRP")
        fig.colorbar(mappable, ax=ax, label="RSRP (dBm)", shrink=0.9)
    diff = predicted_dbm - measured_dbm
    lim = max(1.0, float(np.nanpercentile(np.abs(diff), 98))) if np.isfinite(diff).any() else 10.0
    mappable = _map(axes[2], grid_xy, diff, -lim, lim, ERROR_CMAP)
    axes[2].set_title("predicted − measured")
    fig.colorbar(mappable, ax=axes[2], label="error (dB)", shrink=0.9)
    for ax in axes:
        _sites(ax, cells_xy, azimuth_deg, changed, arrow_m=0.07 * span)
        ax.set_xlabel("x, east (m)")
        ax.set_ylabel("y, north (m)")
        ax.set_aspect("equal")
    fig.suptitle(f"{title}  (▲ sites, arrows = cell azimuths clockwise from north, red = changed)")
    return _save(fig, path)


def _cell_colors(n: int) -> np.ndarray:
    """``n`` distinct qualitative colours (tab20, tab20b, tab20c interleaved so that neighbours in cell-id order
    differ in hue and lightness), RGBA ``[n, 4]``."""
    base = [plt.get_cmap(name)(np.arange(20)) for name in ("tab20", "tab20b", "tab20c")]
    palette = np.concatenate([b[order] for b in base for order in (np.r_[0:20:2, 1:20:2],)])
    return palette[np.arange(n) % len(palette)]


def _serving(ax: plt.Axes, xy: np.ndarray, serving: np.ndarray, cell_ids: np.ndarray) -> None:
    """Serving-cell map: one qualitative colour per cell and the cell id written at the centre of its area."""
    from matplotlib.colors import ListedColormap

    colors = _cell_colors(len(cell_ids))
    codes = np.where(serving >= 0, np.searchsorted(cell_ids, serving), -1).astype(np.float64)
    codes[serving < 0] = np.nan
    _map(ax, xy, codes, -0.5, len(cell_ids) - 0.5, ListedColormap(colors))  # type: ignore[arg-type]
    for k, cell in enumerate(cell_ids):
        mine = serving == cell
        if mine.sum() < 2:
            continue
        own = xy[mine]
        cx, cy = own[np.argmin(np.linalg.norm(own - own.mean(0), axis=1))]  # inside its area, near the centre
        ax.text(
            cx,
            cy,
            str(cell),
            ha="center",
            va="center",
            fontsize=7,
            fontweight="bold",
            zorder=7,
            bbox={"boxstyle": "round,pad=0.15", "fc": colors[k], "ec": "black", "lw": 0.4, "alpha": 0.9},
        )


def kpi_maps(
    path: Path,
    grid_xy: np.ndarray,
    rows: list[tuple[str, dict[str, np.ndarray]]],
    cell_ids: np.ndarray,
    cells_xy: np.ndarray,
    azimuth_deg: np.ndarray,
    changed: np.ndarray,
    title: str,
    difference: tuple[str, int, int] | None = None,
) -> Path:
    """Best-server RSRP, serving cell and SS-SINR maps of one carrier, one row per configuration (or source),
    with an optional difference row.

    Args:
        grid_xy: ``[num_grids, 2]`` grid centres, x east / y north [m].
        rows: ``(label, maps)``; ``maps`` holds ``rsrp_dbm``, ``serving`` (cell id, −1 = none), ``sinr_db``
            ``[num_grids]`` (NaN where the grid has no value).
        cell_ids: ``[num_cells]`` sorted ids of the carrier's cells (serving-cell colours and labels).
        cells_xy, azimuth_deg, changed: every cell's site [m], azimuth (clockwise from north) [deg] and changed flag.
        difference: ``(label, a, b)``: a last row with row b − row a (RSRP and SINR [dB]) and where the
            serving cell differs.
    """
    n_rows = len(rows) + (difference is not None)
    fig, axes = plt.subplots(n_rows, 3, figsize=(17, 5.0 * n_rows), constrained_layout=True, squeeze=False)
    span = np.ptp(np.vstack([grid_xy, cells_xy]), axis=0).max() if len(grid_xy) else 100.0
    for r, (label, m) in enumerate(rows):
        mappable = _map(axes[r, 0], grid_xy, m["rsrp_dbm"], -130.0, -60.0, COVERAGE_CMAP)
        fig.colorbar(mappable, ax=axes[r, 0], label="best-server SSB RSRP (dBm)", shrink=0.85)
        axes[r, 0].set_title(f"{label}: best-server RSRP")
        _serving(axes[r, 1], grid_xy, m["serving"], cell_ids)
        axes[r, 1].set_title(f"{label}: serving cell (id at the centre of its area)")
        mappable = _map(axes[r, 2], grid_xy, m["sinr_db"], -10.0, 30.0, "RdYlGn")
        fig.colorbar(mappable, ax=axes[r, 2], label="SS-SINR (dB)", shrink=0.85)
        axes[r, 2].set_title(f"{label}: SS-SINR")
    if difference is not None:
        label, a, b = difference
        ma, mb = rows[a][1], rows[b][1]
        r = n_rows - 1
        for col, key, name in ((0, "rsrp_dbm", "best-server RSRP"), (2, "sinr_db", "SS-SINR")):
            diff = mb[key] - ma[key]
            lim = max(1.0, float(np.nanpercentile(np.abs(diff), 98))) if np.isfinite(diff).any() else 10.0
            mappable = _map(axes[r, col], grid_xy, diff, -lim, lim, ERROR_CMAP)
            fig.colorbar(mappable, ax=axes[r, col], label=f"{name} difference (dB)", shrink=0.85)
            axes[r, col].set_title(f"{label}: {name}")
        moved = np.where(
            (ma["serving"] >= 0) & (mb["serving"] >= 0), (ma["serving"] != mb["serving"]).astype(float), np.nan
        )
        mappable = _map(axes[r, 1], grid_xy, moved, 0.0, 1.0, "Greys")
        axes[r, 1].set_title(f"{label}: serving cell changed (black) — {np.nansum(moved):.0f} grids")
    for ax in axes.ravel():
        _sites(ax, cells_xy, azimuth_deg, changed, arrow_m=0.07 * span)
        ax.set_xlabel("x, east (m)")
        ax.set_ylabel("y, north (m)")
        ax.set_aspect("equal")
    fig.suptitle(f"{title}\n▲ sites; arrows: cell azimuths, clockwise from north (red: changed)")
    return _save(fig, path)


def error_cdfs(path: Path, errors: dict[str, dict[str, np.ndarray]], title: str) -> Path:
    """Empirical CDFs of the absolute error |predicted − measured| [dB], one panel per beam type, with the
    median and 90th percentile of each predictor in the legend.

    Args:
        errors: beam type → predictor (``model``, ``oracle``, ``trivial``) → flat signed errors [dB].
    """
    fig, axes = plt.subplots(1, len(errors), figsize=(6.5 * len(errors), 4.3), constrained_layout=True, squeeze=False)
    styles = {"model": ("tab:blue", "-"), "oracle": ("black", "--"), "trivial": ("tab:gray", ":")}
    for ax, (beam_type, by_name) in zip(axes[0], errors.items()):
        top = 1.0
        for name, err in by_name.items():
            err = np.sort(np.abs(err[np.isfinite(err)]))
            if not len(err):
                continue
            color, ls = styles.get(name, ("tab:orange", "-"))
            frac = np.arange(1, len(err) + 1) / len(err)
            p50, p90 = np.percentile(err, [50, 90])
            ax.step(
                err,
                frac,
                where="post",
                color=color,
                ls=ls,
                lw=1.8,
                label=f"{name}: median {p50:.2f} dB, 90 % {p90:.2f} dB (n={len(err)})",
            )
            top = max(top, float(p90) * 1.6)
        ax.set_xlim(0.0, min(top, 40.0))
        ax.set_ylim(0.0, 1.0)
        ax.grid(alpha=0.3)
        ax.set_xlabel("absolute RSRP error |predicted − measured| (dB)")
        ax.set_ylabel("fraction of reported beams")
        ax.set_title(f"{beam_type.upper()} beams: error CDF")
        ax.legend(loc="lower right", fontsize=8)
    fig.suptitle(title)
    return _save(fig, path)


def error_histograms(path: Path, errors: dict[str, dict[str, np.ndarray]], title: str) -> Path:
    """Histograms of the signed error predicted − measured [dB], one panel per beam type.

    Args:
        errors: beam type → predictor (``model``, ``oracle``, ``trivial``) → flat signed errors [dB].
    """
    fig, axes = plt.subplots(1, len(errors), figsize=(6.5 * len(errors), 4.3), constrained_layout=True, squeeze=False)
    styles = {
        "model": ("tab:blue", "stepfilled", 0.45),
        "oracle": ("black", "step", 1.0),
        "trivial": ("tab:gray", "step", 1.0),
    }
    bins = np.arange(-20.5, 21.5, 1.0)
    for ax, (beam_type, by_name) in zip(axes[0], errors.items()):
        for name, err in by_name.items():
            err = err[np.isfinite(err)]
            if not len(err):
                continue
            color, kind, alpha = styles.get(name, ("tab:orange", "step", 1.0))
            ax.hist(
                np.clip(err, bins[0], bins[-1]),
                bins=bins,
                histtype=kind,
                color=color,
                alpha=alpha,
                lw=1.6,
                density=True,
                label=f"{name}: MAE {np.abs(err).mean():.2f} dB",
            )
        ax.axvline(0.0, color="k", lw=0.6)
        ax.set_xlabel("predicted − measured RSRP [dB] (clipped to ±20)")
        ax.set_ylabel("fraction of beams per dB")
        ax.set_title(f"{beam_type.upper()} beams")
        ax.legend(loc="upper left", fontsize=9)
    fig.suptitle(title)
    return _save(fig, path)


def per_cell_bars(path: Path, per_cell: dict[str, dict], title: str) -> Path:
    """Model MAE per cell (SSB and CSI-RS bars), oracle as black ticks, trivial as grey ticks; changed cells
    shaded and labelled in red."""
    cells = list(per_cell)
    x = np.arange(len(cells))
    fig, ax = plt.subplots(figsize=(max(7.0, 0.55 * len(cells) + 2), 4.6), constrained_layout=True)
    width = 0.38
    for k, (beam_type, color) in enumerate((("ssb", "tab:blue"), ("csi", "tab:orange"))):
        pos = x + (k - 0.5) * width
        model = [_nan(per_cell[c].get(beam_type)) for c in cells]
        ax.bar(pos, model, width, color=color, label=f"model {beam_type.upper()}")
        ax.scatter(
            pos,
            [_nan(per_cell[c]["oracle"].get(beam_type)) for c in cells],
            marker="_",
            s=160,
            c="black",
            zorder=4,
            label="oracle" if k == 0 else None,
        )
        ax.scatter(
            pos,
            [_nan(per_cell[c]["trivial"].get(beam_type)) for c in cells],
            marker="_",
            s=160,
            c="tab:gray",
            zorder=4,
            label="trivial" if k == 0 else None,
        )
    for i, c in enumerate(cells):
        if per_cell[c]["changed"]:
            ax.axvspan(i - 0.5, i + 0.5, color="red", alpha=0.08, lw=0)
    ax.set_xticks(x, cells, rotation=60 if len(cells) > 12 else 0)
    for label, c in zip(ax.get_xticklabels(), cells):
        label.set_color("red" if per_cell[c]["changed"] else "black")
    ax.set_xlim(-0.6, len(cells) - 0.4)
    ax.set_xlabel("cell id (red, shaded: antenna changed)")
    ax.set_ylabel("MAE [dB]")
    handles, labels = ax.get_legend_handles_labels()
    handles.append(Patch(color="red", alpha=0.15))
    labels.append("changed cell")
    ax.legend(handles, labels, ncol=5, fontsize=9, loc="upper left")
    ax.set_title(title)
    return _save(fig, path)


def aps_heatmaps(
    path: Path,
    angle_grid: AngleGrid,
    labels: list[str],
    true: np.ndarray,
    est: np.ndarray,
    boresight_az_deg: list[float] | None = None,
    floor_db: float = 40.0,
) -> Path:
    """True | estimated APS (elevation × azimuth, dB of path gain) for a few pairs, one row each.

    Each non-zero bin within ``floor_db`` of the row's peak is a square marker (strongest on top),
    so that sparse spectra stay visible; both panels of a row share one colour scale.
    Azimuths are drawn clockwise from north like the cells tables (the angle grid's counter-clockwise-from-east
    bins are converted here); ``boresight_az_deg`` (clockwise from north) draws each row's cell boresight.
    """
    rows = len(labels)
    fig, axes = plt.subplots(rows, 2, figsize=(12, 3.2 * rows + 0.7), constrained_layout=True, squeeze=False)
    el_rad, az_rad = angle_grid.bin_angles()
    az, _ = internal_to_engineering(np.asarray(el_rad), np.asarray(az_rad))  # → clockwise from north
    el = np.degrees(np.asarray(el_rad))
    for r in range(rows):
        vmax = 10 * np.log10(max(float(np.max(true[r])), float(np.max(est[r])), 1e-300))
        for c, (aps, name) in enumerate(((true[r], "true"), (est[r], "estimated"))):
            ax = axes[r, c]
            aps = np.asarray(aps, dtype=np.float64)
            show = np.flatnonzero(aps > 10 ** ((vmax - floor_db) / 10))
            show = show[np.argsort(aps[show])]
            sc = ax.scatter(
                az[show],
                el[show],
                c=10 * np.log10(aps[show]),
                s=30,
                marker="s",
                cmap="magma",
                vmin=vmax - floor_db,
                vmax=vmax,
                edgecolors="black",
                linewidths=0.3,
            )
            if boresight_az_deg is not None:
                ax.axvline(boresight_az_deg[r] % 360.0, color="tab:blue", ls="--", lw=1, label="cell boresight")
                ax.legend(loc="upper right", fontsize=8)
            ax.set_xlim(0, 360)
            ax.set_ylim(-90, 90)
            ax.set_xticks(np.arange(0, 361, 45))
            ax.set_yticks(np.arange(-90, 91, 30))
            ax.grid(alpha=0.3)
            ax.set_title(f"{name} APS, {labels[r]} ({len(show)} bins shown)", fontsize=10)
            ax.set_xlabel("azimuth, clockwise from north (deg)")
            ax.set_ylabel("elevation (deg)")
        fig.colorbar(sc, ax=axes[r, :].tolist(), label="path gain (dB)", shrink=0.9)
    fig.suptitle(f"angular power spectra (bins within {floor_db:g} dB of each row's peak)")
    return _save(fig, path)


def attenuation_map(
    path: Path,
    x_m: np.ndarray,
    y_m: np.ndarray,
    db_per_m: np.ndarray,
    title: str,
    sites_xy: np.ndarray | None = None,
    azimuth_deg: np.ndarray | None = None,
) -> Path:
    """A top-down map of a learned attenuation field.

    Args:
        x_m, y_m: ``[nx]``, ``[ny]`` cell-centre coordinates, east and north [m].
        db_per_m: ``[ny, nx]`` attenuation (the strongest over height) [dB/m].
        sites_xy, azimuth_deg: cells' sites [m] and azimuths (clockwise from north) [deg], drawn when given.
    """
    fig, ax = plt.subplots(figsize=(8.5, 7.2), constrained_layout=True)
    dx = (x_m[1] - x_m[0]) / 2 if len(x_m) > 1 else 0.5
    dy = (y_m[1] - y_m[0]) / 2 if len(y_m) > 1 else 0.5
    extent = (x_m[0] - dx, x_m[-1] + dx, y_m[0] - dy, y_m[-1] + dy)
    finite = np.isfinite(db_per_m).any()
    low, top = (float(np.nanpercentile(db_per_m, q)) for q in (0.5, 99.5)) if finite else (0.0, 1.0)
    image = ax.imshow(
        db_per_m,
        origin="lower",
        extent=extent,
        cmap="inferno",
        vmin=low,
        vmax=max(top, low + 1e-9),
        interpolation="nearest",
    )
    fig.colorbar(image, ax=ax, label="learned attenuation −log|δ|, strongest over height (dB/m)", shrink=0.9)
    if sites_xy is not None and azimuth_deg is not None and len(sites_xy):
        span = max(extent[1] - extent[0], extent[3] - extent[2])
        _sites(ax, sites_xy, azimuth_deg, np.zeros(len(sites_xy), dtype=bool), arrow_m=0.05 * span)
    ax.set_xlabel("x, east (m)")
    ax.set_ylabel("y, north (m)")
    ax.set_aspect("equal")
    ax.set_title(title)
    return _save(fig, path)


def _nan(value: float | None) -> float:
    return np.nan if value is None else float(value)


def _save(fig: plt.Figure, path: Path) -> Path:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=DPI)
    plt.close(fig)
    return path
