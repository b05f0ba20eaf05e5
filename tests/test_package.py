"""The package: one import name, ``vislam``, whose imports point one way.

Every module is read as text (``ast``), so a bare ``import backend`` anywhere (which would load a
second copy of a module under another name) or an import against the layering fails here even
when the code that holds it is never run by another test.
"""

from __future__ import annotations

import ast
import importlib.metadata
import re
import subprocess
import sys
from pathlib import Path

import pytest

import vislam

ROOT = Path(__file__).resolve().parents[1]
TOP = ("backend", "frontend", "synth", "tools")
# backend's floors, bottom first: a module may import from its own floor or below
BACKEND_FLOORS = [("errors", "signals", "compiled", "reading", "chi2"), ("options",), ("config", "geometry"), ("data",), ("estimator",), ("run",),
                  ("evaluation",)]
FLOOR = {name: i for i, names in enumerate(BACKEND_FLOORS) for name in names}


def _python_files(*folders: str) -> list[Path]:
    files = [ROOT / "__init__.py"]
    for folder in folders:
        files += sorted((ROOT / folder).rglob("*.py"))
    return files


def _module_name(path: Path) -> list[str]:
    """Dotted name inside vislam, as parts (``[]`` for the package itself)."""
    parts = list(path.relative_to(ROOT).with_suffix("").parts)
    return parts[:-1] if parts[-1] == "__init__" else parts


def _imports(path: Path) -> list[tuple[int, list[str] | None, str]]:
    """(line, imported vislam module as parts (None: not vislam), text) of every import of ``path``."""
    tree = ast.parse(path.read_text(encoding="utf-8"))
    here = _module_name(path)
    package = here if path.name == "__init__.py" else here[:-1]
    out = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            for alias in node.names:
                parts = alias.name.split(".")
                out.append((node.lineno, parts[1:] if parts[0] == "vislam" else None, f"import {alias.name}"))
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package[: len(package) - (node.level - 1)] + (node.module.split(".") if node.module else [])
                targets = [base + [a.name] for a in node.names] if not node.module else [base]
                for target in targets:
                    out.append((node.lineno, target, f"from {'.' * node.level}{node.module or ''} import ..."))
            else:
                parts = (node.module or "").split(".")
                out.append((node.lineno, parts[1:] if parts[0] == "vislam" else None, f"from {node.module} import ..."))
    return out


_BARE_IN_TEXT = re.compile(r"^\s*(?:from|import)\s+(?:backend|frontend|synth|tools)\b", re.MULTILINE)


def test_no_module_imports_a_bare_top_level_folder():
    """``backend``, ``frontend``, ``synth``, ``tools`` exist only as ``vislam.*``: importing one bare
    would load a second copy of its classes. Code in strings (run in a subprocess) counts too."""
    bare = []
    for path in _python_files(*TOP, "tests", "benchmarks"):
        for line, _, text in _imports(path):
            first = text.split()[1].split(".")[0]
            if first in TOP:
                bare.append(f"{path.relative_to(ROOT)}:{line}: {text}")
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
            if isinstance(node, ast.Constant) and isinstance(node.value, str) and _BARE_IN_TEXT.search(node.value):
                bare.append(f"{path.relative_to(ROOT)}:{node.lineno}: code in a string: "
                            f"{_BARE_IN_TEXT.search(node.value).group(0).strip()}")
    assert not bare, "bare imports:\n" + "\n".join(bare)


def test_relative_imports_stay_inside_the_package():
    for path in _python_files(*TOP):
        for line, target, text in _imports(path):
            if text.startswith("from .") and target is not None:
                assert target and target[0] in TOP + ("__version__",), f"{path.relative_to(ROOT)}:{line}: {text}"


def test_dependencies_point_one_way():
    """backend imports nothing of frontend, synth or tools; frontend and synth nothing of tools or of
    each other; inside backend no module imports from a floor above its own."""
    allowed = {"backend": {"backend"}, "frontend": {"backend", "frontend"}, "synth": {"backend", "synth"},
               "tools": set(TOP)}
    wrong = []
    for path in _python_files(*TOP):
        source = _module_name(path)
        for line, target, text in _imports(path):
            if not target or target[0] not in TOP:
                continue
            if target[0] not in allowed[source[0]]:
                wrong.append(f"{path.relative_to(ROOT)}:{line}: {text}")
            elif source[0] == target[0] == "backend" and len(source) > 1 and len(target) > 1:
                if FLOOR[target[1]] > FLOOR[source[1]]:
                    wrong.append(f"{path.relative_to(ROOT)}:{line}: {text} (backend.{source[1]} -> backend.{target[1]})")
    assert not wrong, "imports against the layering:\n" + "\n".join(wrong)


def test_every_backend_subpackage_has_a_floor():
    subpackages = {p.name for p in (ROOT / "backend").iterdir() if p.is_dir() and (p / "__init__.py").exists()}
    modules = {p.stem for p in (ROOT / "backend").glob("*.py") if p.stem != "__init__"}
    assert subpackages | modules == set(FLOOR)


def test_only_vislam_is_importable_outside_the_repository(tmp_path):
    code = (
        "import importlib, vislam\n"
        "print(vislam.__version__)\n"
        "for name in ('backend', 'frontend', 'synth', 'tools'):\n"
        "    try:\n"
        "        importlib.import_module(name)\n"
        "    except ModuleNotFoundError:\n"
        "        continue\n"
        "    raise SystemExit(f'{name} is importable')\n"
    )
    out = subprocess.run([sys.executable, "-c", code], cwd=tmp_path, capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == vislam.__version__


def test_public_face():
    assert vislam.__version__ == importlib.metadata.version("vislam")
    for name in vislam.__all__:
        assert getattr(vislam, name) is not None, name
    assert vislam.VisualInertialEKF.__module__ == "vislam.backend.estimator.ekf"
    assert vislam.run_sequence.__module__ == "vislam.backend.run.runner"
    with pytest.raises(AttributeError):
        vislam.no_such_name  # noqa: B018


def test_console_script_points_into_vislam():
    scripts = {e.name: e.value for e in importlib.metadata.entry_points(group="console_scripts")}
    assert scripts["vislam"] == "vislam.tools.cli:entry"


def test_every_subpackage_is_listed_for_the_wheel():
    """pyproject's explicit package list names every folder with an __init__.py (a non-editable
    install ships only those; a missing one breaks `pip install .`)."""
    import tomllib

    root = Path(__file__).resolve().parents[1]
    listed = set(tomllib.loads((root / "pyproject.toml").read_text())["tool"]["setuptools"]["packages"])
    found = {"vislam"} | {
        "vislam." + ".".join(p.parent.relative_to(root).parts)
        for p in root.rglob("__init__.py")
        if not ({"tests", ".venv", "build", "benchmarks", "examples"} & set(p.relative_to(root).parts))
        and p.parent != root
    }
    assert listed == found


def _is_covariance(node: ast.AST) -> bool:
    return isinstance(node, ast.Attribute) and node.attr == "P"


def _writes_to_covariance(path: Path) -> list[int]:
    """Lines of ``path`` that may change an attribute ``P``: assignments to it or to part of it
    (``x.P = ...``, ``x.P[...] += ...``), an alias of it (``P = x.P``), or a call of an in-place
    kernel (``*_inplace``, ``repair_if_indefinite``) with it as an argument."""
    lines = []
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        targets = []
        if isinstance(node, ast.Assign):
            targets = node.targets
            if _is_covariance(node.value):
                lines.append(node.lineno)
        elif isinstance(node, (ast.AugAssign, ast.AnnAssign)):
            targets = [node.target]
        elif isinstance(node, ast.Call):
            name = getattr(node.func, "attr", getattr(node.func, "id", ""))
            if (name.endswith("_inplace") or name == "repair_if_indefinite") and any(map(_is_covariance, node.args)):
                lines.append(node.lineno)
        for target in targets:
            while isinstance(target, ast.Subscript):
                target = target.value
            if _is_covariance(target):
                lines.append(node.lineno)
    return lines


def test_only_the_state_helper_writes_the_covariance():
    """OpenVINS's rule: one owner of P. No module of the package assigns to a state's P (or to
    part of it) but ``backend/estimator/state_helper.py`` and the state's own default in ``state.py``;
    the check finds the writes it must (the helper's), so it can fail."""
    found = {path.relative_to(ROOT).as_posix(): _writes_to_covariance(path)
             for path in _python_files("backend", "frontend", "synth", "tools")}
    writers = {name for name, lines in found.items() if lines}
    assert "backend/estimator/state_helper.py" in writers
    assert writers <= {"backend/estimator/state_helper.py", "backend/estimator/state.py"}, writers
    assert len(found["backend/estimator/state.py"]) == 1  # __post_init__: the empty core
