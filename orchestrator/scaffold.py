"""Skeleton code for new vehicles and devices (thesis §7.1: "generate new Vehicle or Device
code ... leave skeleton code where users must fill in the needed methods").

:func:`plan_vehicle` / :func:`plan_device` render the templates in ``templates/`` into
:class:`GeneratedFile` objects; :func:`write_files` writes them, refusing to overwrite anything.
Every generated method that needs the user's knowledge raises ``NotImplementedError`` with a
message that says what to put there, and the generated test fails until it is filled in.

Names: ``NAME`` may be snake_case (``my_rover``) or CamelCase (``MyRover``); the module is the
snake_case form, the class the CamelCase form. A name must be an ASCII identifier that is not
a Python keyword and does not shadow a standard-library module or ``hilswarm``.
"""

from __future__ import annotations

import keyword
import re
import string
import sys
from dataclasses import dataclass
from pathlib import Path

from hilswarm.agents.errors import HilswarmError
from hilswarm.agents.pins import PROFILES
from hilswarm.orchestrator.output_paths import check_output_folder

#: Folder of the ``*.tmpl`` files.
TEMPLATE_DIR = Path(__file__).resolve().parent / "templates"
#: Device kinds ``hilswarm new device --kind`` accepts.
DEVICE_KINDS = ("actuator", "sensor")

_IDENTIFIER = re.compile(r"^[A-Za-z][A-Za-z0-9_]*$")
_CAMEL_BOUNDARY = re.compile(r"(?<=[a-z0-9])(?=[A-Z])|(?<=[A-Z])(?=[A-Z][a-z])")


class ScaffoldError(HilswarmError, ValueError):
    """A bad name or kind, or a generated file would overwrite an existing one."""


@dataclass(frozen=True)
class ScaffoldNames:
    """The names derived from the user's ``NAME``.

    Attributes:
        module: snake_case module name (``my_rover``).
        class_name: CamelCase class name (``MyRover``).
    """

    module: str
    class_name: str


@dataclass(frozen=True)
class GeneratedFile:
    """One file to write: its path and its full text."""

    path: Path
    text: str


def scaffold_names(name: str) -> ScaffoldNames:
    """Snake and Camel forms of ``name``.

    Raises:
        ScaffoldError: not an identifier, a keyword, double/edge underscores, or a name that
            would shadow a standard-library module or hilswarm itself.
    """
    if not isinstance(name, str) or not _IDENTIFIER.match(name):
        raise ScaffoldError(
            f"name {name!r} must start with a letter and hold only ASCII letters, digits and '_' "
            "(e.g. my_rover or MyRover)"
        )
    if "__" in name or name.endswith("_"):
        raise ScaffoldError(f"name {name!r}: no double or trailing underscores")
    module = "_".join(part.lower() for part in _CAMEL_BOUNDARY.split(name))
    class_name = "".join(part[:1].upper() + part[1:] for part in module.split("_"))
    if keyword.iskeyword(module) or module in sys.stdlib_module_names or module == "hilswarm":
        raise ScaffoldError(
            f"name {name!r}: module {module!r} would shadow a Python keyword or module; "
            "choose another name"
        )
    if module.startswith("test"):
        raise ScaffoldError(f"name {name!r}: a module named test* would be collected as a test")
    return ScaffoldNames(module=module, class_name=class_name)


def render(template: str, **values: str) -> str:
    """Fill ``${key}`` placeholders of ``templates/<template>``; every key must be given."""
    text = (TEMPLATE_DIR / template).read_text(encoding="utf-8")
    try:
        return string.Template(text).substitute(values)
    except (KeyError, ValueError) as exc:  # a template bug, not a user error
        raise RuntimeError(f"template {template}: missing or malformed placeholder {exc}") from None


def _sorted_from_imports(*lines: str) -> str:
    """``from x import y`` lines in isort order (by module), so the output is ruff-clean."""
    return "\n".join(sorted(lines, key=lambda line: line.split()[1].lower()))


def plan_vehicle(name: str, directory: Path, *, profile: str = "uno") -> list[GeneratedFile]:
    """Files of ``hilswarm new vehicle NAME``: module, test and experiment file.

    Raises:
        ScaffoldError: a bad name, or ``profile`` is not a board profile (:data:`PROFILES`).
    """
    if profile not in PROFILES:
        raise ScaffoldError(f"unknown board profile {profile!r} (known: {', '.join(PROFILES)})")
    names = scaffold_names(name)
    directory = Path(directory)
    module_file = f"{names.module}.py"
    test_file = f"test_{names.module}.py"
    experiment_file = f"{names.module}.toml"
    values = {
        "module_name": names.module,
        "class_name": names.class_name,
        "test_file": test_file,
        "experiment_file": experiment_file,
        "profile": profile,
    }
    imports = _sorted_from_imports(
        "from hilswarm.agents.link.sim_board import SimBoard",
        f"from {names.module} import {names.class_name}",
    )
    test_text = render("vehicle_test.py.tmpl", imports=imports, **values)
    return [
        GeneratedFile(directory / module_file, render("vehicle.py.tmpl", **values)),
        GeneratedFile(directory / test_file, test_text),
        GeneratedFile(
            directory / experiment_file, render("vehicle_experiment.toml.tmpl", **values)
        ),
    ]


def plan_device(name: str, directory: Path, *, kind: str = "actuator") -> list[GeneratedFile]:
    """Files of ``hilswarm new device NAME``: module and test."""
    if kind not in DEVICE_KINDS:
        raise ScaffoldError(f"device kind must be one of {DEVICE_KINDS}, got {kind!r}")
    names = scaffold_names(name)
    directory = Path(directory)
    test_file = f"test_{names.module}.py"
    values = {"module_name": names.module, "class_name": names.class_name, "test_file": test_file}
    imports = _sorted_from_imports(
        "from hilswarm.agents.link.sim_board import SimBoard",
        "from hilswarm.agents.pins import PinManager" + (", parse_pin" if kind == "sensor" else ""),
        f"from {names.module} import EXAMPLE_PINOUT, {names.class_name}",
    )
    test_text = render(f"device_{kind}_test.py.tmpl", imports=imports, **values)
    return [
        GeneratedFile(directory / f"{names.module}.py", render(f"device_{kind}.py.tmpl", **values)),
        GeneratedFile(directory / test_file, test_text),
    ]


def write_files(files: list[GeneratedFile]) -> list[Path]:
    """Write every file, or none: refuses if any already exists or cannot be written.

    Raises:
        ScaffoldError: the existing files are named; nothing is written.
        OutputPathError: a folder of the files cannot be written into (a file in its place,
            a read-only folder); nothing is written.
    """
    for folder in dict.fromkeys(f.path.parent for f in files):
        check_output_folder(folder, what="the new files")
    existing = [str(f.path) for f in files if f.path.exists()]
    if existing:
        raise ScaffoldError(
            f"refusing to overwrite existing file(s): {', '.join(existing)}; "
            "choose another name or --dir"
        )
    written: list[Path] = []
    for generated in files:
        generated.path.parent.mkdir(parents=True, exist_ok=True)
        with generated.path.open("x", encoding="utf-8") as handle:  # "x": never overwrite
            handle.write(generated.text)
        written.append(generated.path)
    return written
