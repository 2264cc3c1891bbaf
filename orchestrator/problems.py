"""Problems found in an experiment file, and the error that carries all of them at once.

Loading and checking an experiment never stops at the first mistake: every check appends a
:class:`Problem` (file, key, reason) and the caller raises one :class:`ExperimentError` that
lists them all, so a user fixes a file in one pass instead of one error per run.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from hilswarm.agents.errors import HilswarmError
from pydantic import BaseModel, ValidationError


@dataclass(frozen=True)
class Problem:
    """One thing wrong with an experiment file.

    Attributes:
        file: the file the problem is in (the experiment file, or a graph/calibration file
            it names).
        key: the dotted TOML key the problem is about, e.g. ``"agents.leader.link"`` or
            ``"graph.adjacency[2][3]"``; ``""`` when the whole file is at fault.
        message: the reason, saying what was found and what was expected.
    """

    file: Path | str
    key: str
    message: str

    def __str__(self) -> str:
        where = f"{self.file}:{self.key}" if self.key else f"{self.file}"
        return f"{where}: {self.message}"


class ExperimentError(HilswarmError, ValueError):
    """An experiment file (or an override of it) has one or more problems.

    Attributes:
        problems: every problem found, in file order as far as possible.
    """

    def __init__(self, problems: Iterable[Problem]) -> None:
        self.problems: tuple[Problem, ...] = tuple(problems)
        if not self.problems:
            raise ValueError("ExperimentError needs at least one problem")
        super().__init__(self.format())

    def format(self) -> str:
        """All problems, one ``file:key: reason`` per line, preceded by a count."""
        count = len(self.problems)
        head = f"{count} problem{'s' if count != 1 else ''} in experiment"
        return "\n".join([head, *(f"  {problem}" for problem in self.problems)])


# -- schema errors -> problems ---------------------------------------------------------------

#: Key suffix -> unit shown after a value (the project names quantities by unit: rate_hz).
_UNITS = {"_hz": " Hz", "_s": " s", "_m": " m", "_rad": " rad"}
#: pydantic type error -> what was expected, for "'x' is not <expected>".
_EXPECTED = {
    "float_type": "a number",
    "int_type": "an integer",
    "bool_type": "true or false",
    "string_type": "a string",
    "dict_type": "a table",
    "model_type": "a table",
    "list_type": "a list",
}
_BOUNDS = {
    "greater_than": ">",
    "greater_than_equal": ">=",
    "less_than": "<",
    "less_than_equal": "<=",
}
_BOUND_KEYS = {"greater_than": "gt", "greater_than_equal": "ge", "less_than": "lt"}


def key_path(prefix: str, loc: Iterable[str | int]) -> str:
    """The dotted key of a value: ``("agents", "a", "initial_state", 0)`` ->
    ``agents.a.initial_state[0]``."""
    key = prefix
    for part in loc:
        if isinstance(part, int):
            key += f"[{part}]"
        else:
            key = f"{key}.{part}" if key else str(part)
    return key


def schema_problems(
    error: ValidationError, file: Path | str, prefix: str, model: type[BaseModel]
) -> list[Problem]:
    """One :class:`Problem` per error of a table validated with ``model`` at key ``prefix``."""
    problems = []
    for detail in error.errors(include_url=False):
        loc = tuple(detail["loc"])
        if loc and loc[-1] == "[key]":  # a bad table name: reported on the table itself
            loc = loc[:-1]
        field = next(
            (part for part in reversed(loc) if isinstance(part, str)),
            prefix.rsplit(" ", 1)[-1].rsplit(".", 1)[-1],
        )
        reason = _reason(detail, loc, field, model)
        problems.append(Problem(file, key_path(prefix, loc), reason))
    return problems


def _reason(
    detail: Mapping[str, Any], loc: tuple[str | int, ...], field: str, model: type[BaseModel]
) -> str:
    kind, value, ctx = detail["type"], detail.get("input"), detail.get("ctx") or {}
    if kind == "missing":
        info = model.model_fields.get(str(loc[-1])) if len(loc) == 1 else None
        example = info.examples[0] if info is not None and info.examples else None
        return "missing" + (f"; e.g. {loc[-1]} = {_toml(example)}" if example is not None else "")
    if kind == "extra_forbidden":
        known = ", ".join(model.model_fields) if len(loc) == 1 else ""
        return "unknown key" + (f"; expected one of {known}" if known else "")
    if kind in _EXPECTED:
        return f"{value!r} is not {_EXPECTED[kind]}"
    if kind == "finite_number":
        return f"{value!r} is not a finite number"
    if kind == "literal_error":
        return f"{value!r} is not one of {ctx.get('expected', '').replace(' or ', ', ')}"
    if kind in _BOUNDS:
        bound = ctx.get(_BOUND_KEYS.get(kind, "le"))
        unit = next((u for suffix, u in _UNITS.items() if field.endswith(suffix)), "")
        return f"{value!r}{unit} is out of range; expected {field} {_BOUNDS[kind]} {_toml(bound)}"
    if kind == "string_pattern_mismatch":
        return (
            f"{value!r} is not a valid name; use letters, digits, '_' and '-' only "
            "(it is part of bus keys)"
        )
    if kind in ("string_too_short", "too_short"):
        return "must not be empty"
    if kind in ("pin", "occlusion"):  # the schema's own error types carry their message
        return str(detail["msg"])
    return f"{value!r}: {detail['msg']}"


def _toml(value: Any) -> str:
    """A value as it is written in TOML (``20``, ``"x"``)."""
    if isinstance(value, float) and value.is_integer():
        return str(int(value))
    if isinstance(value, str):
        return f'"{value}"'
    return repr(value)
