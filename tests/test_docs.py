"""The docs cannot drift silently: every relative link and section anchor in README.md and docs/
resolves, and every stage of dvc.yaml is named in docs/pipeline.md."""

from __future__ import annotations

import re
from pathlib import Path

import yaml

REPO = Path(__file__).resolve().parents[1]
PAGES = sorted([REPO / "README.md", *REPO.joinpath("docs").glob("*.md")])
LINK = re.compile(r"(?<!!)\[[^\]]*\]\(([^()\s]+)\)")
FENCE = re.compile(r"^(```|~~~).*?^\1", re.M | re.S)


def slug(heading: str) -> str:
    """GitHub's anchor of a heading: lower case, punctuation dropped, spaces as hyphens."""
    text = re.sub(r"[`*_]", "", heading.strip().lower())
    return re.sub(r"[^\w\- ]", "", text).replace(" ", "-")


def anchors(page: Path) -> set[str]:
    text = FENCE.sub("", page.read_text())
    return {slug(m.group(1)) for m in re.finditer(r"^#{1,6}\s+(.+?)\s*#*$", text, re.M)}


def links(page: Path) -> list[str]:
    return LINK.findall(FENCE.sub("", page.read_text()))


def test_every_relative_link_and_anchor_in_the_docs_resolves() -> None:
    # given: README.md and every page under docs/
    broken = []
    for page in PAGES:
        # when: following each of its relative links
        for target in links(page):
            if re.match(r"^[a-z][a-z0-9+.-]*:", target):  # http:, https:, mailto: ...
                continue
            path, _, anchor = target.partition("#")
            file = (page.parent / path).resolve() if path else page
            where = f"{page.relative_to(REPO)}: ({target})"
            if not file.exists():
                broken.append(f"{where}: no {path}")
            elif anchor and file.suffix == ".md" and anchor not in anchors(file):
                broken.append(f"{where}: no section #{anchor} in {file.relative_to(REPO)}")
    # then: each names a file that exists, and a section that file has
    assert broken == []


def test_every_stage_of_dvc_yaml_is_named_in_the_pipeline_page() -> None:
    # given: the stages of dvc.yaml and docs/pipeline.md
    stages = yaml.safe_load((REPO / "dvc.yaml").read_text())["stages"]
    page = (REPO / "docs" / "pipeline.md").read_text()
    # when: looking for each stage's name there, as a word
    missing = [name for name in stages if not re.search(rf"(?<![\w-]){re.escape(name)}(?![\w-])", page)]
    # then: none is missing
    assert missing == []


def test_the_anchor_of_a_heading_is_githubs() -> None:
    # given: headings with code, punctuation and capitals; when: making their anchors
    # then: as GitHub makes them
    assert slug("A new unit read through a map: measured, not kept (issue 58)") == (
        "a-new-unit-read-through-a-map-measured-not-kept-issue-58"
    )
    assert slug("Chosen by validation (`inputs.kind: auto`, `pipeline/modelling/choice.py`)") == (
        "chosen-by-validation-inputskind-auto-pipelinemodellingchoicepy"
    )
