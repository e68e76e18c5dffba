"""The progress lines' expected stage times: the reference run's times, scaled by the work asked for."""

import pytest

from flows.eta import REFERENCE_STAGE_S, expected_stage_s, minutes
from flows.settings import QUICK, RunSettings

DEFAULT = dict(quick=False, step_deg=0.5, bench_points=7, doe_points=16, map_cells=143, workers=2)


@pytest.mark.parametrize("stage", ["calibration", "model", "maps", "gap"])
def test_the_reference_run_gets_its_own_times(stage):
    assert expected_stage_s(stage, **DEFAULT) == pytest.approx(REFERENCE_STAGE_S[False][stage])


@pytest.mark.parametrize("stage,knob", [("calibration", "bench_points"), ("gap", "bench_points"),
                                        ("model", "doe_points"), ("maps", "map_cells")])
def test_each_stage_scales_with_its_own_work_and_only_with_it(stage, knob):
    base = expected_stage_s(stage, **DEFAULT)
    assert expected_stage_s(stage, **{**DEFAULT, knob: 2 * DEFAULT[knob]}) == pytest.approx(2 * base)
    others = [k for k in ("bench_points", "doe_points", "map_cells") if k != knob]
    for k in others:
        assert expected_stage_s(stage, **{**DEFAULT, k: 3 * DEFAULT[k]}) == pytest.approx(base)


def test_more_workers_and_a_coarser_step_are_faster_an_unknown_cluster_is_not_guessed():
    base = expected_stage_s("maps", **DEFAULT)
    assert expected_stage_s("maps", **{**DEFAULT, "workers": 4}) == pytest.approx(base / 2)
    assert expected_stage_s("maps", **{**DEFAULT, "step_deg": 1.0}) == pytest.approx(base / 2)
    assert expected_stage_s("maps", **{**DEFAULT, "workers": None}) == pytest.approx(base)


def test_the_quick_run_is_expected_to_be_shorter_than_the_default():
    def total(rs, cells):
        return sum(expected_stage_s(s, rs.quick, rs.step_deg, 7, rs.doe_points, cells, 2) for s in rs.stages)

    assert total(QUICK, 9) < total(RunSettings(), 143) / 2


@pytest.mark.parametrize("s,text", [(40, "40 s"), (700, "12 min"), (3960, "1 h 06 min"), (-3, "0 s")])
def test_minutes_reads_like_a_person_would_say_it(s, text):
    assert minutes(s) == text
