"""MkDocs hooks (mkdocs.yml): the site is docs/ plus the top-level pages (README as its home,
BENCHMARKS, PERFORMANCE, STABILITY), a CLI reference generated from the argparse parser and the
report.json reference from its schema (plugin/ab/report_schema.py), with
the links that work on GitHub rewritten to where the pages lie in the site.

On GitHub, README.md links `docs/guide.md` and docs/guide.md links `../README.md`; in the site
every page lies in one tree with the README at `index.md`, so the hooks move those links there.
Nothing is written into the working tree: the top-level pages and the CLI page are generated files.
"""
from __future__ import annotations

import functools
import re
import sys
from pathlib import Path

from mkdocs.structure.files import File

ROOT = Path(__file__).resolve().parents[1]
# Top-level page -> its place in the site.
TOP = {"README.md": "index.md", "BENCHMARKS.md": "BENCHMARKS.md", "PERFORMANCE.md": "PERFORMANCE.md",
       "STABILITY.md": "STABILITY.md"}
CLI_PAGE = "cli.md"
REPORT_PAGE = "report_json.md"
_LINK = re.compile(r"\]\(([^)\s#]*)(#[^)\s]*)?\)")


def cli_reference() -> str:
    """Every command's --help, from the parser `layerbvh` runs (plugin/cli.py)."""
    from layerbvh_mitsuba import cli
    parser = cli._parser()
    out = ["# Command-line reference", "",
           "Generated from `layerbvh`'s argparse parser when the site is built (scripts/mkdocs_hooks.py).", "",
           "```text", parser.format_help().rstrip(), "```", ""]
    for action in parser._subparsers._group_actions:
        for name, sub in action.choices.items():
            out += [f"## layerbvh {name}", "", "```text", sub.format_help().rstrip(), "```", ""]
    return "\n".join(out)


MUTATIONS_PAGE = "mutations.md"
API_PAGE = "api_reference.md"
# The engine's public API, documented from its docstrings by mkdocstrings (issue 58): what a user
# of `import layerbvh` calls, and the types it returns.
API_OBJECTS = {"Building": ("build", "build_instanced", "Group", "Instance", "check_mesh", "check_param"),
               "Tracing": ("LayerBVH", "Hits", "Occlusion", "BVHStats", "TraceStats", "AutoPolicy"),
               "The locality model": ("measure", "replay", "LocalitySettings", "RaySet", "LocalityRow",
                                      "preset_verdict", "Preset", "CacheLevel", "preset"),
               "The machine": ("cpu_model", "llvm_vector_width", "set_llvm_vector_width", "llvm_isa", "set_llvm_isa",
                               "from_numpy", "collector_held")}


def api_reference() -> str:
    """The engine's API reference page: mkdocstrings renders each object's docstring and signature
    (an object not exported by `layerbvh` fails the strict build)."""
    out = ["# Python API reference", "",
           "Generated from the engine's docstrings by mkdocstrings when the site is built "
           "(scripts/mkdocs_hooks.py); the [Python API](api.md) page shows them in use.", ""]
    for section, names in API_OBJECTS.items():
        out += [f"## {section}", ""]
        for name in names:
            out += [f"::: layerbvh.{name}", "    options:", "      heading_level: 3", ""]
    return "\n".join(out)


def mutation_table() -> str:
    """The mutation check's table (scripts/mutations/, which scripts/mutation_check.py runs): each
    realistic bug, where it is made and the tests that must catch it."""
    sys.path.insert(0, str(ROOT / "scripts"))  # (the table is a folder of scripts/, not an installed package)
    from mutations import MUTATIONS  # local: only the site's mutation page reads it
    out = ["# The mutation check", "", f"{len(MUTATIONS)} realistic bugs, each made in a copy of the repository "
           "by `bash scripts/mutation_check.sh` (one at a time; `--only NAME`), and the tests that must catch it. "
           "Generated from `scripts/mutations/` when the site is built; see [testing](testing.md) for runs.",
           "", "| mutation | the bug | file | caught by |", "|---|---|---|---|"]
    for m in MUTATIONS:
        tests = "<br>".join(f"`{t.removeprefix('tests/')}`" for t in m.tests)
        out.append(f"| `{m.name}` | {m.what.replace('|', chr(92) + '|')} | `{m.path}` | {tests} |")
    return "\n".join(out) + "\n"


@functools.cache  # (the nav and the files both need them: made once per build)
def _integrator_pages() -> dict:
    from layerbvh_mitsuba.tools import status_matrix
    return status_matrix.integrator_pages()


def on_config(config):
    """The Integrators section of the nav: one generated page per status-matrix row."""
    pages = [{uri.split("/")[-1][:-3]: uri} for uri in _integrator_pages()]
    nav = config["nav"]
    at = next((i for i, item in enumerate(nav) if "Verification" in item), len(nav))
    nav.insert(at, {"Integrators": pages})
    return config


def on_files(files, config):
    for src, dest in TOP.items():
        files.append(File.generated(config, dest, content=(ROOT / src).read_text()))
    files.append(File.generated(config, CLI_PAGE, content=cli_reference()))
    from layerbvh_mitsuba.ab import report_schema
    files.append(File.generated(config, REPORT_PAGE, content=report_schema.markdown()))
    files.append(File.generated(config, MUTATIONS_PAGE, content=mutation_table()))
    files.append(File.generated(config, API_PAGE, content=api_reference()))
    for uri, text in _integrator_pages().items():
        files.append(File.generated(config, uri, content=text))
    return files


def on_page_markdown(markdown, page, config, files):
    uri = page.file.src_uri
    top_level = page.file.generated_by is not None and uri in TOP.values()
    depth = uri.count("/")

    def move(m):
        target, anchor = m.group(1), m.group(2) or ""
        if not target or target.startswith(("http://", "https://", "mailto:")):
            return m.group(0)
        if top_level:
            new = target[len("docs/"):] if target.startswith("docs/") else TOP.get(target, target)
        else:
            new = target
            up = "../" * (depth + 1)
            if target.startswith(up) and target[len(up):] in TOP:
                new = "../" * depth + TOP[target[len(up):]]
        return f"]({new}{anchor})"
    return _LINK.sub(move, markdown)
