"""Element classes of nrhdr, one module each (the only place each class is defined), on the shared
skeleton of `_base.NrElement`; shared code by concern in `_caps`, `_buffers`, `_log`, `_props`,
`_profiles`, `_live`, `_base` (`_common` re-exports what apps and tests use).

`gst_plugins.register_all()` registers them in-process; the plugin loader shims in `gst_plugins/python/`
import the same classes for gst-launch-1.0 / gst-inspect-1.0.
"""

# factory name -> (module under gst_plugins.elements, class name)
ELEMENTS = {
    "nrvalidity": ("nrvalidity", "NrValidity"),
    "nrcrosstalk": ("nrcrosstalk", "NrCrosstalk"),
    "nrreconstruct": ("nrreconstruct", "NrReconstruct"),
    "nrtonemap": ("nrtonemap", "NrTonemap"),
    "nrexrsink": ("nrexrsink", "NrExrSink"),
    "nrcamsrc": ("nrcamsrc", "NrCamSrc"),
    "nrimagesrc": ("nrimagesrc", "NrImageSrc"),
    "nrhdrenc": ("nrhdrenc", "NrHdrEnc"),
}


def element_class(factory: str):
    import importlib
    mod, cls = ELEMENTS[factory]
    return getattr(importlib.import_module(f"{__name__}.{mod}"), cls)


# GStreamer is initialised before any element module starts importing: with GST_REGISTRY_FORK=no the
# registry scan runs inside Gst.init and the plugin loader imports the element modules then; a module
# half-imported at that moment would cache the python plugin with no elements.
from . import _gst  # noqa: E402,F401
