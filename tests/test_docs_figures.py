"""Every figure the README and the docs quote comes from a results file that names the versions
it ran with (issue 28): each reference to ``benchmarks/results/...`` resolves, and the raw
record behind it carries ``versions``; no page quotes a figure as an unrecorded design note."""

from __future__ import annotations

import json
import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
RESULTS = ROOT / "benchmarks" / "results"
PAGES = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]
REFERENCE = re.compile(r"benchmarks/results/([A-Za-z0-9_./*-]+)")
ARCHIVES = {
    # linked as what was measured before the versions record, with no figure quoted
    "ray-h100-k1.md", "ray-h100-k4.md", "ray-h100-k8.md", "seek_dagger/search",
    "FILE",  # BENCHMARKS.md's placeholder in "git log -p -- benchmarks/results/FILE"
}
UNRECORDED = ("design note", "no versions recorded", "no results file")


def references() -> list[tuple[str, str]]:
    found = set()
    for page in PAGES:
        for match in REFERENCE.finditer(page.read_text()):
            found.add((page.name, match.group(1).rstrip(".").rstrip("/")))
    return sorted(found)


def records(reference: str) -> list[Path]:
    """The JSON files that back ``reference``: itself, an .md's or a picture's JSON of the
    same name (else, for a run's other files, its directory's), or every JSON under a
    directory (a README.md: its directory)."""
    paths = sorted(RESULTS.glob(reference)) if "*" in reference else [RESULTS / reference]
    backing: list[Path] = []
    for path in paths:
        if path.name == "README.md":
            path = path.parent
        if path.is_dir():
            backing += sorted(path.rglob("*.json"))
        elif path.suffix == ".json":
            backing.append(path)
        elif path.with_suffix(".json").exists():
            backing.append(path.with_suffix(".json"))
        elif path.exists():  # a run's metrics.csv or curve: its directory's evaluations
            backing += sorted(path.parent.glob("*.json"))
    return backing


def versioned(record: Path) -> bool:
    """Whether the JSON ``record`` names the versions it ran with: a ``versions`` table at its
    top with torch's, pybullet's and onnxruntime's versions in it (and the git commit's key:
    a copy without its .git records None)."""
    try:
        data = json.loads(record.read_text())
    except ValueError:
        return False
    versions = data.get("versions") if isinstance(data, dict) else None
    return isinstance(versions, dict) and "git" in versions and \
        all(versions.get(key) for key in ("torch", "pybullet", "onnxruntime"))


def test_the_pages_reference_results():
    assert len(references()) > 50  # the pattern still finds the pages' references


@pytest.mark.parametrize(("page", "reference"), references())
def test_every_referenced_result_exists_and_names_its_versions(page, reference):
    if reference in ARCHIVES:
        return
    backing = records(reference)
    assert backing, f"{page}: benchmarks/results/{reference} has no JSON record beside it"
    unversioned = [str(p.relative_to(RESULTS)) for p in backing if not versioned(p)]
    assert not unversioned, f"{page}: benchmarks/results/{reference}: no versions in {unversioned}"


@pytest.mark.parametrize("page", PAGES, ids=lambda p: p.name)
def test_no_page_quotes_an_unrecorded_figure(page):
    text = page.read_text().lower()
    assert not [phrase for phrase in UNRECORDED if phrase in text]
