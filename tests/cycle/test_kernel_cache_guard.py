"""The guard that drops numba's cached cycle kernels when any kernel source changes (engine_model/cycle/__init__.py)."""

from engine_model.cycle import KERNEL_SOURCES, STAMP_NAME, drop_stale_kernel_caches


def _tree(tmp_path):
    src = [tmp_path / "a.py", tmp_path / "b.py"]
    src[0].write_text("X = 1\n")
    src[1].write_text("Y = 2\n")
    cache = tmp_path / "__pycache__"
    cache.mkdir()
    return src, cache


def _cached(cache):
    for name in ("k.kernel-10.py311.nbi", "k.kernel-10.py311.1.nbc"):
        (cache / name).write_bytes(b"machine code")


def test_cache_is_kept_while_the_sources_are_unchanged_and_dropped_when_one_changes(tmp_path, monkeypatch):
    monkeypatch.delenv("NUMBA_CACHE_DIR", raising=False)
    src, cache = _tree(tmp_path)
    _cached(cache)
    assert drop_stale_kernel_caches(src, cache)            # no stamp yet: cache of unknown provenance goes
    assert not list(cache.glob("*.nb?")) and (cache / STAMP_NAME).exists()
    _cached(cache)
    assert not drop_stale_kernel_caches(src, cache)        # same sources: kept
    assert len(list(cache.glob("*.nb?"))) == 2
    src[1].write_text("Y = 3\n")                           # an inlined module changes, not the kernel's own file
    assert drop_stale_kernel_caches(src, cache)
    assert not list(cache.glob("*.nb?"))
    (cache / "unrelated.pyc").write_bytes(b"")
    _cached(cache)
    assert not drop_stale_kernel_caches(src, cache)
    assert (cache / "unrelated.pyc").exists()


def test_relocated_cache_is_left_to_numba(tmp_path, monkeypatch):
    src, cache = _tree(tmp_path)
    _cached(cache)
    monkeypatch.setenv("NUMBA_CACHE_DIR", str(tmp_path / "elsewhere"))
    assert not drop_stale_kernel_caches(src, cache)
    assert len(list(cache.glob("*.nb?"))) == 2


def test_the_guard_covers_every_kernel_module_and_thermo():
    names = {p.name for p in KERNEL_SOURCES}
    assert {"engine.py", "volumes.py", "network.py", "flow.py", "layout.py", "thermo.py"} <= names
