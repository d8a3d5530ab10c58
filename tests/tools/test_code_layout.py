"""The house rules of the code, read from its source: arrows run one way (engine <- runtime <- A/B <- tools), no
import cycles, no engine internals on the Mitsuba side, local imports only with a reason, a small top of plugin/, no
module over 500 lines, estimators apart from the render driver, no `__init__` called by name."""
from __future__ import annotations

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
PACKAGES = {"layerbvh": ROOT / "layerbvh", "layerbvh_mitsuba": ROOT / "plugin"}
# The engine's public surface: its package and the numpy-only test and benchmark inputs.
ENGINE_PUBLIC = {"layerbvh", "layerbvh.meshes"}
# Layers of the Mitsuba side, lowest first: a module may import its own layer and those below.
LAYERS = ("runtime", "ab", "tools")
MAX_TOP_MODULES = 10


def _modules() -> dict[str, Path]:
    out = {}
    for pkg, base in PACKAGES.items():
        for path in base.rglob("*.py"):
            parts = path.relative_to(base).with_suffix("").parts
            name = ".".join((pkg,) + parts[:-1] if parts[-1] == "__init__" else (pkg,) + parts)
            out[name] = path
    return out


MODULES = _modules()


def _imports(name: str, path: Path):
    """(imported module, line, at module level) of every import in the file, relative ones resolved."""
    tree = ast.parse(path.read_text())
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    top = {id(n) for n in tree.body}
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            targets = [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                anchor = package.split(".")[: len(package.split(".")) - node.level + 1]
                base = ".".join(anchor + ([node.module] if node.module else []))
            # `from pkg import mod` imports the module pkg.mod where there is one
            targets = [f"{base}.{a.name}" if f"{base}.{a.name}" in MODULES else base for a in node.names]
        else:
            continue
        for t in targets:
            yield t, node.lineno, id(node) in top


def _graph(top_level_only: bool) -> dict[str, set[str]]:
    g = {}
    for name, path in MODULES.items():
        g[name] = {t for t, _, at_top in _imports(name, path) if t in MODULES and t != name
                   and (at_top or not top_level_only)}
    return g


def _cycle(g: dict[str, set[str]]) -> list[str] | None:
    state, stack = {}, []

    def visit(n):
        state[n] = 1
        stack.append(n)
        for m in sorted(g[n]):
            if state.get(m) == 1:
                return stack[stack.index(m):] + [m]
            if m not in state and (c := visit(m)):
                return c
        stack.pop()
        state[n] = 2
        return None
    for n in sorted(g):
        if n not in state and (c := visit(n)):
            return c
    return None


def test_no_import_cycles():
    """Counting imports inside functions too: a cycle hidden in a function is still a cycle."""
    assert _cycle(_graph(top_level_only=False)) is None, " -> ".join(_cycle(_graph(False)))


def test_the_engine_knows_nothing_of_mitsuba():
    bad = [f"{MODULES[n].relative_to(ROOT)}:{line}: {t}" for n in MODULES if n.startswith("layerbvh.")
           or n == "layerbvh" for t, line, _ in _imports(n, MODULES[n])
           if t.split(".")[0] in ("mitsuba", "layerbvh_mitsuba")]
    assert not bad, bad


def test_the_mitsuba_side_uses_the_engines_public_api_only():
    bad = [f"{MODULES[n].relative_to(ROOT)}:{line}: {t}" for n in MODULES if n.startswith("layerbvh_mitsuba")
           for t, line, _ in _imports(n, MODULES[n]) if t.split(".")[0] == "layerbvh" and t not in ENGINE_PUBLIC]
    assert not bad, f"engine internals imported (expose them in layerbvh/__init__.py): {bad}"


def _layer(name: str) -> int | None:
    parts = name.split(".")
    return LAYERS.index(parts[1]) if len(parts) > 1 and parts[1] in LAYERS else None


def test_arrows_run_from_the_tools_down_to_the_runtime():
    """runtime (what a scene needs) imports neither the A/B comparison nor the tools; the A/B
    comparison does not import the tools."""
    bad = []
    for n in MODULES:
        here = _layer(n)
        if here is None:
            continue
        for t, line, _ in _imports(n, MODULES[n]):
            there = _layer(t) if t in MODULES else None
            if there is not None and there > here:
                bad.append(f"{MODULES[n].relative_to(ROOT)}:{line}: {LAYERS[here]} imports {t}")
    assert not bad, bad


def test_local_imports_say_why():
    """An import inside a function hides a dependency from the top of the file: it stays only
    with a comment saying what it buys (`# local: ...` or a noqa with its reason)."""
    bad = []
    for n, path in MODULES.items():
        lines = path.read_text().splitlines()
        for t, line, at_top in _imports(n, path):
            if not at_top and "#" not in lines[line - 1]:
                bad.append(f"{path.relative_to(ROOT)}:{line}: {lines[line - 1].strip()}")
    assert not bad, bad


def test_plugin_top_holds_few_modules_and_the_three_layers():
    top = sorted(p.name for p in PACKAGES["layerbvh_mitsuba"].glob("*.py"))
    assert len(top) <= MAX_TOP_MODULES, top
    for layer in LAYERS:
        assert (PACKAGES["layerbvh_mitsuba"] / layer / "__init__.py").is_file(), layer


@pytest.mark.parametrize("name", ["cli", "testing", "tools.sweep.point", "tools.third_party",
                                  "tools.stability.image_cases"])
def test_every_ab_user_runs_the_one_comparison(name):
    """The CLI, the pytest helpers, the sweep's points, the third-party table and the stability
    suite import ab.compare.compare; none renders a stock/ours pair of its own (`"type": "path"`
    next to `"type": "layerbvh"`), and no sweep point goes through the command line."""
    path = MODULES[f"layerbvh_mitsuba.{name}"]
    src = path.read_text()
    assert any(t == "layerbvh_mitsuba.ab.compare" for t, _, _ in _imports(f"layerbvh_mitsuba.{name}", path))
    assert "compare(" in src
    assert not ('"type": "layerbvh"' in src and '"type": "path"' in src and name != "tools.stability.image_cases"), \
        f"{path.name} builds both sides itself"
    assert "cli import main" not in src and "cli.main(" not in src


MAX_MODULE_LINES = 500


def test_no_module_over_500_lines():
    """A module that outgrows 500 lines does more than one job: split it by job. No exemption
    (issue 58): the locality replay, once exempt because numba's on-disk cache checks only the
    file a function is in, follows the modules it compiles in (layerbvh/numba_cache.py). The
    scripts and tests count too: the mutation table left scripts/mutation_check.py for scripts/mutations/."""
    files = [*MODULES.values(), *(ROOT / "scripts").rglob("*.py"), *(ROOT / "tests").rglob("*.py")]
    long = {rel: n for p in files if (n := len(p.read_text().splitlines())) > MAX_MODULE_LINES
            and (rel := str(p.relative_to(ROOT)))}
    assert not long, long


def test_estimators_import_nothing_of_the_driver():
    """runtime/estimators/ sample given their queries (estimators.common.Tracing): none imports
    the render driver or the registry that pairs them, so each reads alone against its stock file."""
    driver = {"layerbvh_mitsuba.runtime.driver", "layerbvh_mitsuba.runtime.registry"}
    bad = [(n, t) for n, p in MODULES.items() if n.startswith("layerbvh_mitsuba.runtime.estimators")
           for t, _, _ in _imports(n, p) if t in driver]
    assert not bad, bad


def test_no_init_called_by_name_across_classes():
    """`Base.__init__(self, ...)` ties a class to another by name (and once hid which class an
    integrator was): call super().__init__, or compose (the render driver calls super().__init__:
    runtime/driver.py's class statement over each variant's base)."""
    bad = []
    for n, path in MODULES.items():
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute) and node.func.attr == "__init__" \
                    and isinstance(node.func.value, ast.Name):
                bad.append(f"{path.relative_to(ROOT)}:{node.lineno}: {node.func.value.id}.__init__")
    assert not bad, bad


def test_the_package_docstrings_name_every_integrator():
    """The package's and the estimators' docstrings list every integrator we register (issue 58:
    they listed 6 of 9)."""
    import layerbvh_mitsuba
    from layerbvh_mitsuba.runtime import estimators, registry
    for plugin, (_, estimator) in registry.PLUGINS.items():
        assert f"`{plugin}`" in layerbvh_mitsuba.__doc__, plugin
        assert estimator.__module__.rsplit(".", 1)[-1] in estimators.__doc__, plugin


def test_lines_are_at_most_120_columns():
    """ruff (pyproject.toml's [tool.ruff]: 120 columns) passes on the whole tree, with no file
    exempted: no per-file ignores, no ignore list (issue 58 wrapped the last of its backlog)."""
    import subprocess
    import sys
    import tomllib

    ruff = Path(sys.executable).with_name("ruff")
    run = subprocess.run([str(ruff), "check", "--no-cache", "--output-format", "concise", str(ROOT)], cwd=ROOT,
                         capture_output=True, text=True, timeout=120)
    assert run.returncode == 0, run.stdout[-3000:] + run.stderr[-1000:]
    ruff_cfg = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["ruff"]
    lint = ruff_cfg.get("lint", {})
    assert ruff_cfg["line-length"] == 120 and "E501" in lint.get("select", ())
    exempt = {k: v for k, v in {**ruff_cfg, **lint}.items()
              if k in ("per-file-ignores", "ignore", "extend-ignore", "extend-per-file-ignores", "exclude")}
    assert not exempt, f"the 120-column rule has exemptions: {exempt}"
