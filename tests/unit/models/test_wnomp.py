"""WNOMP: exact sparse recovery, non-negativity, missing beams, threshold constraint, the model contract."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.optimize
import torch

from rflscm.antenna import CellAntenna, DFTCodebook, SSBCodebook, sensing_matrix, wavelength_of
from rflscm.data import load_scenario
from rflscm.data.examples import tiny_scenario
from rflscm.errors import CheckpointError, ConfigError
from rflscm.geometry import AngleGrid
from rflscm.models import MODEL_REGISTRY, UnsupportedError, load_model
from rflscm.models.wnomp import WNOMPConfig, WNOMPModel, wnomp_config
from rflscm.models.wnomp_solver import batched_nnls, row_argmax, spd_solve, wnomp_solve
from rflscm.train import fit

SMALL = AngleGrid(num_el=13, num_az=24, el_min_deg=-90.0, el_step_deg=15.0)


def _dense(indices: torch.Tensor, values: torch.Tensor, num_bins: int) -> np.ndarray:
    out = np.zeros((indices.shape[0], num_bins))
    for i in range(indices.shape[0]):
        keep = indices[i] >= 0
        np.add.at(out[i], indices[i][keep].numpy(), values[i][keep].numpy())
    return out


def _well_conditioned(num_beams: int = 30, num_bins: int = 200, seed: int = 0) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    return torch.rand(num_beams, num_bins, generator=g, dtype=torch.float64) ** 4 * 1e3  # [mW per unit gain]


def _sparse_aps(num: int, num_bins: int, k: int, seed: int = 1) -> np.ndarray:
    rng = np.random.default_rng(seed)
    x = np.zeros((num, num_bins))
    for i in range(num):
        x[i, rng.choice(num_bins, k, replace=False)] = 10.0 ** rng.uniform(-11.0, -9.0, k)
    return x


def test_noiseless_k_sparse_aps_is_recovered_exactly() -> None:
    a = _well_conditioned()
    x = _sparse_aps(50, a.shape[1], k=3)
    rsrp_mw = torch.as_tensor(x) @ a.T
    idx, val = wnomp_solve(a, rsrp_mw, k_max=8, tolerance=1e-6)
    est = _dense(idx, val, a.shape[1])
    np.testing.assert_array_equal(est > 0, x > 0)  # the support
    np.testing.assert_allclose(est, x, rtol=1e-6, atol=0.0)  # and the values
    assert ((idx >= 0).sum(1) == 3).all()  # no spurious atoms once the residual is zero


def test_power_is_never_negative_and_indices_are_valid() -> None:
    a = _well_conditioned(seed=2)
    rng = np.random.default_rng(3)
    x = _sparse_aps(64, a.shape[1], k=5, seed=4)
    rsrp_dbm = 10 * np.log10(x @ a.numpy().T) + rng.normal(0.0, 3.0, (64, a.shape[0]))
    rsrp_mw = torch.as_tensor(10 ** (np.round(rsrp_dbm) / 10))
    for weighting in ("inverse_rsrp", "none"):
        idx, val = wnomp_solve(a, rsrp_mw, k_max=6, weighting=weighting)
        assert (val >= 0).all() and (val[idx < 0] == 0).all()
        assert ((idx >= -1) & (idx < a.shape[1])).all()
        assert (idx >= 0).any(1).all()  # every problem with a reported beam gets at least one atom


def test_a_missing_beam_changes_nothing_versus_dropping_its_row() -> None:
    a = _well_conditioned(seed=5)
    rng = np.random.default_rng(6)
    x = _sparse_aps(20, a.shape[1], k=4, seed=7)
    rsrp = 10 ** ((10 * np.log10(x @ a.numpy().T) + rng.normal(0, 2.0, (20, a.shape[0]))) / 10)
    with_nan = rsrp.copy()
    with_nan[:, 7] = np.nan
    idx_nan, val_nan = wnomp_solve(a, torch.as_tensor(with_nan), k_max=5)
    keep = np.r_[0:7, 8 : a.shape[0]]
    idx_drop, val_drop = wnomp_solve(a[keep], torch.as_tensor(rsrp[:, keep]), k_max=5)
    np.testing.assert_array_equal(idx_nan.numpy(), idx_drop.numpy())
    np.testing.assert_allclose(val_nan.numpy(), val_drop.numpy(), rtol=1e-9)


def _cell_sensing(grid: AngleGrid, mech_tilt_deg: float = 4.0) -> torch.Tensor:
    antenna = CellAntenna(azimuth_deg=120.0, mech_tilt_deg=mech_tilt_deg, elec_tilt_deg=2.0)
    wl = wavelength_of(3.5e9)
    return torch.cat(
        [
            sensing_matrix(antenna, SSBCodebook(), grid, wl, dtype=torch.float64),
            sensing_matrix(antenna, DFTCodebook(), grid, wl, dtype=torch.float64),
        ]
    )


@pytest.mark.parametrize("grid", [SMALL, AngleGrid()], ids=["13x24", "91x72"])
def test_single_path_is_recovered_in_its_bin(grid: AngleGrid) -> None:
    a = _cell_sensing(grid)  # 8 SSB + 32 CSI-RS beams of a real array, whole sphere (front and back)
    el, _ = grid.bin_angles()
    off_pole = np.flatnonzero(np.abs(el) < np.pi / 2 - 1e-9)  # at ±90° every azimuth bin is the same direction
    bins = np.random.default_rng(8).choice(off_pole, 40, replace=False)
    x = np.zeros((len(bins), grid.num_bins))
    x[np.arange(len(bins)), bins] = 1e-10
    idx, val = wnomp_solve(a, torch.as_tensor(x) @ a.T, k_max=8)
    assert (idx[:, 0].numpy() == bins).all()  # the bin, exactly
    np.testing.assert_allclose(val[:, 0].numpy(), 1e-10, rtol=1e-6)
    assert (idx[:, 1:] == -1).all()


def test_threshold_constraint_pulls_missing_beams_under_the_threshold() -> None:
    a = _well_conditioned(seed=9)
    x = _sparse_aps(40, a.shape[1], k=4, seed=10)
    rsrp = x @ a.numpy().T
    threshold = np.quantile(rsrp, 0.4)
    hidden = rsrp < threshold
    observed = np.where(hidden, np.nan, rsrp)
    rng = np.random.default_rng(11)
    observed *= 10 ** (rng.normal(0.0, 1.5, observed.shape) / 10)  # noise, so that plain WNOMP over-predicts some

    def violation(**kw: object) -> float:
        idx, val = wnomp_solve(a, torch.as_tensor(observed), k_max=6, **kw)
        pred = _dense(idx, val, a.shape[1]) @ a.numpy().T
        return float(np.clip(pred[hidden] / threshold - 1.0, 0.0, None).sum())

    free, constrained = violation(), violation(threshold_mw=float(threshold))
    assert free > 0.0
    assert constrained < 0.5 * free


def test_batched_nnls_matches_scipy() -> None:
    g = torch.Generator().manual_seed(12)
    b = torch.randn(100, 6, 15, generator=g, dtype=torch.float64)
    t = torch.randn(100, 15, generator=g, dtype=torch.float64)
    z = batched_nnls(b @ b.transpose(1, 2), (b @ t[:, :, None])[:, :, 0], torch.zeros(100, 6, dtype=torch.float64))
    for i in range(100):
        ref, _ = scipy.optimize.nnls(b[i].T.numpy(), t[i].numpy())
        np.testing.assert_allclose(z[i].numpy(), ref, atol=1e-9)


def test_small_kernels_match_torch() -> None:
    g = torch.Generator().manual_seed(13)
    m = torch.randn(64, 7, 20, generator=g, dtype=torch.float64)
    gram = m @ m.transpose(1, 2)
    rhs = torch.randn(64, 7, generator=g, dtype=torch.float64)
    torch.testing.assert_close(spd_solve(gram, rhs), torch.linalg.solve(gram, rhs))
    score = torch.randn(33, 6552, generator=g)
    score[3, 100] = score[3, 200] = 50.0  # a tie: the first index wins, as in Tensor.max
    best, where = row_argmax(score)
    ref_best, ref_where = score.max(1)
    torch.testing.assert_close(best, ref_best)
    assert torch.equal(where, ref_where)


def test_gain_prior_breaks_the_front_back_mirror_tie() -> None:
    """A planar array sees a back-lobe direction like its mirror in front, 30 dB down; with noise the
    normalised correlation may pick either, the gain prior picks the front one (less path power)."""
    a = _cell_sensing(SMALL, mech_tilt_deg=0.0)  # untilted: every back bin mirrors a front bin exactly
    col_gain = a.max(0).values
    front = torch.nonzero(col_gain > 0.1 * col_gain.max()).squeeze(1)
    x = np.zeros((len(front), SMALL.num_bins))
    x[np.arange(len(front)), front.numpy()] = 1e-10
    rng = np.random.default_rng(14)
    rsrp = (torch.as_tensor(x) @ a.T).numpy() * 10 ** (rng.normal(0, 1.0, (len(front), a.shape[0])) / 10)

    def front_share(gain_prior: float) -> float:
        idx, _ = wnomp_solve(a, torch.as_tensor(rsrp), k_max=1, gain_prior=gain_prior)
        return float((col_gain[idx[:, 0]] > 0.01 * col_gain.max()).double().mean())

    assert front_share(0.05) > 0.95
    assert front_share(0.0) < 0.8  # the textbook rule is fooled by the mirror often


# --- the model contract ----------------------------------------------------------------------------
@pytest.fixture(scope="module")
def tiny(tmp_path_factory: pytest.TempPathFactory):
    return load_scenario(tiny_scenario(tmp_path_factory.mktemp("wnomp") / "tiny", seed=1))


def test_fit_answers_seen_pairs_and_refuses_unseen_ones(tiny) -> None:
    model = MODEL_REGISTRY["wnomp"].build(None, SMALL, "cpu")
    assert isinstance(model, WNOMPModel) and not model.supports_unseen_grids
    summary = fit(model, tiny, progress=False)
    assert summary["num_pairs"] == 6  # 2 cells × 3 grids
    pairs, measured = tiny.rsrp_table(1, "csi")
    aps = model.aps(pairs["cell_id"].to_numpy(), pairs["grid_id"].to_numpy())
    assert aps.shape == (6, SMALL.num_bins) and aps.dtype == torch.float32 and (aps >= 0).all()
    fitted = model.predict_rsrp(tiny, 1, "csi", pairs)
    ok = np.isfinite(measured)
    assert np.abs(fitted[ok] - measured[ok]).mean() < 1.5  # round 1 is fitted to about the noise
    with pytest.raises(UnsupportedError, match="WNOMP has no notion of unseen grids"):
        model.aps(np.array([11, 11]), np.array([100, 999]))


def test_save_load_round_trip_and_foreign_scenario(tiny, tmp_path) -> None:
    model = MODEL_REGISTRY["wnomp"].build({"k_max": 3, "tolerance": 0.0}, SMALL, "cpu")
    model.fingerprint = tiny.fingerprint()
    fit(model, tiny, progress=False)
    path = model.save(tmp_path / "w.ckpt")
    loaded = load_model(path, tiny)
    assert loaded.config == model.config and loaded.angle_grid == SMALL
    cells, grids = model.cell_ids, model.grid_ids
    torch.testing.assert_close(loaded.aps(cells, grids), model.aps(cells, grids), rtol=0, atol=0)
    other = load_scenario(tiny_scenario(tmp_path / "other", seed=2))  # other noise → other fingerprint
    with pytest.raises(CheckpointError, match="trained on another scenario"):
        load_model(path, other)


def test_config_presets_and_errors(tmp_path) -> None:
    assert wnomp_config("quick") == wnomp_config("full") == WNOMPConfig()
    assert wnomp_config({"name": "wnomp", "k_max": 4}).k_max == 4
    yaml_file = tmp_path / "w.yaml"
    yaml_file.write_text("k_max: 5\nweighting: none\n")
    assert wnomp_config(yaml_file) == WNOMPConfig(k_max=5, weighting="none")
    with pytest.raises(ConfigError, match=r"valid keys: .*k_max"):
        wnomp_config({"kmax": 4})
    with pytest.raises(ConfigError, match="must be one of 'inverse_rsrp', 'none'"):
        wnomp_config({"weighting": "log"})
    with pytest.raises(ConfigError, match="k_max` must be >= 1"):
        WNOMPConfig(k_max=0)
    with pytest.raises(ConfigError, match="neither a preset"):
        wnomp_config("fast")


def test_speed_benchmark_runs_the_fit_code_path() -> None:
    from rflscm.bench.wnomp_speed import run_wnomp_speed

    result = run_wnomp_speed(64, num_beams=40, num_bins=18 * 72, repeats=1)
    assert result["num_beams"] == 40 and result["num_bins"] == 1296 and result["num_problems"] == 64
    assert result["problems_per_s"] > 0 and 1.0 <= result["mean_atoms"] <= 8.0
    assert result["target_problems_per_s"] == 3000.0


def test_settings_are_chosen_on_held_aside_round1_beams_only(tiny) -> None:
    from rflscm.models.wnomp_select import hold_aside, select_wnomp

    m = tiny.measurements
    train, held = hold_aside(m, fraction=0.5, seed=0)
    assert len(held) > 0 and (m.iloc[held]["round"] == 1).all() and m.iloc[held]["rsrp_dbm"].notna().all()
    assert train.iloc[held]["rsrp_dbm"].isna().all() and train.drop(index=held).equals(m.drop(index=held))
    grid = AngleGrid(num_el=16, num_az=24, el_min_deg=-60.0, el_step_deg=8.0)
    best, table = select_wnomp(tiny, grid, fraction=0.5, seed=0)
    assert len(table) == 12 and table["mae_db"].notna().all()
    # round 2 plays no part: scrambling it changes nothing
    scrambled = m.assign(rsrp_dbm=np.where(m["round"] == 2, m["rsrp_dbm"] - 20.0, m["rsrp_dbm"]))
    best2, table2 = select_wnomp(tiny.with_measurements(scrambled, validate=False), grid, fraction=0.5, seed=0)
    assert best2 == best
    np.testing.assert_allclose(table2["mae_db"], table["mae_db"])


def test_the_selection_fits_only_the_pairs_it_scores_and_holds_aside_at_most_max_held(tiny, monkeypatch) -> None:
    """WNOMP fits each pair alone: fitting only the pairs with a held-aside beam scores every candidate as fitting
    them all does; at most ``max_held`` beams are held aside, a subset of those picked without the cap."""
    import rflscm.models.wnomp_select as ws

    grid = AngleGrid(num_el=16, num_az=24, el_min_deg=-60.0, el_step_deg=8.0)
    best, table = ws.select_wnomp(tiny, grid, fraction=0.5, seed=0)
    monkeypatch.setattr(ws, "_pairs_of", lambda table, held: table)  # every pair fitted, as before
    best_all, table_all = ws.select_wnomp(tiny, grid, fraction=0.5, seed=0)
    assert best == best_all and (table["beams"] == table_all["beams"]).all()
    np.testing.assert_allclose(
        table[["mae_ssb_db", "mae_csi_db", "mae_db"]], table_all[["mae_ssb_db", "mae_csi_db", "mae_db"]], atol=1e-6
    )
    _, held = ws.hold_aside(tiny.measurements, fraction=1.0, seed=0)
    _, capped = ws.hold_aside(tiny.measurements, fraction=1.0, seed=0, max_held=3)
    assert len(held) > 3 and len(capped) == 3 and set(capped) <= set(held) and (np.diff(capped) > 0).all()
