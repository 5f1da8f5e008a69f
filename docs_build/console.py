"""The console examples of the documentation's pages, run and compared with what the page shows.

A page's ```console block holds commands (`$ ` lines; a line ending in `\\` goes on) each followed
by the output the page shows. What is compared:

- the text, word for word (runs of spaces are one space: a table's columns may shift);
- the numbers, to 1 % (the last digits of a fit move with the machine's floating point), except
  durations and rates of the machine (a number followed by `s`, `ms`, `/s`, and a duration's
  share in percent just after it) and its counts of late and missed ticks, which may be any
  (the clock tests hold a real-time trial to none: `tests/test_live.py`, `rig bench`);
- dates, times of day and temporary paths are any;
- `...` on a line of its own stands for any lines (none included), and inside a line for any text.

A ```python block that does not name a file is run as a script, and what it prints compared with
the next block when that is a ```text block (with nothing, when it is not).

A block runs in one shell, in a scratch folder beside which `../shared` is the project's (so the
pages' paths work as written) and `protocols/` and `config/` are the project's own. A code block
of the page whose first line names a file (`# my_effects.py`, `# stiff.yaml`) is written there
first, so the commands use the file the page shows.
"""

from __future__ import annotations

import math
import os
import re
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path

NUMBER = re.compile(r"[-+]?(?:\d+\.\d*|\.\d+|\d+)(?:[eE][-+]?\d+)?")
TIMING = re.compile(NUMBER.pattern + r"(?=\s?(?:s|ms|/s)\b)")
# a duration's share of a whole, as in "reading 1.09 s (23 %)"
TIME_SHARE = re.compile(r"(?<=s \()\d+(?:\.\d*)?(?=\s?%\))")
# a real-time trial's late and missed ticks, as in "(0 late, 0 missed ticks)": a virtual machine's
# host can stall the loop past its tolerance now and then, with nothing else running in the guest
TICKS = re.compile(r"\d+(?= (?:late|missed)\b)")
ANY = [
    (re.compile(r"(?<!\d)\d{8}-\d{6}(?!\d)"), "<stamp>"),  # a log's name
    (re.compile(r"\b\d{4}-\d{2}-\d{2}[T ]\d{2}:\d{2}:\d{2}(?:\.\d+)?(?:Z|[+-]\d{2}:?\d{2})?"), "<when>"),
    (re.compile(r"/tmp/[^/\s'\"),]+"), "<tmp>"),  # a scratch folder; what is in it still counts
]
RELATIVE = 0.01


@dataclass
class Example:
    page: Path
    line: int  # of the block's first line in the page
    commands: list[tuple[str, list[str]]]  # (command, the output the page shows)
    files: dict[str, str]  # the page's named code blocks: file name -> text


FILE_NAME = re.compile(r"^#\s*([\w.-]+\.(?:py|yaml|yml|csv|txt))\s*$")


@dataclass
class Block:
    fence: int  # line of the opening fence in the page
    kind: str  # what follows the fence: console, python, yaml, text, sh, {toctree}, ...
    text: list[str]

    @property
    def file(self) -> str | None:
        """The file the block is, when its first line names one."""
        m = FILE_NAME.match(self.text[0]) if self.text else None
        return m.group(1) if m else None


def blocks(page: Path) -> list[Block]:
    """Every fenced block of a page, in order."""
    out: list[Block] = []
    lines = page.read_text().splitlines()
    i = 0
    while i < len(lines):
        fence = lines[i].strip()
        if fence.startswith("```") and len(fence) > 3:
            start, i = i + 1, i + 1
            block = []
            while i < len(lines) and lines[i].strip() != "```":
                block.append(lines[i])
                i += 1
            out.append(Block(start, fence[3:].strip(), block))
        i += 1
    return out


# files whose format has no comment: the page's `# notes.txt` above one is its label, not its
# first line (a YAML or Python file keeps it, a comment there as it would be in the user's copy)
NO_COMMENTS = (".txt", ".csv")


def _content(block: Block) -> str:
    """What a named block's file holds, as a reader who copies it from the page writes it."""
    text = block.text[1:] if block.file.endswith(NO_COMMENTS) else block.text
    return "\n".join(text) + "\n"


def examples(page: Path) -> list[Example]:
    """Every console block of a page, and every Python block that is not a named file (run as a
    script: its output is the next block when that is a ```text block), each with the page's named
    code blocks."""
    found = blocks(page)
    files = {b.file: _content(b) for b in found if b.file}
    out = []
    for k, b in enumerate(found):
        if b.kind == "console":
            out.append(Example(page, b.fence + 1, _commands(b.text), files))
        elif b.kind == "python" and not b.file:
            nxt = found[k + 1] if k + 1 < len(found) else None
            script = f"example-{b.fence}.py"
            shown = nxt.text if nxt is not None and nxt.kind == "text" else []
            out.append(Example(page, b.fence + 1, [(f"python {script}", shown)],
                               {**files, script: "\n".join(b.text) + "\n"}))
    return out


# not code of their own: output (text), and console blocks, which run (one without a command
# does not, and `unrun` says so); the site's directives ({toctree}) are told by their brace
NOT_CODE = ("text", "console")


def unrun(page: Path) -> list[Block]:
    """The code blocks of a page that no example runs: not a console block with a command, not a
    Python script, not output, not a directive, and not a file that a console command of the page
    uses."""
    found = blocks(page)
    commands = " ".join(c for ex in examples(page) for c, _ in ex.commands)
    return [b for b in found
            if (b.kind == "console" and not _commands(b.text))
            or (b.kind not in NOT_CODE and not b.kind.startswith("{")
            and not (b.kind == "python" and not b.file)
            and not (b.file and b.file in commands))]


def _commands(block: list[str]) -> list[tuple[str, list[str]]]:
    commands: list[tuple[str, list[str]]] = []
    i = 0
    while i < len(block):
        line = block[i]
        if line.startswith("$ "):
            command = line[2:]
            while command.endswith("\\") and i + 1 < len(block):
                i += 1
                command = command[:-1] + " " + block[i].strip()
            commands.append((command, []))
        elif commands:
            commands[-1][1].append(line)
        i += 1
    return commands


def run(example: Example, root: Path, scratch: Path,
        timeout_s: float = 900) -> list[tuple[str, int, list[str]]]:
    """Run a block's commands in one shell: (command, exit status, output lines) for each."""
    work = scratch / "work"
    work.mkdir(parents=True, exist_ok=True)
    for name, text in example.files.items():
        (work / name).write_text(text)
    for name in ("protocols", "config"):
        if not (work / name).exists():
            (work / name).symlink_to(root / name)
    shared = root.parent / "shared"
    if shared.exists() and not (scratch / "shared").exists():
        (scratch / "shared").symlink_to(shared)
    marker = "=====8<===== rig docs"
    script = []
    for n, (command, _) in enumerate(example.commands):
        script.append(f"printf '%s\\n' '{marker} command {n}'")
        # grouped, so that a redirection the page writes applies before the block's own
        script.append(f"{{ {command}\n}} 2>&1; printf '\\n%s %d\\n' '{marker} status' $?")
    # `rig` as installed beside the Python running this, first on the path
    path = os.pathsep.join([str(Path(sys.executable).parent), os.environ.get("PATH", "")])
    env = dict(os.environ, PATH=path, COLUMNS="100", NO_COLOR="1", PYTHONUNBUFFERED="1")
    done = subprocess.run(["bash", "-c", "\n".join(script)], cwd=work, env=env, capture_output=True,
                          text=True, timeout=timeout_s)
    found = {}
    for m in re.finditer(rf"^{re.escape(marker)} command (\d+)\n(.*?)\n{re.escape(marker)} status (\d+)$",
                         done.stdout, flags=re.S | re.M):
        found[int(m.group(1))] = (int(m.group(3)), m.group(2).split("\n"))
    return [(command, *found.get(n, (-1, [f"(no output: the shell ended first: {done.stderr.strip()})"])))
            for n, (command, _) in enumerate(example.commands)]


def _normal(line: str) -> str:
    for pattern, token in ANY:
        line = pattern.sub(token, line)
    return " ".join(line.split())


def _numbers_match(shown: str, got: str) -> bool:
    a, b = float(shown), float(got)
    if a == b:
        return True
    if not (math.isfinite(a) and math.isfinite(b)):
        return False
    # the page's last printed digit is as far as it can be held to, beside the relative part
    digits = shown.lower().split("e")[0]
    step = 10.0 ** -(len(digits.split(".")[1]) if "." in digits else 0)
    if "e" in shown.lower():
        step *= 10.0 ** int(shown.lower().split("e")[1])
    return abs(a - b) <= max(RELATIVE * max(abs(a), abs(b)), step)


def line_matches(shown: str, got: str) -> bool:
    """Does an output line match the line a page shows?"""
    shown, got = _normal(shown), _normal(got)
    if shown == got:
        return True
    # the shown line as a pattern: its text literal, `...` any text, numbers captured
    pattern, numbers, pos = [], [], 0
    timing = {m.start() for pattern in (TIMING, TIME_SHARE, TICKS) for m in pattern.finditer(shown)}
    for m in re.finditer(r"\.\.\.|" + NUMBER.pattern, shown):
        pattern.append(re.escape(shown[pos:m.start()]))
        if m.group() == "...":
            pattern.append(".*?")
        else:
            pattern.append(f"({NUMBER.pattern})")
            numbers.append((m.group(), m.start() in timing))
        pos = m.end()
    pattern.append(re.escape(shown[pos:]))
    found = re.fullmatch("".join(pattern), got)
    if not found:
        return False
    return all(is_timing or _numbers_match(value, found.group(k + 1))
               for k, (value, is_timing) in enumerate(numbers))


def mismatch(shown: list[str], got: list[str]) -> str | None:
    """Where the output departs from what the page shows (None when it does not): `...` lines of
    the page take any lines."""
    # blank lines are layout, not output
    shown = [s for s in shown if s.strip()]
    got = [g for g in got if g.strip()]

    def match(i: int, j: int) -> bool:
        while i < len(shown):
            if shown[i].strip() == "...":
                return any(match(i + 1, k) for k in range(j, len(got) + 1))
            if j >= len(got) or not line_matches(shown[i], got[j]):
                return False
            i, j = i + 1, j + 1
        return j == len(got)

    if match(0, 0):
        return None
    # the first shown line that nothing matches, for the message
    j = 0
    for i, s in enumerate(shown):
        if s.strip() == "...":
            continue
        hit = next((k for k in range(j, len(got)) if line_matches(s, got[k])), None)
        if hit is None:
            return f"line {i + 1} of the shown output, {s!r}, is not in the output"
        j = hit + 1
    return "the output has lines the page does not show (add them, or `...`)"
