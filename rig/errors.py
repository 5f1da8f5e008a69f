"""The error types the CLI turns into one-line messages (never a traceback)."""

from __future__ import annotations

import difflib


class RigError(Exception):
    """Base of every error the user can cause and fix (bad file, bad argument, lost device)."""


class SpecError(RigError):
    """A YAML/CSV input is wrong: says where (file, line, column), which field and what is wrong."""

    def __init__(
        self,
        message: str,
        *,
        path: str | None = None,
        line: int | None = None,
        column: int | None = None,
        field: str | None = None,
    ) -> None:
        self.message = message
        self.path = path
        self.line = line
        self.column = column
        self.field = field
        super().__init__(str(self))

    def __str__(self) -> str:
        where = self.path or "<input>"
        if self.line is not None:
            where += f":{self.line}"
            if self.column is not None:
                where += f":{self.column}"
        field = f" {self.field}:" if self.field else ""
        return f"{where}:{field} {self.message}"


class LimitError(RigError):
    """A protocol or command would take the rig beyond its travel, speed or force limits."""


class DeviceError(RigError):
    """A device did not answer, answered nonsense, or reported an alarm."""


def did_you_mean(name: str, choices, cutoff: float = 0.6) -> str:
    """' (did you mean 'x'?)' for the nearest choice, or ''."""
    near = difflib.get_close_matches(name, list(choices), n=1, cutoff=cutoff)
    return f" (did you mean '{near[0]}'?)" if near else ""
