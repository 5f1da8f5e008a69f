"""The site's figures, drawn by the tool itself at every build (as its users would draw them), so
a picture on the site is what the program draws today. Each is a few seconds' work: a trial on
the simulated rig at speed 0 and its replay; a small simulated force map and its report."""

from __future__ import annotations

import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

RIG = [sys.executable, "-m", "rig"]

# name on the site -> (the commands, run in one scratch folder in order; the file they draw)
FIGURES: dict[str, tuple[list[list[str]], str]] = {
    "demo-trial.png": ([[*RIG, "run", "protocols/demo.yaml", "--speed", "0", "--quiet", "--out", "trials"],
                        [*RIG, "replay", "--plot", "demo.png", "trials/*.mcap"]], "demo.png"),
    "map-E.png": ([[*RIG, "sim-map", "map.h5", "--grid", "6x6", "--seed", "2"],
                   [*RIG, "analyze", "map.h5", "--model", "hertz", "--indenter", "paraboloid:R=5um",
                    "--report", "report"]], "report/map1_E_Pa.png"),
}


def make(out: Path, root: Path) -> None:
    """Draw every figure into `out` (a failure stops the build, saying which command failed)."""
    out.mkdir(parents=True, exist_ok=True)
    for name, (commands, drawn) in FIGURES.items():
        with tempfile.TemporaryDirectory(prefix="rig-docs-") as tmp:
            work = Path(tmp)
            (work / "protocols").symlink_to(root / "protocols")
            for command in commands:
                # a glob names the file an earlier command wrote (a log's name carries its time)
                command = [next(iter(sorted(work.glob(a))), a) if "*" in a else a for a in command]
                command = [str(a.relative_to(work)) if isinstance(a, Path) else a for a in command]
                done = subprocess.run(command, cwd=work, capture_output=True, text=True, timeout=300)
                if done.returncode != 0:
                    raise RuntimeError(f"the figure {name}: `{' '.join(command[2:])}` failed "
                                       f"(exit status {done.returncode}):\n{done.stdout}{done.stderr}")
            shutil.copyfile(work / drawn, out / name)
