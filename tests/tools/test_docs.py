"""The documentation cannot go stale in the ways a script can see (issue 58): the README stays one screen, and every
relative link in the README, docs/ and the generated reports leads to a file (and a heading) that exists."""
from __future__ import annotations

import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

from layerbvh_mitsuba.repo import ROOT

README_MAX_LINES = 200
PAGES = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md")), *sorted((ROOT / "docs").glob("*/*.md")),
         ROOT / "BENCHMARKS.md", ROOT / "PERFORMANCE.md", ROOT / "STABILITY.md"]
LINK = re.compile(r"\]\(([^)\s]+)\)")


def _slug(heading: str) -> str:
    """GitHub's anchor of a markdown heading: lower case, punctuation dropped, spaces to hyphens."""
    text = re.sub(r"[`*_]", "", heading.strip().lower())
    return re.sub(r"\s", "-", re.sub(r"[^\w\s-]", "", text))


def _anchors(page: Path) -> set[str]:
    return {_slug(line.lstrip("#")) for line in page.read_text().splitlines() if line.startswith("#")}


def broken_links(pages=PAGES, root: Path = ROOT) -> list[str]:
    """'page: target' for every relative link whose file, or whose #heading, is not there."""
    bad = []
    for page in pages:
        for target in LINK.findall(page.read_text()):
            if target.startswith(("http://", "https://", "mailto:")):
                continue
            path, _, anchor = target.partition("#")
            dest = (page.parent / path).resolve() if path else page
            if not dest.exists() or (anchor and dest.suffix == ".md" and anchor not in _anchors(dest)):
                bad.append(f"{page.relative_to(root)}: {target}")
    return bad


def test_the_readme_is_one_screen():
    n = len((ROOT / "README.md").read_text().splitlines())
    assert n <= README_MAX_LINES, f"README.md has {n} lines: move detail into docs/"


def test_every_relative_link_resolves():
    assert broken_links() == []


CODE_TREES = ("layerbvh", "plugin", "scripts", "tests", "docs", "scenes")
PATHISH = re.compile(r"`([\w./*-]+(?:/|\.(?:py|md|sh|toml|json|xml|yml)))`")


def missing_paths(page: Path, root: Path = ROOT) -> list[str]:
    """The `code` spans of a page that name a file or folder (a slash or a file suffix) that is not
    in the repository: from its top, from a code tree (`tools/x.py` is plugin/tools/x.py) or, for a
    bare file name, anywhere in one."""
    bad = []
    for name in sorted(set(PATHISH.findall(page.read_text()))):
        bases = [root, *(root / t for t in CODE_TREES)]
        if any(list(b.glob(name.rstrip("/"))) for b in bases):
            continue
        if "/" not in name and any(next((root / t).rglob(name), None) for t in CODE_TREES):
            continue
        bad.append(name)
    return bad


def test_the_repository_map_names_what_is_there(tmp_path):
    """docs/layout.md (the map of the repository) names only files and folders that exist; the
    check can fail: a folder that was renamed (tests/mitsuba/, now tests/runtime/) is named."""
    assert missing_paths(ROOT / "docs" / "layout.md") == []
    page = tmp_path / "layout.md"
    page.write_text("tests in `engine/`, `mitsuba/` and `tools/`; the table in `scripts/mutations/`\n")
    assert missing_paths(page) == ["mitsuba/"]


def test_a_broken_link_is_found(tmp_path):
    """The check can fail: a missing file and a missing heading are both named, a good one not."""
    page = (tmp_path / "page.md").resolve()
    page.write_text("# A title\n\n[gone](nowhere.md) [here](#a-title) [there](#no-such-heading)\n")
    assert broken_links([page], page.parent) == ["page.md: nowhere.md", "page.md: #no-such-heading"]


def _build_site(root: Path, out: Path) -> subprocess.CompletedProcess:
    """`mkdocs build --strict` of the site at `root` (its mkdocs.yml) into `out` (not -q: quiet, the
    warnings that strict counts are not raised)."""
    env = dict(os.environ, NO_MKDOCS_2_WARNING="1")  # (Material's notice about MkDocs 2, on every build)
    return subprocess.run([sys.executable, "-m", "mkdocs", "build", "--strict", "-f", str(root / "mkdocs.yml"),
                           "-d", str(out)], capture_output=True, text=True, env=env, timeout=300)


def test_the_site_builds_strict_with_every_page_and_the_cli(tmp_path):
    """The documentation site (mkdocs.yml) builds with no warning: every page in the nav, every
    link and #anchor found in the site's own tree; the top-level pages and the CLI reference are in it."""
    r = _build_site(ROOT, tmp_path / "site")
    assert r.returncode == 0, r.stdout + r.stderr
    site = tmp_path / "site"
    home = (site / "index.html").read_text()
    assert 'href="guide/"' in home and 'href="BENCHMARKS/"' in home  # (the README's links, moved)
    cli = (site / "cli" / "index.html").read_text()
    assert "layerbvh compare" in cli and "--grad" in cli
    assert "verdict.label" in (site / "report_json" / "index.html").read_text()
    assert "early_verdict_uncounted_pixels" in (site / "mutations" / "index.html").read_text()
    # the engine's API reference, from its docstrings (mkdocstrings; issue 58)
    api = (site / "api_reference" / "index.html").read_text()
    assert "build_instanced" in api and "Build a Layer BVH over a triangle mesh" in api and "trace_inline" in api
    prb = (site / "integrators" / "prb" / "index.html").read_text()
    assert "layerbvh_prb" in prb and "test_prb.py::test_a_textured_area_emitter" in prb


def test_a_broken_site_link_fails_the_build(tmp_path):
    """The strict build can fail: the same site with one link to a heading that is not there."""
    copy = tmp_path / "repo"
    (copy / "scripts").mkdir(parents=True)
    shutil.copy(ROOT / "mkdocs.yml", copy)
    shutil.copy(ROOT / "scripts" / "mkdocs_hooks.py", copy / "scripts")  # (the hooks and the table they read)
    shutil.copytree(ROOT / "scripts" / "mutations", copy / "scripts" / "mutations")
    for name in ("README.md", "BENCHMARKS.md", "PERFORMANCE.md", "STABILITY.md"):
        shutil.copy(ROOT / name, copy)
    shutil.copytree(ROOT / "docs", copy / "docs")
    page = copy / "docs" / "verdict.md"
    page.write_text(page.read_text() + "\nSee [the method](method.md#no-such-heading).\n")
    r = _build_site(copy, tmp_path / "site")
    assert r.returncode != 0 and "no-such-heading" in r.stdout + r.stderr, r.stdout + r.stderr
