"""The README is the front door: its links, and the docs' links, lead to files that exist."""

import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
LINK = re.compile(r"\]\(([^)#\s]+)(?:#[^)]*)?\)")  # [text](target) and ![alt](target)


def _pages() -> list[Path]:
    return [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]


def test_relative_links_lead_to_files() -> None:
    broken = []
    for page in _pages():
        for target in LINK.findall(page.read_text()):
            if "://" not in target and not (page.parent / target).exists():
                broken.append(f"{page.relative_to(ROOT)}: {target}")
    assert not broken, broken


def test_readme_links_every_doc() -> None:
    readme = (ROOT / "README.md").read_text()
    docs = sorted(p.name for p in (ROOT / "docs").glob("*.md"))
    assert len(docs) >= 8
    assert [d for d in docs if f"(docs/{d})" not in readme] == []


def test_documented_names_are_reachable_after_import_ndtom_ti() -> None:
    """Every dotted name `ndtom_ti.x.y` the README and docs give resolves after a plain
    `import ndtom_ti` (a fresh process: nothing else imported first)."""
    import json
    import subprocess
    import sys

    names = sorted({m for page in _pages() for m in re.findall(r"ndtom_ti(?:\.[A-Za-z_]\w*)+", page.read_text())})
    assert "ndtom_ti.pipeline.map_recording" in names and "ndtom_ti.export.export_file" in names
    code = (
        "import json, sys, ndtom_ti\nbad = []\n"
        f"for name in {names!r}:\n"
        "    obj = ndtom_ti\n"
        "    try:\n"
        "        for part in name.split('.')[1:]:\n"
        "            obj = getattr(obj, part)\n"
        "    except ImportError:\n"  # an optional extra (viser) missing: not this test's concern
        "        pass\n"
        "    except AttributeError as exc:\n"
        "        bad.append(f'{name}: {exc}')\n"
        "print(json.dumps(bad))\n"
    )
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120, check=True)
    assert json.loads(r.stdout.strip().splitlines()[-1]) == []


# What a user reads and types: the options, signatures, defaults and names the docs give exist in the code
# and say what the code does. The measurement logs (performance.md, quality.md) quote benchmarks' options.
USER_PAGES = [p for p in _pages() if p.name not in ("performance.md", "quality.md")]
OPTION = re.compile(r"(?<![\w-])(--[a-z][a-z0-9-]*)")
# Options of other tools the docs name: rosbag record --split, ray start --head/--address.
FOREIGN_OPTIONS = {"--split", "--head", "--address"}


def _ndtom_options() -> tuple[set[str], dict[str, set[str]]]:
    import typer

    from ndtom_ti.cli import app

    cmd = typer.main.get_command(app)
    root = {o for p in cmd.params for o in [*p.opts, *p.secondary_opts]} | {"-h", "--help"}
    per = {
        name: root | {o for p in sub.params for o in [*p.opts, *p.secondary_opts]} for name, sub in cmd.commands.items()
    }  # type: ignore[attr-defined]
    return root, per


def test_documented_options_exist() -> None:
    """Every `--option` the docs name is an option of an `ndtom` command (or of a benchmark script
    the text runs, or of another tool it names), and `ndtom CMD ... --opt` is an option of CMD."""
    root, per = _ndtom_options()
    ndtom = set().union(root, *per.values())
    bench = {
        o
        for f in (ROOT / "benchmarks").glob("*.py")
        for o in re.findall(r"[\"'](--[a-z][a-z0-9-]*)[\"']", f.read_text())
    }
    unknown, misplaced = [], []
    for page in USER_PAGES:
        text = page.read_text()
        unknown += [f"{page.name}: {o}" for o in OPTION.findall(text) if o not in ndtom | bench | FOREIGN_OPTIONS]
        commands = re.findall(r"`(ndtom [^`]+)`", text) + re.findall(r"^(ndtom .*)$", text, re.M)
        for line in (c.split("#")[0].split() for c in commands):
            if len(line) > 1 and line[1] in per:
                misplaced += [
                    f"{page.name}: ndtom {line[1]} {o}" for o in OPTION.findall(" ".join(line)) if o not in per[line[1]]
                ]
    assert not unknown, unknown
    assert not misplaced, misplaced


def test_sensor_model_table_gives_mapconfig_defaults() -> None:
    """docs/sensor-model.md's table of MapConfig options: every field, each with its default."""
    import dataclasses
    import math

    from ndtom_ti import MapConfig

    text = (ROOT / "docs" / "sensor-model.md").read_text()
    rows = re.findall(r"^\| (`[^|]+`)[^|]*\| ([^|]+) \|", text, re.M)
    documented = {}
    for names, default in rows:
        for name, value in zip(re.findall(r"`(\w+)`", names), default.split(","), strict=False):
            documented[name] = value.strip().split(" ")[0].strip("`")
    fields = {f.name: f.default for f in dataclasses.fields(MapConfig)}
    assert set(documented) == set(fields)
    wrong = []
    for name, value in documented.items():
        want = fields[name]
        got = {"inf": math.inf, "None:": None}.get(value, value)
        if want is not None and not isinstance(want, str):
            got = float(got)  # type: ignore[arg-type]
        if got != want:
            wrong.append(f"{name}: docs {value}, MapConfig {want!r}")
    assert not wrong, wrong


def _documented_callables() -> dict:
    """The callables the docs give as `Name(...)`, by the name they are written with."""
    from ndtom_ti import NdtOmMap, init
    from ndtom_ti.cluster import TiledMap
    from ndtom_ti.pipeline import map_recording
    from ndtom_ti.snapshot import MapSnapshot

    found = {"NdtOmMap": NdtOmMap, "TiledMap": TiledMap, "init": init, "gaussians": NdtOmMap.gaussians}
    found["pipeline.map_recording"] = map_recording
    found |= {
        "save": NdtOmMap.save,
        "s.save": MapSnapshot.save,
        "MapSnapshot.save": MapSnapshot.save,
        "m.save": NdtOmMap.save,
    }
    try:
        from ndtom_ti.viewer import MapViewer
        from ndtom_ti.viewer.live import LiveMapper
    except ImportError:  # the [viewer] extra
        return found
    return found | {"MapViewer": MapViewer, "live": (MapViewer.live, LiveMapper.__init__)}


def _last_call(span: str) -> tuple[str, str]:
    """The call a code span ends with, `a.b(x).c(y=1)` -> ("c", "y=1"), and its name as written
    (`ndtom_ti.init` -> "init"; `s.save`, `m.save` kept: whose save it is)."""
    depth = 0
    for i in range(len(span) - 1, -1, -1):
        depth += {")": 1, "(": -1}.get(span[i], 0)
        if depth == 0:
            name = re.search(r"([A-Za-z_][\w.]*)$", span[:i])
            if name is None:
                return "", ""
            return name.group(1).removeprefix("ndtom_ti.").split(").")[-1].removeprefix("MapViewer(...)."), span[
                i + 1 : -1
            ]
    return "", ""


def test_documented_signatures_match_the_code() -> None:
    """`Name(kw=value, ...)` in the docs: every keyword is one the callable takes (NdtOmMap and TiledMap
    also take MapConfig's fields); a signature (a bullet that starts with the call, two or more keywords,
    all with values) gives each keyword's default (for map options left None, MapConfig's)."""
    import ast
    import dataclasses
    import inspect
    import math

    from ndtom_ti import MapConfig

    config = {f.name: f.default for f in dataclasses.fields(MapConfig)}
    callables = _documented_callables()
    bad, checked = [], 0
    for page in USER_PAGES:
        for lead, span in re.findall(r"(^- )?`([^`]*\))`", page.read_text(), re.M):
            name, args = _last_call(span)
            if name not in callables:
                continue
            funcs = callables[name] if isinstance(callables[name], tuple) else (callables[name],)
            params = {}
            for f in reversed(funcs):
                params |= {p.name: p.default for p in inspect.signature(f).parameters.values()}
            if name in ("NdtOmMap", "TiledMap"):
                params = {**config, **{k: (config[k] if v is None and k in config else v) for k, v in params.items()}}
            given = re.findall(r"(\w+)=([^,()]+(?:\([^)]*\))?)", " ".join(args.split()))
            literal = {}
            for key, value in given:
                if key not in params:
                    bad.append(f"{page.name}: {name}() takes no {key}=")
                    continue
                try:
                    literal[key] = ast.literal_eval(value.strip())
                except (ValueError, SyntaxError):
                    literal[key] = math.inf if value.strip() == "inf" else Ellipsis
            if lead and len(literal) >= 2 and Ellipsis not in literal.values():
                checked += 1
                bad += [
                    f"{page.name}: {name}({key}={value!r}), the code's default is {params[key]!r}"
                    for key, value in literal.items()
                    if params[key] != value
                ]
    assert checked >= 3  # NdtOmMap, gaussians, TiledMap in api.md
    assert not bad, bad


def test_api_md_names_exist() -> None:
    """Every `name` and `name(...)` docs/api.md gives is something of the API: an attribute of a map, a
    snapshot, a ScanReport, a TiledMap (its instance attributes too) or the package, a MapConfig option or
    a parameter of a callable it documents."""
    import dataclasses
    import inspect

    import ndtom_ti
    from ndtom_ti import MapConfig, MapSnapshot, NdtOmMap, ScanReport
    from ndtom_ti.cluster import TiledMap

    owners = [NdtOmMap, MapSnapshot, ScanReport, TiledMap, ndtom_ti, ndtom_ti.cluster]
    known = {f.name for f in dataclasses.fields(MapConfig)}
    known |= set(re.findall(r"self\.(\w+)\s*[:=]", inspect.getsource(TiledMap)))
    for f in _documented_callables().values():
        for g in f if isinstance(f, tuple) else (f,):
            known |= set(inspect.signature(g).parameters)
    known |= {"OFF", "fork"}  # an environment variable's value; the start method
    text = (ROOT / "docs" / "api.md").read_text()
    names = set(re.findall(r"`([A-Za-z_]\w*)(?:\([^`]*\))?`", text))
    missing = sorted(n for n in names if n not in known and not any(hasattr(o, n) for o in owners))
    assert not missing, missing


def test_large_maps_record_bytes() -> None:
    """docs/large-maps.md's bytes of a Gaussian record, without and with the NDT miss model's arrays."""
    from ndtom_ti.kernels.layout import NDT_RECORD_BYTES, RECORD_BYTES

    text = " ".join((ROOT / "docs" / "large-maps.md").read_text().split())
    plain = {int(b) for b in re.findall(r"(\d+) B (?:each|record)\b", text)}
    ndt = {int(b) for b in re.findall(r"(\d+) B with the NDT miss model", text)}
    assert plain == {RECORD_BYTES}, plain
    assert ndt == {RECORD_BYTES + NDT_RECORD_BYTES}, ndt


def test_public_docstrings_cite_docs_that_exist() -> None:
    """The docstrings of `ndtom_ti.__all__` (and of their methods and functions) cite only pages a user
    has: docs/NAME.md or README.md, not the maintainers' notes outside the repository."""
    import inspect

    import ndtom_ti

    cited = set()
    for name in ndtom_ti.__all__:
        obj = getattr(ndtom_ti, name)
        parts = [obj]
        if inspect.isclass(obj) or inspect.ismodule(obj):
            parts += [v for k, v in vars(obj).items() if callable(v) or isinstance(v, property)]
        for part in parts:
            doc = inspect.getdoc(part) or ""
            cited |= {(name, page) for page in re.findall(r"[\w./-]*\.md\b", doc)}
    missing = [f"{name}: {page}" for name, page in sorted(cited) if not (ROOT / "docs" / Path(page).name).exists()]
    missing = [m for m in missing if not m.endswith("README.md")]
    assert not missing, missing


def _anchors(page: Path) -> set[str]:
    """GitHub's anchors of a page's headings (fenced code left out): lower case, punctuation but - and _
    dropped, spaces as -."""
    text = re.sub(r"^```.*?^```", "", page.read_text(), flags=re.M | re.S)
    return {re.sub(r"[^\w\- ]", "", h.strip().lower()).replace(" ", "-") for h in re.findall(r"^#+ (.+)$", text, re.M)}


def test_link_anchors_lead_to_headings() -> None:
    broken = []
    for page in _pages():
        for target, anchor in re.findall(r"\]\(([^)#\s]*)#([^)\s]+)\)", page.read_text()):
            dest = page.parent / target if target else page
            if "://" not in target and anchor not in _anchors(dest):
                broken.append(f"{page.relative_to(ROOT)}: {target}#{anchor}")
    assert not broken, broken


def test_named_files_and_tests_exist() -> None:
    """The repository's files the docs name (`benchmarks/x.py`, `tests/x.py::test_y`, `ndtom_ti/x.py`, ...)
    are there, and a named test is defined in its file."""
    missing = []
    for page in _pages():
        text = page.read_text()
        for path, test in set(
            re.findall(r"(?<![\w/.])((?:tests|benchmarks|ndtom_ti|kernels|viewer)/[\w/]+\.py)(?:::(\w+))?", text)
        ):
            if not (ROOT / path).exists():
                missing.append(f"{page.name}: {path}")
            elif test and not re.search(rf"def {test}\b", (ROOT / path).read_text()):
                missing.append(f"{page.name}: {path}::{test}")
    assert not missing, missing


def test_sensor_model_limits_are_the_codes() -> None:
    """The bounds docs/sensor-model.md gives for MapConfig's options are config.py's."""
    from ndtom_ti import config

    text = " ".join((ROOT / "docs" / "sensor-model.md").read_text().split())
    stated = {
        "N_LIMIT": r"at most 2\^(\d+) \(`N_LIMIT`",
        "RANGE_LIMIT": r"`max_range` at most (\S+) m",
        "SIGMA_S_LOW": r"`sigma_s` from (\S+) to",
        "SIGMA_S_HIGH": r"`sigma_s` from \S+ to (\S+) m",
        "RESOLUTION_MAX": r"a resolution is at most (\S+) m",
        "SIGMA_S_CELLS": r"None: (\d+) cells",
        "SIGMA_S_MIN": r"cells, at least ([\d.]+) m",
    }
    found = {name: re.search(pattern, text) for name, pattern in stated.items()}
    assert all(found.values()), [name for name, m in found.items() if m is None]
    got = {name: float(m.group(1)) for name, m in found.items() if m is not None}
    got["N_LIMIT"] = 2 ** got["N_LIMIT"]
    want = {
        "N_LIMIT": config.N_LIMIT,
        "RANGE_LIMIT": config.RANGE_LIMIT,
        "SIGMA_S_LOW": config.SIGMA_S_LIMITS[0],
        "SIGMA_S_HIGH": config.SIGMA_S_LIMITS[1],
        "RESOLUTION_MAX": config.RESOLUTION_MAX,
        "SIGMA_S_CELLS": config.SIGMA_S_CELLS,
        "SIGMA_S_MIN": config.SIGMA_S_MIN,
    }
    assert got == want
