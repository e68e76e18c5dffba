"""What a run leaves for people: file and folder modes from the umask, index.html figures rounded with units and
parameters at their search bounds flagged, figure labels that cannot be misread."""

from __future__ import annotations

import os
import stat

import numpy as np
import pandas as pd
import pytest

from engine_model import io
from engine_model.calibration.plots import BSFC_PLOT_MAX_G_KWH, bsfc_scale
from engine_model.report import bound_note, format_parameters, write_index
from engine_model.tables.export import cell_label


@pytest.fixture(params=[0o022, 0o027])
def umask(request):
    old = os.umask(request.param)
    try:
        yield request.param
    finally:
        os.umask(old)


def _mode(p):
    return stat.S_IMODE(os.stat(p).st_mode)


def test_files_and_folders_get_the_umask_of_the_moment(tmp_path, umask):
    """The umask is read at each write, not once at import: 0644/0755 under 022, 0640/0750 under 027."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    f_mode, d_mode = 0o666 & ~umask, 0o777 & ~umask
    assert io.current_umask() == umask
    run = tmp_path / "run"
    written = [io.write_csv(pd.DataFrame({"a": [1]}), run / "maps" / "t.csv"),
               io.write_parquet(pd.DataFrame({"a": [1]}), run / "t.parquet"),
               io.write_json({"a": 1}, run / "manifest.json"),
               io.write_text("<html></html>", run / "index.html")]
    fig, ax = plt.subplots()
    ax.plot([0, 1])
    written.append(io.write_figure(fig, run / "figures" / "f.png"))
    plt.close(fig)
    for p in written:
        assert _mode(p) == f_mode, p
    for d in (run, run / "maps", run / "figures"):
        assert _mode(d) == d_mode, d
    tmp = io.make_temp_dir(run, ".maps.")
    (tmp / "x.csv").write_text("a\n")
    os.replace(tmp, run / "maps2")
    assert _mode(run / "maps2") == d_mode and _mode(run / "maps2" / "x.csv") == f_mode
    assert not [p for p in run.rglob("*.tmp")]


def _manifest(quick: bool, recovery: float) -> dict:
    return {
        "engine": "yamaha_r6_fs", "spec_hash": "12dbde9b26db0000", "calibrated_spec_hash": "f80b8dbc7bc00000",
        "bench": "bench.csv", "stages": ["calibration", "model"], "quick": quick, "settings": {"step_deg": 1.0},
        "calibration": {
            "airflow": {"parameters": {"exhaust.runner_length_m": 0.21555296992839162,
                                       "intake.restrictor_recovery": recovery},
                        "bounds": {"exhaust.runner_length_m": [0.2, 0.7], "intake.restrictor_recovery": [0.3, 0.95]},
                        "at_bound": {}, "max_abs_ga_rel_pct": 2.466},
            "identification": {"fit_ok": 1, "points": 2, "search_range": {"bdur_10_90_deg": [20, 50],
                                                                          "wiebe_m": [2, 8]},
                               "per_point": [{"point_id": "wot_8000", "bdur_10_90_deg": 50.0, "wiebe_m": 2.38},
                                             {"point_id": "wot_9000", "bdur_10_90_deg": 41.2, "wiebe_m": 4.1}]}},
        "model": {"holdout": {"bdur_rmse_deg": 2.957932182407641, "m_rmse": 0.9819141115130845},
                  "model_chosen": {"bdur_10_90_deg": "gp", "wiebe_m": "poly"}, "lines": ["x"]},
        "wall_time_s": 1980.4, "timings_s": {"calibration": 755.2, "model": 534.0},
    }


def test_index_rounds_numbers_shows_the_run_mode_and_flags_bounds(tmp_path):
    from flows.run import index_summary

    rows = dict(index_summary(_manifest(quick=True, recovery=0.95)))
    text = " ".join(rows.values())
    assert "0.21555296992839162" not in text and "{" not in text and "'" not in text
    assert rows["airflow match"].startswith("exhaust.runner_length_m = 0.216 m (near lower bound 0.2 m)")
    assert "intake.restrictor_recovery = 0.95 (at upper bound 0.95)" in rows["airflow match"]
    assert "BDUR10-90 at its upper search bound 50 deg at 1 point(s) (wot_8000)" in rows["identification"]
    assert "--quick" in rows["run mode"] and "crank step 1 deg" in rows["run mode"]
    assert rows["global model"].startswith("bdur_10_90_deg gp, wiebe_m poly")
    full = dict(index_summary(_manifest(quick=False, recovery=0.6)))
    assert "--quick" not in full["run mode"] and "bound" not in full["airflow match"].split(",")[1]
    page = write_index(tmp_path, "run", list(rows.items()), [])
    assert "at upper bound 0.95" in page.read_text()


@pytest.mark.parametrize("value, note", [(0.40, " (at upper bound 0.4)"), (0.2, " (at lower bound 0.2)"),
                                         (0.392, " (near upper bound 0.4)"), (0.3, "")])
def test_bound_note(value, note):
    assert bound_note(value, 0.2, 0.4) == note


def test_at_bound_flag_from_the_fit_is_shown_without_bounds():
    assert format_parameters({"a.x_m": 0.123456}, None, {"a.x_m": True}) == "a.x_m = 0.123 m (at a search bound)"


def test_bsfc_scale_is_clipped_and_marks_near_zero_power_cells():
    z = np.array([[250.0, 320.0, 480.0], [720000.0, -5.0, np.inf]])
    levels, over = bsfc_scale(z)
    assert levels[0] == pytest.approx(250.0) and levels[-1] == pytest.approx(BSFC_PLOT_MAX_G_KWH)
    assert over.tolist() == [[False, False, False], [True, True, True]]


def test_knock_limited_cell_label_has_no_letter_suffix():
    assert cell_label("spark_advance", 26.62, 1, "knock") == "26.6*"
    assert cell_label("spark_advance", 26.62, 1, "mbt") == "26.6"
    assert cell_label("injection_time", 3.456, 3, "knock") == "3.46"
    assert not any(c.isalpha() for c in cell_label("spark_advance", 26.6, 1, "knock"))
