"""Biomomentum Mach-1 Motion `.txt` exports: tagged sections, each test function's data
between `<DATA>` and `<END DATA>`, a header row `Name, unit` (tab-separated), `<divider>`
lines between the blocks of a multi-ramp test. Force in N or gf; compression usually reads
as negative Fz."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from rig.errors import SpecError
from rig.records.record import Record
from rig.records.units import split_header, to_si


def looks_like_mach1(head: str) -> bool:
    """Whether a file's head is a Mach-1 export (its `<Mach-1 File>`, `<INFO>` and `<DATA>` blocks)."""
    return "<Mach-1 File>" in head[:200] or ("<DATA>" in head and "<INFO>" in head)


def count_blocks(path: Path) -> int:
    """How many <DATA> blocks (test functions, one site each in a mapping test) the file holds."""
    with open(path, errors="replace") as fh:
        return sum(1 for line in fh if line.strip() == "<DATA>")


def read_mach1(path: Path, block: int | None = None) -> Record:
    """One test function's data, dividers joined: block number `block` (from 1), by default the
    longest (a file often holds a short find-contact step before the test)."""
    where = str(path)
    try:
        lines = path.read_text(errors="replace").splitlines()
    except OSError as exc:
        raise SpecError(f"cannot open: {exc.strerror or exc}", path=where) from None
    blocks: list[tuple[str, int, list[str], list[tuple[int, list[str]]]]] = []
    section = ""
    i = 0
    while i < len(lines):
        s = lines[i].strip()
        if (s.startswith("<") and s.endswith(">") and s not in ("<DATA>", "<END DATA>", "<divider>")
                and not s.startswith("<END")):
            section = s.strip("<>")
        if s == "<DATA>":
            if i + 1 >= len(lines):
                raise SpecError("<DATA> without a header row", path=where, line=i + 1)
            header = [h.strip() for h in lines[i + 1].split("\t")]
            rows = []
            j = i + 2
            while j < len(lines) and lines[j].strip() != "<END DATA>":
                r = lines[j].strip()
                if r and r != "<divider>":
                    rows.append((j + 1, lines[j].split("\t")))
                j += 1
            if j >= len(lines):
                raise SpecError("<DATA> block without <END DATA>", path=where, line=i + 1)
            blocks.append((section, i + 2, header, rows))
            i = j
        i += 1
    if not blocks:
        raise SpecError("a Mach-1 file without a <DATA> ... <END DATA> block", path=where)
    if block is not None and not 1 <= block <= len(blocks):
        raise SpecError(f"the file has {len(blocks)} data block(s), not {block}", path=where)
    if block is None:  # the test itself, not a find-contact step before it: the longest block
        block = 1 + max(range(len(blocks)), key=lambda k: len(blocks[k][3]))
    section, header_line, header, rows = blocks[block - 1]
    t_i, z_i, f_i = _columns(header, where, header_line)
    out = np.empty((len(rows), 3))
    for k, (no, r) in enumerate(rows):
        try:
            out[k] = [float(r[t_i[0]]), float(r[z_i[0]]), float(r[f_i[0]])]
        except (IndexError, ValueError):
            raise SpecError(f"not a row of {len(header)} numbers: '{chr(9).join(r)[:50]}'", path=where,
                            line=no) from None
    if len(out) < 10:
        raise SpecError(f"the {section} data block has {len(out)} rows: too few", path=where, line=header_line)
    t = out[:, 0] * t_i[1]
    from rig.records.csvfile import check_time

    check_time(t, header[t_i[0]], where, header_line)
    notes = [f"Mach-1 {section}" + (f" (data block {block} of {len(blocks)}; --block picks another)"
                                    if len(blocks) > 1 else "")]
    return Record(path.name, "mach1", t, out[:, 1] * z_i[1], out[:, 2] * f_i[1], length_unit="mm",
                  force_unit=split_header(header[f_i[0]])[1] or "N", notes=notes)


def _columns(header: list[str], where: str, line: int):
    def find(names: tuple[str, ...], kind: str):
        for i, h in enumerate(header):
            name, unit = split_header(h)
            if name.strip().lower() in names:
                return i, to_si(h, kind, unit, where)
        return None

    t = find(("time",), "time")
    z = find(("position (z)", "position(z)", "position"), "length")
    f = find(("fz", "force", "load"), "force")
    missing = [n for n, c in (("Time, s", t), ("Position (z), mm", z), ("Fz, N", f)) if c is None]
    if missing:
        raise SpecError(f"Mach-1 data header lacks {', '.join(missing)} (has {', '.join(header)})",
                        path=where, line=line)
    return t, z, f
