"""Optional parts of ndtom_ti (pyproject's extras) and how to install them.

The package is installed from its repository, not from PyPI, so the hint names the
repository folder when this copy runs from one (an editable install), and otherwise says
to run pip in the repository folder.
"""

from __future__ import annotations

import importlib.util
from pathlib import Path

# extra -> the modules it brings
EXTRAS = {"viewer": ("viser",), "bench": ("pyoctomap", "matplotlib"), "cluster": ("ray",)}


class ExtraMissingError(ImportError):
    """A part of ndtom_ti needs an optional package that is not installed."""


def repo_root() -> Path | None:
    """The repository folder of this copy of ndtom_ti (an editable install), else None."""
    root = Path(__file__).resolve().parents[1]
    try:
        text = (root / "pyproject.toml").read_text(encoding="utf-8")
    except OSError:
        return None
    return root if 'name = "ndtom_ti"' in text else None


def install_hint(extra: str) -> str:
    """How to install the optional packages of ``extra`` from the repository."""
    modules = " ".join(EXTRAS.get(extra, ()))
    root = repo_root()
    if root is not None:
        return f'pip install -e "{root}[{extra}]"  (or: pip install {modules})'
    return f'in the ndtom_ti repository folder: pip install ".[{extra}]"  (or: pip install {modules})'


def available(module: str) -> bool:
    """Whether ``module`` can be imported (without importing it)."""
    try:
        return importlib.util.find_spec(module) is not None
    except (ImportError, ValueError):  # a parent package missing, or a module without a spec
        return False


def import_error(module: str) -> str | None:
    """Why ``module`` cannot be imported (it is imported now), or None when it can: an
    installed package whose own libraries are missing or broken fails here, where
    :func:`available` only finds it."""
    try:
        importlib.import_module(module)
    except Exception as exc:  # noqa: BLE001 - a broken package raises anything (ImportError, OSError, ...)
        lines = [line.strip() for line in str(exc).splitlines() if line.strip()]
        return f"{type(exc).__name__}: {lines[0] if lines else ''}".rstrip(": ")
    return None


def broken_message(module: str, purpose: str, error: str) -> str:
    """'<module> is installed but cannot be imported: <error>; <purpose> needs it'."""
    return f"{module} is installed but cannot be imported ({error}); {purpose} needs it"


def reinstall_hint(module: str) -> str:
    return f"reinstall it: pip install --force-reinstall {module} (part of the [{extra_of(module)}] extra)"


def extra_of(module: str) -> str:
    return next(extra for extra, mods in EXTRAS.items() if module in mods)


def missing_message(module: str, purpose: str) -> str:
    """'<purpose> needs <module>, which is not installed (extra [x])'."""
    return f"{purpose} needs the optional package {module}, which is not installed (extra [{extra_of(module)}])"


def require(module: str, purpose: str) -> None:
    """Raise :class:`ExtraMissingError` (naming the extra and how to install it) when
    ``module`` is not installed, or installed but cannot be imported."""
    if not available(module):
        raise ExtraMissingError(
            f"{missing_message(module, purpose)}; install it with: {install_hint(extra_of(module))}"
        )
    error = import_error(module)
    if error is not None:
        raise ExtraMissingError(f"{broken_message(module, purpose, error)}; {reinstall_hint(module)}")
