"""The documentation is reachable: docs/index.md lists every page, the README stays short and names every file a
run writes, every extra and every command's page."""

from __future__ import annotations

import re
import tomllib

from surfelslam.io.run_folder import RUN_OUTPUT_NAMES

from helpers import REPO

#: The README is for users: beyond this it is a manual (the docs/ pages are).
README_MAX_LINES = 200


def test_the_index_lists_every_docs_page():
    linked = set(re.findall(r"\]\(([\w.-]+\.md)\)", (REPO / "docs" / "index.md").read_text()))
    pages = {p.name for p in (REPO / "docs").glob("*.md")} - {"index.md"}
    assert pages - linked == set() and linked - pages == set()


def test_the_readme_is_short_and_complete():
    text = (REPO / "README.md").read_text()
    assert len(text.splitlines()) <= README_MAX_LINES
    assert [name for name in RUN_OUTPUT_NAMES if f"`{name}`" not in text] == []
    extras = tomllib.loads((REPO / "pyproject.toml").read_text())["project"]["optional-dependencies"]
    assert [e for e in extras if e != "dev" and f"'.[{e}]'" not in text and f"`{e}` extra" not in text
            and f"the {e} extra" not in text] == []
    assert "surfelslam batch" in text and "(docs/batch.md)" in text
