"""B9's time-to-target summary (:mod:`rflscm.bench.b09_time_to_target`) on hand-made MAE-vs-time curves."""

from __future__ import annotations


def test_b9_time_to_target_on_a_hand_made_curve() -> None:
    from rflscm.bench.b09_time_to_target import best, compare, time_to

    def rows(*points: tuple[float, float | None]) -> list[dict]:
        return [{"train_s": t, "mae_db": {"ssb": {"all": 1.0, "changed": m}, "csi": None}} for t, m in points]

    old = rows((5, 9.0), (10, 7.0), (20, 6.0), (40, 6.5), (80, 6.0))
    new = rows((5, 8.0), (10, None), (20, 5.5), (40, 4.0))
    assert time_to(old, "ssb", 7.0) == 10 and time_to(old, "ssb", 5.0) is None and time_to(old, "ssb", None) is None
    assert time_to(new, "ssb", 6.0) == 20  # a missing value is skipped, never taken as reached
    assert time_to(old, "ssb", 1.0, cells="all") == 5 and time_to(old, "csi", 99.0) is None
    assert best(old, "ssb") == (6.0, 20) and best(new, "csi") == (None, None)
    reached = compare(old, new, "ssb", 7.0)
    assert reached["old_time_to_wnomp_s"] == 10 and reached["new_time_to_wnomp_s"] == 20
    assert reached["ratio_old_new"] == 0.5 and reached["basis"] == "wnomp"
    missed = compare(old, new, "ssb", 5.0)  # the old model never reaches WNOMP: compare at its best
    assert missed["old_time_to_wnomp_s"] is None and missed["ratio_old_new"] is None and missed["basis"] == "old_best"
    assert missed["new_time_to_wnomp_s"] == 40
    assert missed["old_best_mae_db"] == 6.0 and missed["old_time_to_best_s"] == 20
    assert missed["new_time_to_old_best_s"] == 20 and missed["ratio_to_old_best"] == 1.0
    assert missed["new_best_mae_db"] == 4.0
    # a row's time carries its own finish_training, so a later row can be quicker than an earlier one
    finished = rows((60, 6.0), (45, 5.0), (70, 5.0))
    assert time_to(finished, "ssb", 6.0) == 45 and best(finished, "ssb") == (5.0, 45)


def test_b9_baseline_is_a_folder_holding_src(tmp_path) -> None:
    # the old model's code comes as a folder (no git where B9 runs, e.g. from an installed wheel)
    import pytest

    from rflscm.bench.b09_time_to_target import baseline_src
    from rflscm.errors import ConfigError

    pkg = tmp_path / "old" / "src" / "rflscm"
    pkg.mkdir(parents=True)
    (pkg / "__init__.py").write_text("")
    assert baseline_src(str(tmp_path / "old")) == (tmp_path / "old" / "src").resolve()
    assert baseline_src(tmp_path / "old" / "src") == (tmp_path / "old" / "src").resolve()
    with pytest.raises(ConfigError, match="needs --baseline PATH") as missing:
        baseline_src(None)
    assert "\n" not in str(missing.value)
    with pytest.raises(ConfigError, match="holds no src/rflscm"):
        baseline_src(tmp_path / "empty")


def test_b9_marks_are_geometric_and_end_at_the_cap() -> None:
    import itertools

    import pytest

    from rflscm.bench.b09_time_to_target import MARK_FACTOR, SETTINGS, _marks

    assert _marks(5.0, 40.0) == [5.0, 10.0, 20.0, 40.0]  # the cap itself is a mark when it falls on one
    marks = SETTINGS["quick"]["marks_s"]
    ratios = [b / a for a, b in itertools.pairwise(marks)]
    assert all(r == pytest.approx(MARK_FACTOR, rel=1e-4) for r in ratios)
    assert marks[0] == 5.0 and marks[-1] <= SETTINGS["quick"]["max_train_s"] < marks[-1] * MARK_FACTOR
