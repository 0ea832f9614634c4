"""Lint and type checks of the package (ndtom_ti, kernels, viewer) and the format of all the
Python of the repository (package, tests, benchmarks), run with the tests.

Settings live in pyproject.toml ([tool.ruff], [tool.pyright]); the tools come with the dev extra.
"""

import importlib.util
import json
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

try:
    import tomllib
except ModuleNotFoundError:  # Python 3.10
    import tomli as tomllib

ROOT = Path(__file__).resolve().parents[1]
PACKAGE = ["ndtom_ti", "kernels", "viewer"]
# where the installed package has kernels/ and viewer/ (pyproject's package-dir)
INSTALLED = {"ndtom_ti": "ndtom_ti", "kernels": "ndtom_ti/kernels", "viewer": "ndtom_ti/viewer"}


def _tool(module: str) -> None:
    if importlib.util.find_spec(module) is None:
        pytest.skip(f"{module} is not installed (pip install -e '.[dev]')")


def _run(*args: str, cwd: Path = ROOT, timeout: float = 600) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", *args], cwd=cwd, capture_output=True, text=True, timeout=timeout, check=False
    )


def test_ruff_check() -> None:
    _tool("ruff")
    p = _run("ruff", "check", "--no-cache", *PACKAGE)
    assert p.returncode == 0, p.stdout + p.stderr


def test_ruff_format() -> None:
    _tool("ruff")
    p = _run("ruff", "format", "--check", "--no-cache", *PACKAGE, "tests", "benchmarks")
    assert p.returncode == 0, "run `ruff format FILE` on:\n" + p.stdout + p.stderr


def _installed_layout(dest: Path) -> dict:
    """Copy the package into ``dest`` as it is installed; the pyright settings for it."""
    for src, rel in INSTALLED.items():
        shutil.copytree(ROOT / src, dest / rel, ignore=shutil.ignore_patterns("__pycache__", "kernels", "viewer"))
    config = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["pyright"]

    def moved(path: str) -> str:
        top, _, rest = path.partition("/")
        return INSTALLED[top] + ("/" + rest if rest else "") if top in INSTALLED else path

    config["include"] = [moved(p) for p in config["include"]]
    config["executionEnvironments"] = [
        {**env, "root": moved(env["root"])} for env in config.get("executionEnvironments", [])
    ]
    return config


def test_pyright(tmp_path: Path) -> None:
    _tool("pyright")
    config = _installed_layout(tmp_path)
    (tmp_path / "pyrightconfig.json").write_text(json.dumps(config))
    # the first run fetches pyright's node part from npm
    p = _run("pyright", "--pythonpath", sys.executable, "--outputjson", cwd=tmp_path)
    try:
        report = json.loads(p.stdout)
    except json.JSONDecodeError:
        pytest.fail(f"pyright did not run: {p.stdout[-2000:]}{p.stderr[-2000:]}")
    back = {str(tmp_path / rel): src for src, rel in sorted(INSTALLED.items(), key=lambda kv: -len(kv[1]))}
    found = []
    for d in report["generalDiagnostics"]:
        path = d["file"]
        for where, src in back.items():
            if path.startswith(where + "/"):
                path = src + path[len(where) :]
                break
        line = d["range"]["start"]["line"] + 1
        found.append(f"{path}:{line}: {d['severity']}: {d['message']} ({d.get('rule', '')})")
    assert report["summary"]["filesAnalyzed"] > 30
    assert not [f for f in found if ": error: " in f], "\n".join(found)


def _module_imports() -> dict[str, set[str]]:
    """Each module of the package (installed names) -> the package's modules it imports,
    anywhere in its source: at the top, inside functions and for type checking alike."""
    import ast

    files = {}
    for src, rel in INSTALLED.items():
        for f in (ROOT / src).rglob("*.py"):
            parts = [rel.replace("/", "."), *f.relative_to(ROOT / src).with_suffix("").parts]
            if src == "ndtom_ti" and parts[1:2] in (["kernels"], ["viewer"]):
                continue
            files[".".join(parts[:-1] if parts[-1] == "__init__" else parts)] = f
    edges: dict[str, set[str]] = {name: set() for name in files}
    for name, f in files.items():
        package = name if f.name == "__init__.py" else name.rpartition(".")[0]
        for node in ast.walk(ast.parse(f.read_text(encoding="utf-8"))):
            if isinstance(node, ast.Import):
                targets = [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom):
                base = package
                for _ in range(node.level - 1):
                    base = base.rpartition(".")[0]
                mod = (base + "." + node.module if node.module else base) if node.level else (node.module or "")
                targets = [mod] + [f"{mod}.{a.name}" for a in node.names]
            else:
                continue
            for t in targets:
                while t and t not in files:
                    t = t.rpartition(".")[0]
                # a module's own package is imported with it anyway
                if t and t != name and not name.startswith(t + "."):
                    edges[name].add(t)
    return edges


def test_no_import_cycles() -> None:
    """No module imports, through others, a module that imports it: loading a file or a
    map climbs one way through the layers."""
    edges = _module_imports()
    assert "ndtom_ti.map" in edges and "ndtom_ti.viewer.live" in edges and "ndtom_ti.kernels.layout" in edges
    cycles, done = [], set()

    def walk(name: str, path: list[str]) -> None:
        if name in path:
            cycles.append(" -> ".join([*path[path.index(name) :], name]))
            return
        if name in done:
            return
        for t in sorted(edges[name]):
            walk(t, [*path, name])
        done.add(name)

    for name in sorted(edges):
        walk(name, [])
    assert not cycles, "import cycles:\n" + "\n".join(cycles)
