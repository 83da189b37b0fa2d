# GStreamer Python plugin loader shim: the class lives in gst_plugins/elements/nrhdrenc.py (defined only there).
import os
import sys

try:
    import gst_plugins  # noqa: F401
except ImportError:  # PYTHONPATH without the project root: add it (this file is <root>/gst_plugins/python/)
    sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__)))))

from gst_plugins.elements.nrhdrenc import NrHdrEnc  # noqa: E402

from gi.repository import Gst  # noqa: E402  (version already required)

__gstelementfactory__ = ("nrhdrenc", Gst.Rank.NONE, NrHdrEnc)
