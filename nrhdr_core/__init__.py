"""nrhdr core: the non-regular ND HDR camera chain in plain numpy/numba (no GStreamer).

One module per stage (docs/ARCHITECTURE.md): mask, profile, sensor, simulate, validity, crosstalk,
calibration, reconstruction (+ fse), tonemap, metrics, analysis, io. Importing this package compiles
nothing; numba kernels compile (and are cached) on first use.
"""
__version__ = "0.1.0"


def reconstruct(values, known, method="fse", preset="balanced", lower=None, upper=None, **params):
    """Fill missing pixels; see `nrhdr_core.reconstruction.reconstruct`."""
    from .reconstruction import reconstruct as _r
    return _r(values, known, method=method, preset=preset, lower=lower, upper=upper, **params)


__all__ = ["reconstruct", "__version__"]
