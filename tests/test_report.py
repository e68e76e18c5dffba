"""The run index page links what exists and marks what is missing."""

from pathlib import Path

from engine_model.report import write_index


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
