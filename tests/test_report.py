"""The run index page links what exists and marks what is missing; a stage report links its figures
relative to itself."""

from pathlib import Path

import pandas as pd

from engine_model.report import write_index, write_report


def test_index_links_files_and_marks_missing(tmp_path: Path):
    (tmp_path / "maps").mkdir()
    (tmp_path / "maps" / "spark_advance.csv").write_text("throttle_pct,1000\n0,10\n")
    (tmp_path / "fig.png").write_bytes(b"\x89PNG\r\n")
    page = write_index(tmp_path, "run x", [("wall time", "12 s")],
                       [("Maps", "tables", ["maps/spark_advance.csv", tmp_path / "fig.png", "gap/report.html"])])
    text = page.read_text()
    assert page == tmp_path / "index.html"
    assert "href='maps/spark_advance.csv'" in text
    assert "<img src='fig.png'" in text
    assert "gap/report.html (missing)" in text
    assert "12 s" in text
    assert not list(tmp_path.glob("*.tmp*"))


def test_stage_report_links_its_figure_relative_to_the_report(tmp_path: Path, monkeypatch):
    # the stages write into a relative folder (``results/<run>.partial/model``) that is renamed when the
    # run completes: a link carrying that folder's path breaks, one relative to the report does not
    monkeypatch.chdir(tmp_path)
    folder = Path("results") / "run.partial" / "model"
    (folder / "figs").mkdir(parents=True)
    (folder / "figs" / "curve.png").write_bytes(b"\x89PNG\r\n")
    md, ht = write_report(folder, "model", "Model", [("Fit", [pd.DataFrame({"a": [1.0]}),
                                                              folder / "figs" / "curve.png"])])
    assert "![curve](figs/curve.png)" in md.read_text()
    assert "<img src='figs/curve.png'" in ht.read_text()
    assert "partial" not in md.read_text() + ht.read_text()
