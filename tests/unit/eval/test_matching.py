"""``sogm-service eval matching`` on a slice of the Intel log, and the matcher's defaults."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import pytest

from sogm_service.adapters.carmen import read_carmen
from sogm_service.core.geometry import GridGeometry, Pose2D
from sogm_service.core.matching.match import match_window
from sogm_service.core.matching.params import MatchParams
from sogm_service.eval import matching as em
from sogm_service.service.config import MatchingSettings
from sogm_service.service.server.matcher import match_params
from tests.helpers import INTEL_LOG, needs_intel

SLICE = dict(start=110, stride=3, seed=5)


@pytest.fixture(scope="module")
def scans() -> list:  # type: ignore[type-arg]
    return list(read_carmen(INTEL_LOG, limit=140))


@needs_intel
def test_gates_evaluated_afterwards_equal_match_ism_run_with_them(scans: list) -> None:  # type: ignore[type-arg]
    """The trade-off table's premise: one permissive pass decides every gate exactly as
    ``match_ism`` with that gate would."""
    base = MatchParams()
    opened = em.evaluate(scans, {"v": base}, **SLICE)
    assert len(opened) == 10
    for gate in (em.Gate(6, 0.3, 0.0), em.Gate(12, 0.3, 0.0), em.Gate(4, 0.6, 0.05),
                 em.Gate(8, 0.45, 0.0)):
        params = replace(base, min_inliers=gate.min_inliers, min_score=gate.min_score,
                         min_gain=gate.min_gain)
        real = em.evaluate(scans, {"v": params}, gated=True, **SLICE)
        assert [t.index for t in real] == [t.index for t in opened]
        assert [t.reason == "ok" for t in real] == [t.accepted_by(gate) for t in opened]
        for r, o in zip(real, opened, strict=True):
            if r.reason == "ok":
                assert r.error_found == o.error_found  # the same correction
    # The gates do select: the slice has both outcomes at the default.
    default = em.Gate(base.min_inliers, base.min_score, base.min_gain)
    decided = {t.accepted_by(default) for t in opened}
    assert decided == {True, False}


@needs_intel
def test_accepted_corrections_land_near_the_truth(scans: list) -> None:  # type: ignore[type-arg]
    trials = em.evaluate(scans, {"v": MatchParams()}, start=100, stride=2, seed=1)
    row = em.summarize(trials, "v", em.Gate())
    assert row.trials == 20 and row.accepted >= 8
    assert row.gross == 0
    assert row.accepted_m < 0.1 and row.after_m < row.before_m
    # Raising min_inliers only removes acceptances (monotone), never adds any.
    counts = [em.summarize(trials, "v", em.Gate(k)).accepted for k in (4, 6, 8, 12, 16)]
    assert counts == sorted(counts, reverse=True)


@needs_intel
def test_command_prints_the_trade_off_table(tmp_path: Path,
                                            capsys: pytest.CaptureFixture[str]) -> None:
    out_csv = tmp_path / "trials.csv"
    assert em.main([str(INTEL_LOG), "--limit", "125", "--start", "115", "--stride", "5",
                    "--min-inliers", "6,12", "--quiet", "--csv", str(out_csv)]) == 0
    out = capsys.readouterr().out
    rows = [line for line in out.splitlines() if line.startswith("| ratio=1 |")]
    assert [r.split("|")[2].strip() for r in rows] == ["6", "12"]
    assert "/2 = " in rows[0]  # two trials (scans 115 and 120)
    assert len(out_csv.read_text().splitlines()) == 1 + 2


def test_command_refuses_a_missing_log(tmp_path: Path) -> None:
    assert em.main([str(tmp_path / "missing.log")]) == 2


def test_service_defaults_are_the_measured_operating_point() -> None:
    """The service's defaults are the core's, which are the README's measured point."""
    settings = MatchingSettings()
    params = match_params(settings, 0.05)
    assert settings.min_inliers == MatchParams().min_inliers == params.min_inliers == 6
    assert params.max_translation == pytest.approx(20.0)
    assert params.window_extra == 0.0
    assert params.min_score == MatchParams().min_score and params.ratio == 1.0


def test_margin_m_is_honoured() -> None:
    """[ism.matching] margin_m widens the map window around the claimed ISM by that much."""
    g = GridGeometry(0.05, 100, 80, Pose2D(1.0, 2.0, 0.3))
    plain = match_window(g, match_params(MatchingSettings(), 0.05))
    wider = match_window(g, match_params(MatchingSettings(margin_m=1.0), 0.05))
    assert wider.width - plain.width == 40 and wider.height - plain.height == 40  # 20 a side
    with pytest.raises(ValueError):
        MatchParams(window_extra=-1.0)
