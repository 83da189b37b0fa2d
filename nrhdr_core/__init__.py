"""nrhdr core: the non-regular ND HDR camera chain in plain numpy/numba (no GStreamer).

One module per stage (docs/ARCHITECTURE.md): mask, profile, sensor, simulate, validity, crosstalk,
calibration, reconstruction (+ fse), tonemap, metrics, analysis, io. Importing this package compiles
nothing; numba kernels compile (and are cached) on first use.
"""
import os as _os

__version__ = "0.1.0"

# GStreamer runs elements in several streaming threads that may call parallel kernels at once; numba's
# fallback "workqueue" threading layer is not safe for that, so require a thread-safe one (OpenMP via
# libgomp1, or TBB). Set NUMBA_THREADING_LAYER yourself to override.
_os.environ.setdefault("NUMBA_THREADING_LAYER", "threadsafe")
# libgomp's default ACTIVE wait makes idle worker threads spin after every parallel region: on 2 cores that
# steals the core from the next serial step and from the other streaming threads (measured on the shared
# 2-core machine: pull-push 1080p 65-70 ms wall and ~50 ms CPU with 2 threads, 12 ms / 9 ms with PASSIVE;
# docs/BENCHMARKS.md). Must be set before the OpenMP runtime loads; set OMP_WAIT_POLICY yourself to override.
_os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")


def _drop_stale_kernel_caches(root=None) -> bool:
    """numba's cache checks a kernel against its own source file only: a kernel that inlines a function of
    another module (`pullpush.pull_row` in `reconstruction` and `demosaic`, ...) would keep the old code after
    that module changed. So the package's cached kernels (`__pycache__/*.nbi`, `*.nbc` under `root`, default
    this package) are tied to a digest of all its sources, stored beside them: when the stored digest is
    missing or differs, they are removed and compile again on first use. Returns whether it removed them;
    a read-only installation is left as it is."""
    import hashlib
    from pathlib import Path
    root = Path(root) if root is not None else Path(__file__).resolve().parent
    digest = hashlib.sha256()
    for f in sorted(root.rglob("*.py")):
        digest.update(str(f.relative_to(root)).encode() + b"\0" + f.read_bytes() + b"\0")
    stamp = root / "__pycache__" / "nrhdr-kernel-sources.sha256"
    try:
        if stamp.read_text() == digest.hexdigest():
            return False
    except OSError:
        pass
    try:
        for f in root.rglob("__pycache__/*"):
            if f.suffix in (".nbi", ".nbc"):
                f.unlink(missing_ok=True)
        stamp.parent.mkdir(exist_ok=True)
        tmp = stamp.with_name(f"{stamp.name}.{_os.getpid()}.tmp")
        tmp.write_text(digest.hexdigest())
        tmp.replace(stamp)
    except OSError:
        return False
    return True


_drop_stale_kernel_caches()


def reconstruct(values, known, method="fse", preset="balanced", lower=None, upper=None, **params):
    """Fill missing pixels; see `nrhdr_core.reconstruction.reconstruct`."""
    from .reconstruction import reconstruct as _r
    return _r(values, known, method=method, preset=preset, lower=lower, upper=upper, **params)


__all__ = ["reconstruct", "__version__"]
