"""`python -m gst_plugins.cli ...` = `nrhdr ...`."""
import sys

from . import main

sys.exit(main())
