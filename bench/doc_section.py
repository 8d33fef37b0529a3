"""One marked section of a docs page, rewritten in place by the bench that measures it.

A bench (validate_learning.py, validate_afc.py) writes its figures between its own
`<!-- name:begin -->` and `<!-- name:end -->` markers; everything else on the page
stays as it is. A page without the markers gets the section appended.
"""

from __future__ import annotations

from pathlib import Path


def write_section(text: str, doc: Path, begin: str, end: str) -> None:
    old = doc.read_text() if doc.exists() else ""
    if begin in old and end in old:
        head, rest = old.split(begin, 1)
        tail = rest.split(end, 1)[1].lstrip("\n")
        new = head + text + ("\n" + tail if tail else "")
    else:
        new = old.rstrip("\n") + "\n\n" + text
    doc.write_text(new)
