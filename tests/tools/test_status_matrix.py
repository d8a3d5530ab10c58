"""The README's status matrix (tools/status_matrix.py): every test it names exists, and the README holds what the
script writes."""
from __future__ import annotations

from layerbvh_mitsuba import atomic
from layerbvh_mitsuba.repo import ROOT
from layerbvh_mitsuba.tools import status_matrix as sm


def test_every_named_test_is_collected():
    """A claim whose test was renamed or deleted must not stay on the README (pytest --collect-only)."""
    assert sm.nodes()
    gone = sm.missing_nodes()
    assert gone == [], f"the README's status matrix names tests that do not exist: {gone}"


def test_a_missing_test_is_named():
    """The check can fail: a node id that no test has is reported."""
    row = sm.Row("path", sm.Cell("same seed", ("tests/runtime/test_mitsuba_backend.py::test_no_such_test",)))
    assert sm.missing_nodes((row,)) == ["tests/runtime/test_mitsuba_backend.py::test_no_such_test"]


def test_the_readme_holds_the_generated_matrix():
    text = (ROOT / "README.md").read_text()
    start, end = atomic.section_markers(sm.SECTION)
    assert text[text.index(start) + len(start):text.index(end)].strip() == sm.markdown().strip(), \
        "README's status matrix is stale: run .venv/bin/python scripts/status_matrix.py --readme"
    for row in sm.ROWS:  # one row per mirrored integrator
        assert f"| `{row.integrator}` |" in text


def test_every_mirrored_integrator_has_its_page():
    """The site's Integrators section: a page per integrator we stand in for, holding its
    estimator's docstring (the algorithm and draw order) and the tests behind each claim."""
    from layerbvh_mitsuba.runtime.registry import PLUGINS, STANDS_IN_FOR
    pages = sm.integrator_pages()
    for stock, ours in STANDS_IN_FOR.items():
        page = next((text for text in pages.values() if f"standing in for stock `{stock}`" in text), None)
        assert page is not None, stock
        first_line = PLUGINS[ours][1].__doc__.strip().splitlines()[0].replace("``", "`")
        assert first_line in page and "## What the suite compares with stock" in page, stock
