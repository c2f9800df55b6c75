"""README.md and every page under docs/ link only to files and sections that exist, and every
file under docs/ (pages, figures, raw bench records) is linked from some page.

Links are markdown links and images (``[text](target)``, ``![alt](target)``) and HTML
``<img src="...">`` outside code; web addresses are not followed. A ``#section`` must name a
heading of the target page, as GitHub makes its anchors. The checkers are shown to fail on a
small tree with a broken link, a missing section and an unlinked file.

docs/index.md also states how many of the JSON files under docs/ carry a "provenance" key and
links every one that does not; that statement is checked against the files.
"""
from __future__ import annotations

import json
import re
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]

FENCE = re.compile(r"^```.*?^```", re.M | re.S)
CODE = re.compile(FENCE.pattern + r"|`[^`\n]*`", re.M | re.S)
LINK = re.compile(r"\]\(\s*<?([^)\s>]+)>?(?:\s+\"[^\"]*\")?\s*\)|<img\b[^>]*\bsrc=\"([^\"]+)\"")
HEADING = re.compile(r"^#{1,6}\s+(.*?)\s*#*\s*$", re.M)


def pages(root: Path) -> list[Path]:
    """README.md and every markdown page below docs/."""
    return [root / "README.md", *sorted((root / "docs").rglob("*.md"))]


def link_targets(page: Path) -> list[str]:
    """The relative link and image targets of `page`, code spans and blocks left out."""
    text = CODE.sub("", page.read_text())
    targets = [a or b for a, b in LINK.findall(text)]
    return [t for t in targets if not re.match(r"[a-zA-Z][a-zA-Z0-9+.-]*:", t)]


def anchor(heading: str) -> str:
    """GitHub's anchor of a heading: link syntax reduced to its text, lower case, punctuation
    dropped, spaces as hyphens."""
    text = re.sub(r"!?\[([^\]]*)\]\([^)]*\)", r"\1", heading).lower()
    return re.sub(r"[^\w\- ]", "", text).replace(" ", "-")


def anchors(page: Path) -> set[str]:
    """Every heading anchor of `page`, repeated headings numbered as GitHub numbers them."""
    seen: dict[str, int] = {}
    names = set()
    for heading in HEADING.findall(FENCE.sub("", page.read_text())):
        base = anchor(heading)
        count = seen.get(base, 0)
        names.add(base if count == 0 else f"{base}-{count}")
        seen[base] = count + 1
    return names


def broken_links(root: Path) -> list[str]:
    """`page: target` for every link whose file, or whose section in a markdown page, is missing."""
    broken = []
    for page in pages(root):
        for target in link_targets(page):
            path, _, section = target.partition("#")
            resolved = (page.parent / path).resolve() if path else page
            missing = not resolved.exists() or (
                section and resolved.suffix == ".md" and section not in anchors(resolved))
            if missing:
                broken.append(f"{page.relative_to(root)}: {target}")
    return broken


def unlinked_files(root: Path) -> list[str]:
    """Files under docs/ that no page (README.md or docs/**.md) links to."""
    linked = {(page.parent / t.partition("#")[0]).resolve()
              for page in pages(root) for t in link_targets(page) if t.partition("#")[0]}
    return [str(f.relative_to(root)) for f in sorted((root / "docs").rglob("*"))
            if f.is_file() and f.resolve() not in linked]


def json_without_provenance(root: Path) -> tuple[int, list[str]]:
    """The number of JSON files under docs/, and those (relative to docs/) whose top level has no
    "provenance" key."""
    files = sorted((root / "docs").rglob("*.json"))
    lacking = [str(f.relative_to(root / "docs")) for f in files if "provenance" not in json.loads(f.read_text())]
    return len(files), lacking


PROVENANCE_CLAIM = re.compile(r"Of the (\d+) JSON files under docs/, (\d+) have that key\. These (\d+) do not"
                              r"(.*?)(?:\n\n|\Z)", re.S)


def provenance_claim(index: Path) -> tuple[int, int, list[str]]:
    """What `index` says: (JSON files, files with the key, the linked files without it)."""
    match = PROVENANCE_CLAIM.search(index.read_text())
    assert match, f"{index} has no sentence 'Of the N JSON files under docs/, M have that key. These K do not ...'"
    total, having, lacking = (int(g) for g in match.groups()[:3])
    named = [a for a, _ in LINK.findall(match.group(4))]
    assert lacking == len(named), f"{index} says {lacking} files lack the key but links {len(named)}"
    return total, having, named


def test_index_states_which_json_lack_provenance():
    total, lacking = json_without_provenance(REPO)
    assert provenance_claim(REPO / "docs" / "index.md") == (total, total - len(lacking), lacking)


def test_every_link_resolves():
    assert broken_links(REPO) == []


def test_every_docs_file_is_linked():
    assert unlinked_files(REPO) == []


def test_anchor_follows_github():
    assert anchor("Figure 13: the occluded hand (`examples/fit_body_occluded_hand.py`)") == \
        "figure-13-the-occluded-hand-examplesfit_body_occluded_handpy"
    assert anchor("Measured at the end ([bench/x.json](bench/x.json))") == "measured-at-the-end-benchxjson"


def test_checkers_catch_broken_links_and_orphans(tmp_path):
    docs = tmp_path / "docs"
    (docs / "bench").mkdir(parents=True)
    (tmp_path / "README.md").write_text("[map](docs/index.md) and `[in code](docs/nowhere.md)`\n")
    (docs / "index.md").write_text("# Map\n\n## Pages\n\n[a](a.md#pages) [b](a.md#results) "
                                   "[c](bench/gone.json) [d](#pages) [e](https://example.org/x)\n"
                                   '<img src="chart.png">\n')
    (docs / "a.md").write_text("# A\n\n## Pages\n\n[back](index.md#map)\n")
    (docs / "chart.png").write_bytes(b"")
    (docs / "bench" / "orphan.json").write_text("{}")
    assert broken_links(tmp_path) == ["docs/index.md: a.md#results", "docs/index.md: bench/gone.json"]
    assert unlinked_files(tmp_path) == ["docs/bench/orphan.json"]
    (docs / "x.json").write_text('{"provenance": {}}')
    (docs / "index.md").write_text("Of the 2 JSON files under docs/, 1 have that key. These 1 do not: "
                                   "[bench/orphan.json](bench/orphan.json).\n")
    assert provenance_claim(docs / "index.md") == (2, 1, ["bench/orphan.json"])
    assert json_without_provenance(tmp_path) == (2, ["bench/orphan.json"])
