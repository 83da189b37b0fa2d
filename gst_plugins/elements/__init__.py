"""Element classes of nrhdr, one module each (the only place each class is defined).

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
}


def element_class(factory: str):
    import importlib
    mod, cls = ELEMENTS[factory]
    return getattr(importlib.import_module(f"{__name__}.{mod}"), cls)
