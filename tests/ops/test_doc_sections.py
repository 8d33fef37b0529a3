"""bench/doc_section.py: a bench that rewrites docs/validation.md whole keeps the other benches' sections.

bench/validate.py rewrote the page from scratch and deleted every figure, so a
run of it dropped the learned-limits and AFC sections (validate_learning.py,
validate_afc.py) and their plots, which only those benches can measure again.
"""

from __future__ import annotations

import sys
from pathlib import Path

import pytest

pytestmark = pytest.mark.quick

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "bench"))

from doc_section import stale_figures, with_marked_sections, write_section  # noqa: E402

PAGE = """# Validation

old whole-page text ![old](validation/fig5.png)

<!-- learned-limits:begin -->
## Learned limits
![envelope](validation/learning-envelope.png)
<!-- learned-limits:end -->

<!-- afc:begin -->
## AFC
![steps](validation/afc-steps.png)
<!-- afc:end -->
"""


def _page(tmp_path: Path) -> tuple[Path, Path]:
    doc, figs = tmp_path / "validation.md", tmp_path / "validation"
    doc.write_text(PAGE)
    figs.mkdir()
    for name in ("fig5.png", "learning-envelope.png", "afc-steps.png", "bias.png"):
        (figs / name).write_bytes(b"png")
    return doc, figs


def test_a_whole_page_rewrite_carries_the_marked_sections_over(tmp_path):
    doc, _ = _page(tmp_path)
    new = with_marked_sections(doc, "# Validation\n\nnew whole-page text\n")
    assert "old whole-page text" not in new and "new whole-page text" in new
    assert new.index("<!-- learned-limits:begin -->") < new.index("<!-- afc:begin -->")
    assert "## Learned limits\n![envelope](validation/learning-envelope.png)\n<!-- learned-limits:end -->" in new
    assert new.rstrip().endswith("<!-- afc:end -->")
    doc.write_text(new)
    write_section("<!-- afc:begin -->\n## AFC, again\n<!-- afc:end -->\n", doc, "<!-- afc:begin -->",
                  "<!-- afc:end -->")
    again = doc.read_text()
    assert "## AFC, again" in again and "## AFC\n" not in again and "## Learned limits" in again


def test_only_the_figures_no_marked_section_shows_are_stale(tmp_path):
    doc, figs = _page(tmp_path)
    assert [p.name for p in stale_figures(doc, figs)] == ["bias.png", "fig5.png"]


def test_a_page_without_sections_is_rewritten_whole(tmp_path):
    doc = tmp_path / "validation.md"
    assert with_marked_sections(doc, "new\n") == "new\n"          # no page yet
    doc.write_text("old, no markers\n")
    assert with_marked_sections(doc, "new\n") == "new\n"
