"""One exception type for bad input: the CLI turns it into one line and exit code 2."""

from __future__ import annotations

from pathlib import Path


def one_line(text: object) -> str:
    """A message as one line (YAML, XML and checker errors span lines)."""
    return " ".join(str(text).split())


class InputError(Exception):
    """Input that cannot be used. `where` names the file (and element), `problem` says what is wrong."""

    def __init__(self, where: str | Path, problem: str) -> None:
        self.where = str(where)
        self.problem = problem
        super().__init__(f"{self.where}: {problem}")


class OutputError(Exception):
    """An output that cannot be written (unwritable folder, disk full)."""

    def __init__(self, where: str | Path, problem: str) -> None:
        self.where = str(where)
        self.problem = problem
        super().__init__(f"{self.where}: {problem}")
