"""Frequency Selective Extrapolation (FSE) in numba: the paper's reconstruction of the missing pixels
(section 2.2, ref. 9).

Block-wise sparse Fourier model fitted to the known pixels of a support area around each block
(Seiler & Kaup, SPL 2010; Seiler et al., TIP 2015, "FSR"), with the refinements of Genser et al.
(IWSSIP 2017/2018, PCS 2018): adaptive iteration count, spectral prior, processing order by neighbour
availability. Facts: ``/work/shared/docs/fse-reference.md``; the package and its measured choices:
``docs/FSE.md``.

Modules, in the order of the algorithm: ``params`` (presets, validation, tables), ``domain`` (statistics,
log domain offset, working image and the way back), ``bounds`` (data and local bounds), ``plan`` (quadtree
leaves, rounds), ``kernel`` (the block kernel, one function per step), ``parallel`` (worker, run),
``fallback`` (pixels no block could fill; the nearest fill is ``nrhdr_core.fill``), ``reconstruct`` (:func:`fse_reconstruct`, the steps on a frame).
Nothing is compiled at import time; kernels compile on first call (``cache=True``).
"""
from __future__ import annotations

from .domain import f32_key, f32_unkey, log_offset
from .params import FSE_PRESETS, resolve_params
from .reconstruct import fse_reconstruct

__all__ = ["FSE_PRESETS", "fse_reconstruct", "resolve_params", "log_offset", "f32_key", "f32_unkey"]
