"""Problems found in an experiment file, and the error that carries all of them at once.

Loading and checking an experiment never stops at the first mistake: every check appends a
:class:`Problem` (file, key, reason) and the caller raises one :class:`ExperimentError` that
lists them all, so a user fixes a file in one pass instead of one error per run.
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path

from hilswarm.agents.errors import HilswarmError


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
