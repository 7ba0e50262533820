"""Rewrite the import-graph block of docs/architecture.md from the source:

    python tests/update_import_graph.py
"""

import re

from import_graph import ROOT, text

path = ROOT / "docs" / "architecture.md"
doc = path.read_text()
new, count = re.subn(r"(## Import graph\n.*?```text\n).*?(\n```)", lambda m: m.group(1) + text() + m.group(2),
                     doc, flags=re.S)
assert count == 1, "docs/architecture.md has no '## Import graph' text block"
path.write_text(new)
