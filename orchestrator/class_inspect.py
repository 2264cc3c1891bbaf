"""Look at a ``"package.module:Class"`` name *without running the module*.

``hilswarm check`` must not execute arbitrary code to find out that ``vehicle = "this:s"`` is
not a vehicle. Before anything is imported, :func:`static_class_problem` finds the module's
file (``importlib.machinery.PathFinder``, which locates packages level by level without
executing their ``__init__``) and reads its syntax tree (``ast``): the name must be bound at the
module's top level by a ``class`` statement, or be imported there from another module that
does (followed statically). Only then is the module imported (by the registry, which also
checks that the class subclasses ``Vehicle`` / ``Controller``): the user's module beside the
experiment runs in the agents anyway.

Modules of hilswarm itself are trusted and imported directly; Python's standard library has no
hilswarm classes, so a standard-library module is refused without importing it. Modules that
have no Python source to read (extension modules, namespace packages) cannot be inspected and
are left to the import.
"""

from __future__ import annotations

import ast
import importlib.machinery
import importlib.util
import sys
from pathlib import Path

from hilswarm.agents.registry import BASES

__all__ = ["static_class_problem"]

#: How many ``from x import Y`` hops are followed before giving up (then the import decides).
MAX_IMPORT_HOPS = 8


def static_class_problem(kind: str, name: str, target: str) -> str | None:
    """What is wrong with ``target`` (``"module:attr"``) as a ``kind`` class, or ``None``.

    ``None`` means "nothing found statically": the module may be imported to finish the check.

    Args:
        kind: ``"vehicle"`` or ``"controller"`` (for messages).
        name: the name as written in the experiment (for messages).
        target: ``"package.module:attr"`` (a registry name already replaced by its path).
    """
    module_name, _, attr = target.partition(":")
    top = module_name.split(".")[0]
    if top == "hilswarm" or module_name in sys.modules:
        return None
    if top in sys.stdlib_module_names:
        return (
            f"{kind} {name!r}: module {module_name!r} is part of Python's standard library, "
            f"which has no hilswarm {kind} classes; name a class that subclasses "
            f'{_BASES[kind]} (e.g. "my_robots:MyBot" in a file beside the experiment)'
        )
    return _inspect(kind, name, module_name, attr, hops=0)


_BASES = {kind: path.replace(":", ".") for kind, path in BASES.items()}


def _inspect(kind: str, name: str, module_name: str, attr: str, *, hops: int) -> str | None:
    if hops > MAX_IMPORT_HOPS or module_name.split(".", maxsplit=1)[0] in (
        "hilswarm",
        *sys.stdlib_module_names,
    ):
        return None
    spec = _find_spec(module_name)
    if spec is None:
        return (
            f"{kind} {name!r}: cannot find module {module_name!r} (looked beside the experiment "
            "file and on the Python path)"
        )
    origin = spec.origin
    if not origin or not origin.endswith(".py"):
        return None  # no source to read (extension module, namespace package)
    try:
        tree = ast.parse(Path(origin).read_text(encoding="utf-8"), filename=origin)
    except (OSError, UnicodeDecodeError, SyntaxError, ValueError) as exc:
        return f"{kind} {name!r}: cannot read module {module_name!r} ({origin}): {exc}"
    binding = _top_level_binding(tree, attr)
    if binding is None:
        return f"{kind} {name!r}: module {module_name!r} ({origin}) defines no {attr!r}"
    if isinstance(binding, ast.ClassDef):
        return None
    if isinstance(binding, ast.ImportFrom):
        source, source_attr = _import_source(binding, attr, module_name, spec)
        if source is None:
            return None
        return _inspect(kind, name, source, source_attr, hops=hops + 1)
    what = type(binding).__name__
    if isinstance(binding, ast.FunctionDef | ast.AsyncFunctionDef):
        what = "a function"
    elif isinstance(binding, ast.Assign | ast.AnnAssign):
        value = binding.value
        what = f"assigned a {type(value).__name__.lower()} expression" if value else "annotated"
    return (
        f"{kind} {name!r} is not a class: module {module_name!r} binds {attr!r} as {what} "
        f"(line {binding.lineno}); name a class that subclasses {_BASES[kind]}"
    )


def _find_spec(module_name: str) -> importlib.machinery.ModuleSpec | None:
    """The module's spec, found package by package without executing any package."""
    path: list[str] | None = None
    spec = None
    parts = module_name.split(".")
    for i in range(len(parts)):
        full = ".".join(parts[: i + 1])
        spec = importlib.machinery.PathFinder.find_spec(full, path)
        if spec is None:
            return None
        if i < len(parts) - 1:
            locations = spec.submodule_search_locations
            if locations is None:
                return None
            path = list(locations)
    return spec


def _top_level_binding(tree: ast.Module, attr: str) -> ast.stmt | None:
    """The last top-level statement (also inside ``if``/``try``) that binds ``attr``."""
    found: ast.stmt | None = None
    for node in _top_level_statements(tree.body):
        if isinstance(node, ast.ClassDef | ast.FunctionDef | ast.AsyncFunctionDef):
            if node.name == attr:
                found = node
        elif isinstance(node, ast.ImportFrom | ast.Import):
            for alias in node.names:
                bound = alias.asname or alias.name.split(".")[0]
                if bound == attr:
                    found = node
        elif isinstance(node, ast.Assign):
            if any(isinstance(t, ast.Name) and t.id == attr for t in node.targets):
                found = node
        elif (
            isinstance(node, ast.AnnAssign)
            and isinstance(node.target, ast.Name)
            and node.target.id == attr
        ):
            found = node
    return found


def _top_level_statements(body: list[ast.stmt]) -> list[ast.stmt]:
    statements: list[ast.stmt] = []
    for node in body:
        statements.append(node)
        if isinstance(node, ast.If):
            statements += _top_level_statements(node.body) + _top_level_statements(node.orelse)
        elif isinstance(node, ast.Try):
            statements += _top_level_statements(node.body)
            for handler in node.handlers:
                statements += _top_level_statements(handler.body)
    return statements


def _import_source(
    node: ast.stmt, attr: str, module_name: str, spec: importlib.machinery.ModuleSpec
) -> tuple[str | None, str]:
    """``(module, name)`` that ``from module import name as attr`` refers to."""
    if not isinstance(node, ast.ImportFrom):
        return None, attr  # `import x as attr` binds a module: the import decides
    original = next(a.name for a in node.names if (a.asname or a.name) == attr)
    if node.level == 0:
        return node.module, original
    package = spec.parent if spec.submodule_search_locations is None else spec.name
    base = package.rsplit(".", node.level - 1)[0] if node.level > 1 else package
    source = f"{base}.{node.module}" if node.module else base
    return (source if source else None), original
