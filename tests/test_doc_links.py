"""The README's and docs' relative links resolve, and every committed benchmark result is linked from them."""

import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
DOCS = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]
RESULTS = ROOT / "benchmarks" / "results"

#: ``[text](target)`` and ``![alt](target "title")``: the target, without a title
LINK = re.compile(r"\]\(\s*<?([^)\s>]+)>?(?:\s+\"[^\"]*\")?\s*\)")


def relative_links(doc: Path) -> list[str]:
    """The relative link targets of a Markdown file (web addresses, mail and in-page anchors left out), each
    without its ``#anchor``."""
    targets = (m.group(1) for m in LINK.finditer(doc.read_text(encoding="utf-8")))
    return [t.split("#")[0] for t in targets if not re.match(r"[a-zA-Z][a-zA-Z0-9+.-]*:", t) and not t.startswith("#")]


def test_relative_links_resolve():
    dangling = [f"{doc.relative_to(ROOT)}: {t}" for doc in DOCS for t in relative_links(doc)
                if not (doc.parent / t).exists()]
    assert not dangling, "links to nothing:\n" + "\n".join(dangling)


def test_every_result_is_linked():
    """Each result (``NAME.json``, ``.md``, ``.png`` of one run) is linked, by one of its files, from the README
    or docs/: a result nobody can find is a record, which git keeps."""
    linked = {(doc.parent / t).resolve() for doc in DOCS for t in relative_links(doc)}
    runs = {p.stem for p in RESULTS.iterdir() if p.suffix in (".json", ".md", ".png")}
    assert len(runs) >= 10                                     # the benchmarks' results are there
    unlinked = sorted(r for r in runs if not any((RESULTS / f"{r}{ext}").resolve() in linked
                                                 for ext in (".json", ".md", ".png")))
    assert not unlinked, f"results linked from neither README.md nor docs/: {unlinked}"


def test_the_link_pattern_finds_links_and_images(tmp_path):
    """The check itself: links, images and titled links are found; addresses and anchors are not checked."""
    doc = tmp_path / "a.md"
    doc.write_text('[x](b.md#part) ![p](img/c.png "a title") [w](https://example.org/d.md) [s](#here) '
                   "[m](mailto:a@b.c) [e](<spaced.md>)\n")
    assert relative_links(doc) == ["b.md", "img/c.png", "spaced.md"]
