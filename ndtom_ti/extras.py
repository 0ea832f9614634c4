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


def extra_of(module: str) -> str:
    return next(extra for extra, mods in EXTRAS.items() if module in mods)


def missing_message(module: str, purpose: str) -> str:
    """'<purpose> needs <module>, which is not installed (extra [x])'."""
    return f"{purpose} needs the optional package {module}, which is not installed (extra [{extra_of(module)}])"


def require(module: str, purpose: str) -> None:
    """Raise :class:`ExtraMissingError` (naming the extra and how to install it) when
    ``module`` is not installed."""
    if not available(module):
        raise ExtraMissingError(
            f"{missing_message(module, purpose)}; install it with: {install_hint(extra_of(module))}"
        )
