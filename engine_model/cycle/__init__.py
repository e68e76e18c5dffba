"""Numba kernels of the crank-angle-resolved cycle model.

Rule of this package: pure ``@njit(cache=True)`` functions over float64 scalars
and arrays, SI units, no I/O, no pandas, no logging.  The Python face that
builds the arrays from an :class:`~engine_model.spec.EngineSpec` lives in
:mod:`engine_model.sim.prepare` and :mod:`engine_model.simulate`.

The one exception to "no I/O" is the cache guard below, which runs once at
import, before any kernel is loaded.
"""

import hashlib
import os
from pathlib import Path

_HERE = Path(__file__).resolve().parent
#: Every source whose code ends up inside the compiled cycle kernels (numba
#: inlines called ``@njit`` functions, and ``FASTMATH`` in layout.py changes code
#: generation of all of them).
KERNEL_SOURCES = tuple(sorted(_HERE.glob("*.py"))) + (_HERE.parent / "thermo.py",)
STAMP_NAME = "kernel_sources.sha256"


def drop_stale_kernel_caches(sources=KERNEL_SOURCES, cache_dir: Path = _HERE / "__pycache__") -> bool:
    """Delete numba's cached cycle kernels when any kernel source changed since they were cached.

    numba's ``cache=True`` keys each cached function on the modification time
    and size of *its own* file only.  A kernel in engine.py that inlines a
    function of volumes.py or thermo.py would otherwise keep running the old
    machine code after those files change (measured on 2026-11-23: an edit of
    the ``FASTMATH`` constant did not reach flow.py's cached kernels).  The guard
    hashes all kernel sources into a stamp file next to the cache; on a
    mismatch it removes the cache files (``*.nbi`` index, ``*.nbc`` code) so
    that numba recompiles, then writes the new stamp.  Returns True if it
    cleared the cache.  A read-only install or a relocated cache
    (``NUMBA_CACHE_DIR``) is left alone: there numba's own rules apply.
    """
    if os.environ.get("NUMBA_CACHE_DIR"):
        return False
    digest = hashlib.sha256()
    for src in sources:
        digest.update(Path(src).name.encode())
        digest.update(Path(src).read_bytes())
    want = digest.hexdigest()
    stamp = Path(cache_dir) / STAMP_NAME
    try:
        if stamp.read_text().strip() == want:
            return False
    except OSError:
        pass
    try:
        Path(cache_dir).mkdir(exist_ok=True)
        for f in list(Path(cache_dir).glob("*.nbi")) + list(Path(cache_dir).glob("*.nbc")):
            f.unlink(missing_ok=True)
        tmp = stamp.with_name(f"{STAMP_NAME}.{os.getpid()}.tmp")
        tmp.write_text(want + "\n")
        os.replace(tmp, stamp)
    except OSError:
        return False
    return True


drop_stale_kernel_caches()
