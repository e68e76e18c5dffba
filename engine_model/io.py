"""Atomic file output: write to a temporary file in the target folder, then rename.

A reader never sees a half-written file, and an interrupted run leaves either
the old file or none.  Files get the permissions the user's umask gives a new
file (0644 under the usual umask 022), not the private 0600 of a temporary file.
"""

from __future__ import annotations

import json
import os
import tempfile
import threading
from pathlib import Path

import pandas as pd


_UMASK_LOCK = threading.Lock()


def current_umask() -> int:
    """The process umask now (0o022 on most systems).

    Read from ``/proc/self/status`` where the kernel reports it (Linux), which changes nothing;
    elsewhere by setting and restoring it under a lock (``os.umask`` can only be read by setting it).
    """
    try:
        with open("/proc/self/status") as fh:
            for line in fh:
                if line.startswith("Umask:"):
                    return int(line.split()[1], 8)
    except (OSError, ValueError, IndexError):
        pass
    with _UMASK_LOCK:
        mask = os.umask(0o077)
        os.umask(mask)
    return mask


def file_mode() -> int:
    """Mode of a new file under the current umask (0o644 under umask 022)."""
    return 0o666 & ~current_umask()


def dir_mode() -> int:
    """Mode of a new folder under the current umask (0o755 under umask 022)."""
    return 0o777 & ~current_umask()


def make_temp_dir(parent: Path, prefix: str) -> Path:
    """A fresh hidden folder in ``parent`` with the mode the umask gives a new folder (not mkdtemp's 0700),
    to be filled and renamed into place."""
    tmp = Path(tempfile.mkdtemp(prefix=prefix, suffix=".tmp", dir=parent))
    os.chmod(tmp, dir_mode())
    return tmp


def atomic_write(path: Path, write) -> Path:
    """Call ``write(tmp_path)`` on a temporary file next to ``path``, then rename it onto ``path``.

    The file gets mode ``0666 & ~umask`` (the umask at the time of the call); on any failure the temporary
    file is removed and ``path`` is untouched.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    os.close(fd)
    try:
        write(tmp)
        os.chmod(tmp, file_mode())
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise
    return path


def write_parquet(df: pd.DataFrame, path) -> Path:
    """Write a DataFrame to Parquet (pyarrow) atomically."""
    return atomic_write(path, lambda tmp: df.to_parquet(tmp, engine="pyarrow", index=False))


def write_csv(df: pd.DataFrame, path, **kwargs) -> Path:
    """Write a DataFrame to CSV atomically."""
    return atomic_write(path, lambda tmp: df.to_csv(tmp, index=False, **kwargs))


def write_text(text: str, path) -> Path:
    """Write text atomically."""
    return atomic_write(path, lambda tmp: Path(tmp).write_text(text))


def write_json(obj, path) -> Path:
    """Write JSON (sorted keys, indented) atomically."""
    return write_text(json.dumps(obj, indent=2, sort_keys=True, default=str) + "\n", path)


def write_figure(fig, path, dpi: int = 100) -> Path:
    """Save a matplotlib figure as PNG atomically (same file mode as every other output)."""
    return atomic_write(path, lambda tmp: fig.savefig(tmp, dpi=dpi, format="png"))


def read_table(path, text_columns=("point_id",)) -> pd.DataFrame:
    """Read a CSV or Parquet table; ValueError naming the file on failure.

    ``text_columns`` present in a CSV are read as text (an id "007" stays "007").
    """
    p = Path(path)
    if not p.is_file():
        raise ValueError(f"{p}: file not found")
    suffix = p.suffix.lower()
    try:
        if suffix == ".csv":
            head = pd.read_csv(p, nrows=0).columns
            return pd.read_csv(p, dtype={c: str for c in text_columns if c in head})
        if suffix in (".parquet", ".pq"):
            return pd.read_parquet(p)
    except Exception as exc:  # noqa: BLE001 - report any parser failure with the file name
        raise ValueError(f"{p}: could not be read as {suffix[1:]}: {exc}") from None
    raise ValueError(f"{p}: unsupported file type {suffix!r}; expected .csv or .parquet")
