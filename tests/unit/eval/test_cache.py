"""The APS cache: the in-memory memo (:class:`APSCache`) is an APS source, not a model; the file cache
(:class:`ScenarioAPS`) round-trips, is keyed by the checkpoint's content and is refused in one line when it
is of another checkpoint or scenario, damaged, non-finite, or not a cache at all — and it never runs code."""

from __future__ import annotations

import builtins
import dataclasses
import pickle
from pathlib import Path
from typing import ClassVar

import numpy as np
import pandas as pd
import pytest
import torch

from rflscm.data import load_scenario
from rflscm.data.examples import tiny_scenario
from rflscm.eval import UnseenProtocol, fit_with_protocol
from rflscm.eval.cache import (
    CACHE_FORMAT,
    REACH_MARGIN,
    APSCache,
    APSCacheError,
    ScenarioAPS,
    hearing_range_m,
    load_or_render,
    render_rows,
)
from rflscm.geometry import AngleGrid
from rflscm.models import MODEL_REGISTRY, LSCMModel, load_model
from rflscm.models.base import content_hash
from rflscm.models.source import APSSource, RsrpMix, predict_rsrp, source_sha256

GRID = AngleGrid(num_el=31, num_az=36, el_min_deg=-90.0, el_step_deg=6.0)
SRC = Path(__file__).resolve().parents[3] / "src"


@pytest.fixture(scope="module")
def fitted(tmp_path_factory: pytest.TempPathFactory):
    """The tiny scenario, a WNOMP fitted on it and saved, and one fitted on fewer grids (another checkpoint)."""
    root = tiny_scenario(tmp_path_factory.mktemp("cache") / "tiny", seed=3)
    scenario = load_scenario(root)
    model = MODEL_REGISTRY["wnomp"].build(None, GRID, "cpu")
    fit_with_protocol(model, scenario, None, progress=False)
    ckpt = model.save(root.parent / "w.ckpt")
    other = MODEL_REGISTRY["wnomp"].build(None, GRID, "cpu")
    fit_with_protocol(other, scenario, UnseenProtocol(fraction=0.34, seed=1), progress=False)
    return scenario, model, ckpt, other


def _one_line(exc: pytest.ExceptionInfo) -> str:
    text = str(exc.value)
    assert "\n" not in text
    return text


def test_the_memo_is_an_aps_source_not_a_model_and_predicts_like_its_model(fitted) -> None:
    scenario, model, _, _ = fitted
    cached = APSCache(model)
    assert isinstance(cached, APSSource) and not isinstance(cached, LSCMModel)
    assert not hasattr(cached, "save") and not hasattr(cached, "fit")
    assert (cached.name, cached.angle_grid, cached.supports_unseen_grids) == ("wnomp", GRID, False)
    pairs, _ = scenario.rsrp_table(1, "ssb")
    pairs = pairs.iloc[:3].reset_index(drop=True)
    np.testing.assert_array_equal(
        cached.predict_rsrp(scenario, 1, "ssb", pairs), model.predict_rsrp(scenario, 1, "ssb", pairs)
    )
    assert len(cached) == 3  # each pair rendered once
    assert cached.content_sha256() == source_sha256(model)


def test_round_trip_and_the_key_survives_reloading_the_checkpoint(fitted, tmp_path: Path) -> None:
    scenario, model, ckpt, _ = fitted
    cache = ScenarioAPS.render(model, scenario)
    assert cache.source_sha256 == source_sha256(model) and cache.fingerprint == scenario.fingerprint()
    cache.save(tmp_path / "aps.pt")
    reloaded = load_model(ckpt, scenario)  # another process would see this: the same checkpoint, read again
    back = ScenarioAPS.load(tmp_path / "aps.pt", reloaded, scenario)
    np.testing.assert_array_equal(back.cell_ids, cache.cell_ids)
    np.testing.assert_array_equal(back.known, cache.known)
    assert back.angle_grid == cache.angle_grid and back.model == "wnomp"
    for a, b, c, d in zip(back.aps, cache.aps, back.bins, cache.bins, strict=True):
        torch.testing.assert_close(a, b, rtol=0, atol=0)
        np.testing.assert_array_equal(c, d)
    again, _ = load_or_render(reloaded, scenario, tmp_path / "aps.pt")  # read, not rendered
    torch.testing.assert_close(again.aps[0], cache.aps[0], rtol=0, atol=0)
    assert not list(tmp_path.glob("*.tmp")) and not list(tmp_path.glob(".*.tmp"))


def test_a_cache_of_another_checkpoint_or_scenario_is_refused(fitted, tmp_path: Path) -> None:
    scenario, model, _, other = fitted
    assert source_sha256(other) != source_sha256(model)  # same model name, same scenario: only the content differs
    ScenarioAPS.render(model, scenario).save(tmp_path / "aps.pt")
    with pytest.raises(APSCacheError, match="another checkpoint") as exc:
        load_or_render(other, scenario, tmp_path / "aps.pt")
    assert "--aps-cache" in _one_line(exc)
    elsewhere = load_scenario(tiny_scenario(tmp_path / "t2", seed=4))
    with pytest.raises(APSCacheError, match="another scenario"):
        ScenarioAPS.load(tmp_path / "aps.pt", model, elsewhere)


@pytest.mark.parametrize("value", [float("nan"), float("inf"), -1.0])
def test_non_finite_or_negative_cached_aps_are_refused(fitted, tmp_path: Path, value: float) -> None:
    scenario, model, _, _ = fitted
    cache = ScenarioAPS.render(model, scenario)
    cache.aps = [torch.full_like(a, value) for a in cache.aps]  # e.g. a diverged model's cache from elsewhere
    cache.save(tmp_path / "bad.pt")
    with pytest.raises(APSCacheError, match="non-finite or negative") as exc:
        ScenarioAPS.load(tmp_path / "bad.pt", model, scenario)
    _one_line(exc)


def test_an_edited_cache_fails_its_hash_and_other_files_are_not_caches(fitted, tmp_path: Path) -> None:
    scenario, model, ckpt, _ = fitted
    cache = ScenarioAPS.render(model, scenario)
    archive = {"format": CACHE_FORMAT, "sha256": "0" * 64, "payload": cache._payload()}
    torch.save(archive, tmp_path / "edited.pt")
    with pytest.raises(APSCacheError, match="does not match the SHA-256"):
        ScenarioAPS.load(tmp_path / "edited.pt", model)
    with pytest.raises(APSCacheError, match=f"no `{CACHE_FORMAT}` header"):
        ScenarioAPS.load(ckpt, model)  # the checkpoint given as the cache: refused, never overwritten
    (tmp_path / "notes.txt").write_text("hello")
    cases = [
        (tmp_path / "notes.txt", "not a PyTorch archive"),
        (tmp_path, "is a folder"),
        (tmp_path / "no.pt", "not found"),
    ]
    for path, message in cases:
        with pytest.raises(APSCacheError, match=message) as exc:
            load_or_render(model, scenario, path) if path.exists() else ScenarioAPS.load(path)
        _one_line(exc)
    payload = cache._payload()
    payload["aps"] = payload["aps"][:-1]  # shapes that do not fit, under a valid hash
    torch.save({"format": CACHE_FORMAT, "sha256": content_hash(payload), "payload": payload}, tmp_path / "cut.pt")
    with pytest.raises(APSCacheError, match="not a consistent APS cache"):
        ScenarioAPS.load(tmp_path / "cut.pt")


class _Payload:
    """Unpickling this object would create the marker file (what an attacker's cache would do instead)."""

    def __init__(self, marker: Path) -> None:
        self.marker = marker

    def __reduce__(self):
        return (builtins.open, (str(self.marker), "w"))


def plant_payloads(folder: Path, marker: Path) -> list[Path]:
    """Cache files carrying a code payload: in a torch archive (as the header, inside the payload) and as a bare
    pickle."""
    folder.mkdir(parents=True, exist_ok=True)
    files = []
    inside = {"format": CACHE_FORMAT, "sha256": "x", "payload": {"aps": _Payload(marker)}}
    for name, obj in (("header.pt", _Payload(marker)), ("inside.pt", inside)):
        torch.save(obj, folder / name)
        files.append(folder / name)
    (folder / "bare.pkl").write_bytes(pickle.dumps(_Payload(marker)))
    files.append(folder / "bare.pkl")
    assert not marker.exists()
    return files


def test_a_planted_code_payload_never_runs_and_is_refused_in_one_line(fitted, tmp_path: Path) -> None:
    scenario, model, _, _ = fitted
    marker = tmp_path / "pwned"
    for path in plant_payloads(tmp_path / "evil", marker):
        with pytest.raises(APSCacheError, match=r"refused|not a PyTorch archive") as exc:
            load_or_render(model, scenario, path)
        _one_line(exc)
        assert not marker.exists(), path
        assert path.stat().st_size > 0  # refused, not overwritten


def test_no_loader_in_the_package_unpickles() -> None:
    hits = [str(p) for p in SRC.rglob("*.py") if "weights_only=False" in p.read_text()]
    assert hits == []


def test_predict_rsrp_of_a_source_matches_the_model_method(fitted) -> None:
    scenario, model, _, _ = fitted
    pairs, _ = scenario.rsrp_table(2, "csi")
    np.testing.assert_array_equal(
        predict_rsrp(model, scenario, 2, "csi", pairs), model.predict_rsrp(scenario, 2, "csi", pairs)
    )


def test_a_tensor_larger_than_its_stored_data_is_refused_before_hashing(fitted, tmp_path: Path) -> None:
    scenario, model, _, _ = fitted
    payload = ScenarioAPS.render(model, scenario)._payload()
    payload["aps"][0] = torch.zeros(1).expand(10**6, 10**4)  # 40 GB if hashed or copied; 4 bytes in the file
    torch.save({"format": CACHE_FORMAT, "sha256": "x", "payload": payload}, tmp_path / "stride0.pt")
    assert (tmp_path / "stride0.pt").stat().st_size < 10**6
    with pytest.raises(APSCacheError, match="claims more elements than the file stores") as exc:
        ScenarioAPS.load(tmp_path / "stride0.pt", model, scenario)
    _one_line(exc)


class _DistanceField:
    """A field source (unseen grids supported) whose APS is one bin of gain 1 / (1 + grid id)."""

    name, angle_grid, device, supports_unseen_grids, fingerprint = "field", GRID, torch.device("cpu"), True, None
    run_info: ClassVar[dict] = {}

    def aps(self, cell_ids: np.ndarray, grid_ids: np.ndarray, grid_xyz: np.ndarray | None = None) -> torch.Tensor:
        out = torch.zeros(len(cell_ids), GRID.num_bins)
        out[:, 7] = torch.as_tensor(1.0 / (1.0 + np.asarray(grid_ids, dtype=np.float64)), dtype=torch.float32)
        return out

    def level_offset_db(self, cell_ids: np.ndarray, beam_type: str, grid_ids: np.ndarray | None = None) -> None:
        return None

    def content_sha256(self) -> str:
        return "d" * 64


def test_a_field_model_is_rendered_at_the_grids_within_the_networks_hearing_range(fitted) -> None:
    scenario, model, _, _ = fitted
    source = _DistanceField()
    m = scenario.measurements
    r1 = m[(m["round"] == 1).to_numpy()]
    cells = scenario.cells[1].set_index("cell_id")
    grids = scenario.grids.set_index("grid_id")
    far = np.hypot(
        cells.loc[r1["cell_id"], "x"].to_numpy() - grids.loc[r1["grid_id"], "x"].to_numpy(),
        cells.loc[r1["cell_id"], "y"].to_numpy() - grids.loc[r1["grid_id"], "y"].to_numpy(),
    ).max()
    assert hearing_range_m(scenario) == pytest.approx(far)
    # A grid moved 400 m away, with its reports dropped: out of the network's hearing range.
    moved = scenario.grids.copy()
    last = moved.index[-1]
    moved.loc[last, "x"] += 400.0
    kept = m[(m["grid_id"] != moved.loc[last, "grid_id"]).to_numpy()].reset_index(drop=True)
    near = dataclasses.replace(scenario, grids=moved, measurements=kept)
    grids = moved.set_index("grid_id")
    reach = REACH_MARGIN * hearing_range_m(near)
    assert reach < 400.0
    rows = render_rows(source, near)
    cache = ScenarioAPS.render(source, near)
    for i, cell in enumerate(near.cell_ids()):
        d = np.hypot(*(grids.loc[near.grid_ids(), ["x", "y"]].to_numpy() - cells.loc[cell, ["x", "y"]].to_numpy()).T)
        np.testing.assert_array_equal(rows[i], np.flatnonzero(d <= reach))
        np.testing.assert_array_equal(cache.known[i], d <= reach)
        # compact rows: one per grid in reach, the source's own values there
        assert cache.aps[i].shape == (len(rows[i]), 1)
        expect = 1.0 / (1.0 + near.grid_ids()[rows[i]].astype(np.float64))
        np.testing.assert_allclose(cache.aps[i][:, 0].numpy(), expect, rtol=1e-7)
    assert 0 < cache.known.sum() < cache.known.size
    # free cells: only the grids some free cell reaches, for every cell heard there
    first = near.cell_ids()[:1]
    area = np.zeros(len(near.grid_ids()), dtype=bool)
    area[rows[0]] = True
    for r, r_free in zip(rows, render_rows(source, near, first), strict=True):
        np.testing.assert_array_equal(r_free, r[area[r]])
    assert cache.pairs == "the (cell, grid) pairs within the model's reach"
    # measured: a field model too only at the measured round-1 pairs, as WNOMP
    only = ScenarioAPS.render(source, near, measured=True)
    for a, b in zip(render_rows(source, near, measured=True), render_rows(model, near), strict=True):
        np.testing.assert_array_equal(a, b)
    assert only.pairs == "measured round-1 pairs only" and only.known.sum() <= cache.known.sum()
    # a WNOMP-like source keeps its measured pairs, whatever the range
    wn = render_rows(model, near)
    pairs = near.measurements[(near.measurements["round"] == 1).to_numpy()]
    for i, cell in enumerate(near.cell_ids()):
        measured = np.unique(pairs.loc[pairs["cell_id"] == cell, "grid_id"].to_numpy())
        np.testing.assert_array_equal(near.grid_ids()[wn[i]], measured)


def test_a_cache_of_an_older_format_is_refused_with_what_to_do(fitted, tmp_path: Path) -> None:
    scenario, model, _, _ = fitted
    payload = ScenarioAPS.render(model, scenario)._payload()
    torch.save({"format": "rflscm-aps-cache/1", "sha256": content_hash(payload), "payload": payload}, tmp_path / "o.pt")
    with pytest.raises(APSCacheError, match=r"another format .*delete it") as exc:
        ScenarioAPS.load(tmp_path / "o.pt", model)
    _one_line(exc)


class _Mixed(APSCache):
    """A source whose odd grids mix in a second APS (its own, shifted by 5 bins, 4× as strong) with weight 0.3 and
    whose CSI-RS predictions carry a +2 dB offset: what RF-LSCM's posterior pairs do (:class:`RsrpMix`)."""

    def other(self, cell_ids: np.ndarray, grid_ids: np.ndarray) -> torch.Tensor:
        return 4.0 * torch.roll(self.aps(cell_ids, grid_ids), 5, dims=1)

    def rsrp_mix(self, cell_ids: np.ndarray, grid_ids: np.ndarray, beam_type: str) -> RsrpMix | None:
        weight = torch.as_tensor(np.asarray(grid_ids) % 2 == 1, dtype=torch.float32) * 0.3
        return RsrpMix(self.other(cell_ids, grid_ids), weight)

    def level_offset_db(self, cell_ids: np.ndarray, beam_type: str, grid_ids: np.ndarray | None = None) -> np.ndarray:
        return np.full(len(np.asarray(cell_ids).reshape(-1)), 2.0 if beam_type == "csi" else 0.0)


class _Other(APSCache):
    """The second APS of :class:`_Mixed` as a source of its own (no offset, no mix)."""

    def aps(self, cell_ids: np.ndarray, grid_ids: np.ndarray, grid_xyz: np.ndarray | None = None) -> torch.Tensor:
        return 4.0 * torch.roll(super().aps(cell_ids, grid_ids, grid_xyz), 5, dims=1)


@pytest.mark.parametrize("beam_type", ["ssb", "csi"])
def test_a_mixed_source_predicts_the_db_average_and_its_offset_only_on_its_own_share(fitted, beam_type: str) -> None:
    scenario, model, _, _ = fitted
    pairs = scenario.measurements[scenario.measurements["round"] == 1][["cell_id", "grid_id"]].drop_duplicates()
    pairs = pairs.reset_index(drop=True)
    mixed = predict_rsrp(_Mixed(model), scenario, 2, beam_type, pairs)
    own = predict_rsrp(model, scenario, 2, beam_type, pairs) + (2.0 if beam_type == "csi" else 0.0)
    other = predict_rsrp(_Other(model), scenario, 2, beam_type, pairs)
    w = np.where(pairs["grid_id"].to_numpy() % 2 == 1, 0.3, 0.0)[:, None]
    assert 0 < w.mean() < 0.3 and np.nanmax(np.abs(other - own)) > 1.0  # both kinds of pairs, and a real difference
    np.testing.assert_allclose(mixed, (1 - w) * own + w * other, atol=1e-4)


def test_the_optimisers_cache_keeps_the_mix_and_its_best_beam_power_is_predicts(fitted, tmp_path: Path) -> None:
    """ScenarioAPS renders the mix with the APS, saves and loads it, and the optimiser's best-beam power of the
    present antennas is the best beam of `predict`'s SSB RSRP (the same dB average); a damaged weight is refused."""
    from rflscm.network.candidates import CellSensing, best_beam_power
    from rflscm.network.space import build_space

    scenario, model, _, _ = fitted
    source = _Mixed(model)
    cache = ScenarioAPS.render(source, scenario)
    assert cache.mix_aps is not None and cache.mix_weight is not None
    assert any(len(w) and float(w.max()) == pytest.approx(0.3) for w in cache.mix_weight)
    path = cache.save(tmp_path / "mixed.pt")
    loaded = ScenarioAPS.load(path, source, scenario)
    assert loaded.mix_aps is not None and loaded.mix_weight is not None
    for a, b in zip(cache.mix_aps, loaded.mix_aps, strict=True):
        torch.testing.assert_close(a, b)
    space = build_space({}, scenario.cells[1], scenario.meta.codebooks)
    dirs = cache.angle_grid.directions(dtype=torch.float32)
    pos = 0
    cell = int(cache.cell_ids[pos])
    sensing = CellSensing(scenario, cell, 1, dirs[torch.as_tensor(cache.bins[pos])], space.cells[pos])
    power = best_beam_power(cache.aps[pos], sensing.matrices([space.cells[pos].current]), cache.mix_of(pos))[0]
    grids = cache.grid_ids[cache.known[pos]]
    rsrp = predict_rsrp(source, scenario, 1, "ssb", pd.DataFrame({"cell_id": cell, "grid_id": grids}))
    np.testing.assert_allclose(10 * np.log10(power.double().numpy()), np.nanmax(rsrp, axis=1), atol=1e-3)
    plain = best_beam_power(cache.aps[pos], sensing.matrices([space.cells[pos].current]))[0]
    assert float((10 * torch.log10(power / plain)).abs().max()) > 0.5  # the mix moved the optimiser's powers too
    payload = torch.load(path, weights_only=True)["payload"]
    payload["mix_weight"][pos] = payload["mix_weight"][pos] * 0 + 1.5
    cache_bad = ScenarioAPS._from_payload(payload)
    with pytest.raises(APSCacheError, match="damaged mixed APS or weight"):
        cache_bad._check(path)


class _Capped(APSCache):
    """A source that caps its odd grids' pairs at -100 dBm on the strongest round-1 SSB beam."""

    def round1_caps(self, cell_ids: np.ndarray, grid_ids: np.ndarray) -> np.ndarray:
        return np.where(np.asarray(grid_ids) % 2 == 1, 1e-10, np.nan)


def test_capped_pairs_never_predict_their_round1_ssb_above_the_cap_and_the_others_are_untouched(fitted) -> None:
    scenario, model, _, _ = fitted
    pairs = scenario.measurements[scenario.measurements["round"] == 1][["cell_id", "grid_id"]].drop_duplicates()
    pairs = pairs.reset_index(drop=True)
    odd = pairs["grid_id"].to_numpy() % 2 == 1
    own = predict_rsrp(model, scenario, 1, "ssb", pairs)
    capped = predict_rsrp(_Capped(model), scenario, 1, "ssb", pairs)
    assert (np.nanmax(own[odd], axis=1) > -100.0).any()  # the cap binds somewhere
    np.testing.assert_allclose(
        np.nanmax(capped[odd], axis=1), np.minimum(np.nanmax(own[odd], axis=1), -100.0), atol=1e-6
    )
    np.testing.assert_array_equal(capped[~odd], own[~odd])
    # one scale per pair: the beams keep their differences (the APS is scaled, not clipped)
    diff = capped[odd] - own[odd]
    np.testing.assert_allclose(np.nanmax(diff, axis=1), np.nanmin(diff, axis=1), atol=1e-6)
    cache = ScenarioAPS.render(_Capped(model), scenario)  # the optimiser's cache is capped the same way
    i = 0
    rows = cache.grid_ids[cache.known[i]]
    a = scenario.sensing(int(cache.cell_ids[i]), "ssb", cache.angle_grid, round=1)[:, torch.as_tensor(cache.bins[i])]
    best = 10 * torch.log10((cache.aps[i].double() @ a.double().T).amax(1))
    assert float(best[torch.as_tensor(rows % 2 == 1)].max()) <= -100.0 + 1e-6


def test_a_cell_with_no_pair_in_the_area_renders_to_an_empty_row_set(fitted) -> None:
    """A cluster's area can leave a cell with no grid to render (it reaches none of the free cells' grids): its
    cache entry is empty, with or without a mixing source (a regression: the kept bins were read off an empty
    array)."""
    scenario, model, _, _ = fitted
    m = scenario.measurements
    silent = int(scenario.cell_ids()[0])  # no round-1 row left: WNOMP renders it nowhere
    quiet = dataclasses.replace(scenario, measurements=m[~((m["round"] == 1) & (m["cell_id"] == silent))])
    for source in (model, _Mixed(model)):
        cache = ScenarioAPS.render(source, quiet)
        assert not cache.known[0].any() and len(cache.bins[0]) == 0 and cache.aps[0].shape[0] == 0
        assert cache.known[1:].any()


def test_the_row_store_gives_back_each_keys_latest_row_whatever_block_and_order() -> None:
    """Rows added in blocks (dense, or sparse as workers answer them) come back exactly, in any order and with repeats;
    a key added again answers its latest row; empty rows and an empty block are rows too."""
    from rflscm.eval.cache import SparseRowStore
    from rflscm.parallel.aps import sparse_rows

    gen = torch.Generator().manual_seed(0)
    first = torch.rand(5, 12, generator=gen) * (torch.rand(5, 12, generator=gen) < 0.3)
    first[2] = 0.0  # a row without a nonzero bin
    second = torch.rand(3, 12, generator=gen) * (torch.rand(3, 12, generator=gen) < 0.5)
    store = SparseRowStore(12, "cpu")
    store.add([(1, g) for g in range(5)], first)
    store.add_sparse([(2, 0), (1, 4), (2, 1)], sparse_rows(second))  # (1, 4) replaced
    store.add_sparse([], sparse_rows(second[:0]))
    assert len(store) == 7 and (1, 4) in store and (3, 0) not in store
    keys = [(2, 1), (1, 0), (1, 4), (1, 2), (1, 0), (2, 0)]
    expected = torch.stack([second[2], first[0], second[1], first[2], first[0], second[0]])
    assert torch.equal(store.dense(keys), expected)
    assert store.dense([]).shape == (0, 12)
