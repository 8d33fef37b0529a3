"""One marked section of a docs page, rewritten in place by the bench that measures it.

A bench (validate_learning.py, validate_afc.py) writes its figures between its own
`<!-- name:begin -->` and `<!-- name:end -->` markers; everything else on the page
stays as it is. A page without the markers gets the section appended. A bench
that writes the whole page (validate.py) carries the marked sections over
(`with_marked_sections`), and keeps the figures they show (`stale_figures`).
"""

from __future__ import annotations

import re
from pathlib import Path

_MARKED = re.compile(r"<!-- ([\w-]+):begin -->.*?<!-- \1:end -->", re.S)
_FIGURE = re.compile(r"\]\(([^)\s]+\.png)\)")


def _marked(doc: Path) -> list[str]:
    old = doc.read_text() if doc.exists() else ""
    return [m.group(0) for m in _MARKED.finditer(old)]


def stale_figures(doc: Path, fig_dir: Path) -> list[Path]:
    """The figures in `fig_dir` that no marked section of `doc` links: a whole-page rewrite may delete them."""
    kept = {Path(f).name for s in _marked(doc) for f in _FIGURE.findall(s) if Path(f).parent.name == fig_dir.name}
    return [p for p in sorted(fig_dir.glob("*.png")) if p.name not in kept]


def with_marked_sections(doc: Path, text: str) -> str:
    """`text`, the new whole page, with the marked sections of the page it replaces appended."""
    kept = _marked(doc)
    return text if not kept else text.rstrip("\n") + "\n\n" + "\n\n".join(kept) + "\n"


def write_section(text: str, doc: Path, begin: str, end: str) -> None:
    old = doc.read_text() if doc.exists() else ""
    if begin in old and end in old:
        head, rest = old.split(begin, 1)
        tail = rest.split(end, 1)[1].lstrip("\n")
        new = head + text + ("\n" + tail if tail else "")
    else:
        new = old.rstrip("\n") + "\n\n" + text
    doc.write_text(new)
