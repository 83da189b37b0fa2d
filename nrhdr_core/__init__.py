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


def reconstruct(values, known, method="fse", preset="balanced", lower=None, upper=None, **params):
    """Fill missing pixels; see `nrhdr_core.reconstruction.reconstruct`."""
    from .reconstruction import reconstruct as _r
    return _r(values, known, method=method, preset=preset, lower=lower, upper=upper, **params)


__all__ = ["reconstruct", "__version__"]
