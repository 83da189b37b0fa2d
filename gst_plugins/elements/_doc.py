"""Write each element's property table (`PropertyTable.markdown`) into docs/ELEMENTS.md, in place of the
table under its `### <factory>` heading: `python -m gst_plugins.elements._doc [docs/ELEMENTS.md]`."""
from __future__ import annotations

import re
import sys
from pathlib import Path

from . import ELEMENTS, element_class

HEADER = "| Property | Type |"


def update(text: str) -> str:
    lines, out, i, current = text.split("\n"), [], 0, None
    while i < len(lines):
        line = lines[i]
        m = re.match(r"### (nr\w+)$", line)
        if m:
            current = m.group(1) if m.group(1) in ELEMENTS else None
        elif line.startswith("## "):
            current = None
        if current and line.startswith(HEADER):
            while i < len(lines) and lines[i].startswith("|"):
                i += 1
            out.append(element_class(current).PROPERTIES.markdown())
            continue
        out.append(line)
        i += 1
    return "\n".join(out)


def main(argv=None) -> int:
    args = sys.argv[1:] if argv is None else argv
    path = Path(args[0] if args else Path(__file__).resolve().parents[2] / "docs" / "ELEMENTS.md")
    path.write_text(update(path.read_text()))
    return 0


if __name__ == "__main__":
    sys.exit(main())
