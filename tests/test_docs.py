"""The documentation's references hold: every file under docs/results/ is cited by a document,
every file a document cites exists, and nothing points outside the repository.

The documents are README.md and every markdown file under docs/. A results file is cited by
its repository path (``docs/results/x.png``) anywhere in the text, or by a relative markdown
link that resolves to it (``[x](results/x.png)`` from docs/). Plain text only: no JAX, so this
runs in well under a second.
"""

from __future__ import annotations

import re
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
RESULTS = REPO / "docs" / "results"

PENDING: set[str] = set()
"""Files docs/results.md already cites that the box-world noise-scale experiment has not yet
written. Take a path out of this set when its file is added (a test fails until then)."""

_LINK = re.compile(r"\]\(([^)\s]+)(?:\s+\"[^\"]*\")?\)")
_RESULTS_PATH = re.compile(r"docs/results/[A-Za-z0-9_.\-]+")


def documents() -> list[Path]:
    return [REPO / "README.md", *sorted((REPO / "docs").rglob("*.md"))]


def _rel(path: Path) -> str:
    return path.resolve().relative_to(REPO).as_posix()


def _links(doc: Path) -> list[tuple[str, str]]:
    """(target path, anchor) of every relative markdown link in ``doc`` (URLs and pure anchors skipped)."""
    out = []
    for target in _LINK.findall(doc.read_text(encoding="utf-8")):
        if re.match(r"^[a-z][a-z0-9+.\-]*:", target) or target.startswith("#"):
            continue
        path, _, anchor = target.partition("#")
        out.append((path, anchor))
    return out


def _slugs(doc: Path) -> set[str]:
    """GitHub-style anchors of the headings of a markdown file."""
    slugs = set()
    for line in doc.read_text(encoding="utf-8").splitlines():
        m = re.match(r"^#{1,6}\s+(.*?)\s*#*\s*$", line)
        if m:
            text = re.sub(r"[^\w\- ]", "", m.group(1).lower())
            slugs.add(text.replace(" ", "-"))
    return slugs


def cited_paths() -> dict[str, set[str]]:
    """Repository-relative path -> the documents that cite it (results paths and relative links)."""
    cited: dict[str, set[str]] = {}
    for doc in documents():
        name = _rel(doc)
        for match in _RESULTS_PATH.findall(doc.read_text(encoding="utf-8")):
            cited.setdefault(match.rstrip("."), set()).add(name)
        for path, _ in _links(doc):
            target = (doc.parent / path).resolve()
            try:
                key = target.relative_to(REPO).as_posix()
            except ValueError:
                key = "OUTSIDE:" + path
            cited.setdefault(key, set()).add(name)
    return cited


def test_the_documents_exist():
    names = {_rel(d) for d in documents()}
    assert {"README.md", "docs/design.md", "docs/results.md", "docs/tuning.md"} <= names


def test_every_results_file_is_cited():
    cited = cited_paths()
    files = sorted(_rel(p) for p in RESULTS.rglob("*") if p.is_file())
    assert files, "docs/results/ is empty"
    uncited = [f for f in files if f not in cited]
    assert not uncited, f"files under docs/results/ that no document cites (cite or delete them): {uncited}"


def test_every_cited_file_exists():
    missing = []
    for path, docs in sorted(cited_paths().items()):
        if path.startswith("OUTSIDE:"):
            continue
        if path in PENDING:
            continue
        if not (REPO / path).exists():
            missing.append(f"{path} (cited by {', '.join(sorted(docs))})")
    assert not missing, "documents cite files that do not exist:\n" + "\n".join(missing)


def test_pending_files_are_still_pending():
    """A PENDING file that now exists must leave the set, so that its existence is checked again."""
    cited = cited_paths()
    for path in sorted(PENDING):
        assert path in cited, f"{path} is in PENDING but no document cites it"
        assert not (REPO / path).exists(), f"{path} exists now: remove it from PENDING in tests/test_docs.py"


def test_no_link_leaves_the_repository():
    outside = sorted(k for k in cited_paths() if k.startswith("OUTSIDE:"))
    assert not outside, f"links that resolve outside the repository: {outside}"


def test_link_anchors_exist():
    bad = []
    for doc in documents():
        for path, anchor in _links(doc):
            target = (doc.parent / path).resolve()
            if anchor and target.suffix == ".md" and target.is_file() and anchor not in _slugs(target):
                bad.append(f"{_rel(doc)}: {path}#{anchor}")
    assert not bad, f"links to headings that do not exist: {bad}"


def _code_files():
    """The repository's code and notebooks (this file included: it spells the strings in pieces)."""
    for folder in ("jaxslam", "tests", "experiments", "benchmarks", "notebooks"):
        for path in sorted((REPO / folder).rglob("*")):
            if path.suffix in (".py", ".ipynb", ".json"):
                yield path


# Spelled in pieces, so that this file does not itself name the outside design file.
_OUTSIDE_DESIGN = "DESIGN" + ".md"


@pytest.mark.parametrize("forbidden", [_OUTSIDE_DESIGN, "../shared/" + "DESIGN", "/work/" + "shared"])
def test_nothing_points_at_the_design_notes_outside_the_repository(forbidden):
    """The design lives in docs/design.md; no document, module, test, script or notebook names a
    design file outside the repository."""
    offenders = [_rel(d) for d in [*documents(), *_code_files()] if forbidden in d.read_text(encoding="utf-8")]
    assert not offenders, f"{forbidden!r} appears in {offenders}"


def test_the_checks_can_fail(tmp_path, monkeypatch):
    """On a toy repository the checks see an uncited file, a missing file, a link outside the
    repository and a link to a heading that does not exist."""
    docs = tmp_path / "docs"
    (docs / "results").mkdir(parents=True)
    (docs / "results" / "kept.json").write_text("{}")
    (docs / "results" / "orphan.json").write_text("{}")
    (docs / "x.md").write_text("# Somewhere\n")
    (tmp_path / "README.md").write_text(
        "[a](docs/results/kept.json) docs/results/missing.png [b](../outside.md) [c](docs/x.md#nowhere)\n")
    module = sys.modules[__name__]
    monkeypatch.setattr(module, "REPO", tmp_path)
    monkeypatch.setattr(module, "RESULTS", docs / "results")
    for check in (test_every_results_file_is_cited, test_every_cited_file_exists,
                  test_no_link_leaves_the_repository, test_link_anchors_exist):
        with pytest.raises(AssertionError):
            check()
