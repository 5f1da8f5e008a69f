"""Names that become files: a specimen, an operator or a protocol name as one component of a
file name inside a log folder.

A name comes from whoever asks for a trial (over the daemon's socket, the daemon perhaps running
as root), so it is text, never a path: `/etc/x`, `..`, `a/b`, a NUL or `.hidden` must not pick
where a file goes. `file_part` keeps letters, digits, `-` and `_` and turns every other run of
characters into one `-`, so what it returns is never empty, absolute, `.` or `..`, hidden, or
more than one path component. `inside` checks a path built from such parts before anything is
written there.
"""

from __future__ import annotations

from pathlib import Path

from rig.errors import RigError


def file_part(text: str, *, default: str, max_chars: int = 40, lower: bool = False) -> str:
    """`text` as one safe component of a file name: letters and digits kept, `-` and `_` kept,
    any other run of characters (spaces, dots, slashes, NUL, ...) one `-`; no `-` at either
    end (a name that starts with one reads as an option to the shell's tools); at most
    `max_chars`; `default` when nothing is left."""
    kept = "".join(c if c.isalnum() or c in "-_" else "-" for c in (text.lower() if lower else text))
    part = "-".join(filter(None, kept.split("-")))[:max_chars].strip("-")
    return part or default


def inside(folder: Path, path: Path) -> Path:
    """`path`, once it is certain to lie inside `folder` (both resolved, symlinks followed);
    `RigError` naming both otherwise."""
    where = Path(path).resolve()
    if not where.is_relative_to(Path(folder).resolve()):
        raise RigError(f"{path} is outside the log folder {folder}: not written")
    return Path(path)
