"""mypy checks the package under the names it is installed as (``ballbar.analysis`` is ``analysis/``, ...).

``.typecheck/ballbar`` links each folder of ``[tool.setuptools.package-dir]``
under its package name, and ``[tool.mypy] files`` is that tree: an import of
``ballbar.x`` is then the code itself, not an unresolved module mypy would
take as ``Any`` (the editable install's import hook is invisible to it), and
no module is checked under two names.
"""

from __future__ import annotations

import tomllib
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]


def test_the_typecheck_tree_mirrors_the_package_dirs() -> None:
    project = tomllib.loads((REPO / "pyproject.toml").read_text(encoding="utf-8"))
    assert project["tool"]["mypy"]["files"] == [".typecheck/ballbar"]
    tree = REPO / ".typecheck"
    for package, folder in project["tool"]["setuptools"]["package-dir"].items():
        if package == "ballbar":
            continue  # the tree's own folder, holding the links
        linked = tree.joinpath(*package.split("."))
        assert linked.resolve() == (REPO / folder).resolve(), f"{package}: .typecheck does not link {folder}"
    # the package itself: its __init__ and its marker, not its schema files (data)
    assert (tree / "ballbar" / "__init__.py").resolve() == (REPO / "ballbar" / "__init__.py").resolve()
    assert (tree / "ballbar" / "py.typed").resolve() == (REPO / "ballbar" / "py.typed").resolve()
