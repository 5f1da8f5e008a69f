"""What a new technician and a new researcher met in their first hour with the README and the site
(issue 45): each item with the check that it stays fixed."""

from __future__ import annotations

import argparse
import importlib.util
import os
import re
import subprocess
import sys

import pytest

from tests.pages import DOCS


@pytest.fixture(scope="module")
def site(tmp_path_factory):
    """The site, built as .ci/run builds it (warnings are errors)."""
    for name in ("sphinx", "myst_parser", "furo"):
        if importlib.util.find_spec(name) is None:
            pytest.skip(f"{name} is not installed: the docs extra builds the site (pip install '.[docs]')")
    out = tmp_path_factory.mktemp("site") / "html"
    done = subprocess.run([sys.executable, "-m", "sphinx", "-W", "--keep-going", "-q", "-b", "html",
                           str(DOCS), str(out)], capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stderr
    return out


def _options(parser: argparse.ArgumentParser) -> set[str]:
    found = set()
    for action in parser._actions:
        found.update(o for o in action.option_strings if o.startswith("--"))
        if isinstance(action, argparse._SubParsersAction):
            for sub in action.choices.values():
                found |= _options(sub)
    return found


# --- an option is written with two hyphens on every page --------------------------------------

def test_no_option_of_rig_help_is_rendered_with_an_en_dash(site):
    from rig.cli import build_parser

    options = _options(build_parser())
    assert {"--config", "--characterize", "--target-rse", "--save", "--each"} <= options
    mangled = {}
    for page in site.rglob("*.html"):
        text = page.read_text()
        hits = sorted({o for o in options if re.search("\u2013" + re.escape(o[2:]) + r"(?![\w-])", text)})
        if hits:
            mangled[str(page.relative_to(site))] = hits
    assert mangled == {}, f"options rendered with an en dash instead of two hyphens: {mangled}"
    cli = (site / "reference" / "cli.html").read_text()
    assert "named by --config" in cli and "without --each" in cli
    # a docstring's `rig analyze --add` is code on the API page, as it is in Markdown
    api = (site / "api.html").read_text()
    assert '<span class="pre">--add</span>' in api


def test_an_empty_default_reads_empty_not_a_pair_of_backticks(site):
    cli = (site / "reference" / "cli.html").read_text()
    assert "<p>``</p>" not in cli
    rows = re.findall(r"<td><p><code[^>]*><span class=\"pre\">--operator</span></code>.*?</tr>", cli,
                      flags=re.S)
    assert len(rows) == 2 and all("<td><p>empty</p></td>" in r for r in rows), rows


# --- a plain text file is "not a file this tool can read", label or none -----------------------

def test_notes_txt_without_its_label_is_not_a_file_this_tool_can_read(tmp_path):
    from tests.pages import console

    page = DOCS / "explanation" / "records.md"
    example = next(ex for ex in console().examples(page)
                   if any(c == "rig analyze notes.txt" for c, _ in ex.commands))
    # the page's `# notes.txt` is the block's label, not the file's first line
    assert example.files["notes.txt"] == "lab notes, not a measurement\n"
    (tmp_path / "notes.txt").write_text("lab notes, not a measurement\n")
    done = subprocess.run([sys.executable, "-m", "rig", "analyze", "notes.txt"], cwd=tmp_path,
                          capture_output=True, text=True, timeout=60)
    assert done.returncode == 2
    assert done.stderr.startswith("rig analyze: error: notes.txt: not a file this tool can read (looked for"), \
        done.stderr
    # a table with a column missing still says which
    (tmp_path / "short.csv").write_text("t_s,position_mm\n0,1\n")
    done = subprocess.run([sys.executable, "-m", "rig", "analyze", "short.csv"], cwd=tmp_path,
                          capture_output=True, text=True, timeout=60)
    assert "missing column(s) force_N" in done.stderr


# --- the README's first command installs what its tour uses ------------------------------------

def test_the_readmes_first_command_installs_every_extra_its_tour_needs(tmp_path):
    """The tour's commands run where a package of an extra is missing name the extra they need;
    the README's first set-up command installs each of them (and stays one of exactly two)."""
    from tests.pages import README, ROOT, console

    text = README.read_text()
    first = text.index("```sh\n") + len("```sh\n")
    setup = text[first:text.index("```", first)].strip().splitlines()
    assert len(setup) == 2
    installed = re.match(r"python3 -m pip install '\.\[([\w,]+)\]' && python3 -m rig run ", setup[0])
    assert installed, f"the first set-up command installs no extra: {setup[0]}"
    extras = set(installed.group(1).split(","))
    (tour,) = console().examples(README)
    analyses = [c.split(" | ")[0] for c, _ in tour.commands if c.startswith("rig analyze ")]
    assert analyses
    # an environment with what `pip install .` alone gives: the optional readers are not there
    blocked = tmp_path / "without-extras"
    blocked.mkdir()
    (blocked / "afmformats.py").write_text("raise ImportError('not installed: the afm extra has it')\n")
    work = tmp_path / "work"
    work.mkdir()
    if "../shared/" in " ".join(analyses) and not (ROOT.parent / "shared").is_dir():
        pytest.skip("the tour reads ../shared/ (the real measurements), which is not beside the project")
    (tmp_path / "shared").symlink_to(ROOT.parent / "shared")
    needed = set()
    for command in analyses:
        done = subprocess.run(command, shell=True, cwd=work, capture_output=True, text=True, timeout=300,
                              env={**os.environ, "PYTHONPATH": str(blocked)})
        needed |= set(re.findall(r"indentation-rig\[(\w+)\]", done.stderr))
    assert needed == {"afm"}, needed
    assert needed <= extras, f"the tour needs the extras {sorted(needed)}; the first command installs {extras}"


# --- a console block fits the text column ------------------------------------------------------

# After the page has laid out, the blocks of the article wider than their box: "OVERFLOW:n:widths".
_MEASURE = """<script>window.addEventListener("load", () => {
  const wide = [...document.querySelectorAll("article div[class^='highlight-'] pre")]
    .filter(p => /highlight-(console|text|none)/.test(p.parentElement.parentElement.className))
    .filter(p => p.scrollWidth > p.clientWidth + 1).map(p => p.scrollWidth + "/" + p.clientWidth);
  const out = document.createElement("div");
  out.textContent = "OVERFLOW" + ":" + wide.length + ":" + wide.join(",");
  document.body.appendChild(out);
});</script>"""


@pytest.mark.parametrize("page", ["tutorials/force-map", "tutorials/afm-curve", "tutorials/first-trial"])
def test_console_blocks_fit_the_text_column_in_a_browser(site, page, tmp_path):
    import shutil

    browser = shutil.which("chromium") or shutil.which("chromium-browser")
    if browser is None:
        pytest.skip("chromium is not installed (apt-get install chromium): the blocks are measured in a "
                    "browser")
    html = site / f"{page}.html"
    probe = html.with_name(html.stem + "-measured.html")
    probe.write_text(html.read_text().replace("</body>", _MEASURE + "</body>"))
    done = subprocess.run([browser, "--headless", "--disable-gpu", "--no-sandbox", "--window-size=1280,900",
                           f"--user-data-dir={tmp_path}", "--virtual-time-budget=3000", "--dump-dom",
                           probe.as_uri()], capture_output=True, text=True, timeout=120)
    found = re.search(r"OVERFLOW:(\d+):([^<]*)", done.stdout)
    assert found, done.stderr[-2000:]
    assert found.group(1) == "0", (f"{page}: console blocks wider than the column (scroll/box px): "
                                   f"{found.group(2)}")
    # the rule is the site's, on every page
    assert "_static/console.css" in html.read_text()


# --- --design agrees with the verdict and with itself ------------------------------------------

def test_every_designed_candidate_says_what_its_steps_do():
    from rig.analysis.diagnosis.design import Shape, candidate_steps

    for c in candidate_steps(Shape(0.03, 0.003, 60.0, 0.005, 106.0), 0.01, 0.05):
        holds = [p for kind, p in c.steps if kind == "hold"]
        assert not ("without a hold" in c.why and holds), (c.name, c.why)
    cycles = next(c for c in candidate_steps(Shape(0.03, 0.003, 60.0, 0.005, 106.0), 0.01, 0.05)
                  if c.name == "load-unload cycles")
    assert "hold" in cycles.why and any(kind == "hold" for kind, _ in cycles.steps)


def test_design_on_the_what_is_missing_trials_warns_that_nothing_settles_the_tie(tmp_path):
    """The walk-through's trials (a second relaxation hidden): the verdict's look-alike cannot be
    separated within the rig's reach; --design says so, in its output and its file, and says how the
    verdict's own proposal (a longer hold) fared."""
    from rig.specs.protocol import load_protocol
    from tests.pages import ROOT

    (tmp_path / "hidden.yaml").write_text("sim: {effects: {relaxation2: {k_N_per_m: 60, tau_s: 40}}}\n")
    for v in ("0.75", "1.5", "3"):
        subprocess.run([sys.executable, "-m", "rig", "run", str(ROOT / "protocols" / f"paper-{v}mm_s.yaml"),
                        "--config", "hidden.yaml", "--speed", "0", "--quiet", "--out", "mystery"],
                       cwd=tmp_path, check=True, capture_output=True, timeout=300)
    logs = sorted(str(p) for p in (tmp_path / "mystery").glob("*.mcap"))
    done = subprocess.run([sys.executable, "-m", "rig", "analyze", *logs, "--explain", "--design",
                           "separate.yaml"], cwd=tmp_path, capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stderr
    verdict = next(line for line in done.stdout.splitlines() if line.startswith("=> "))
    assert "look-alike: fractional_relaxation" in verdict and "to separate them, try: a longer hold" in verdict
    shown = done.stdout[done.stdout.index("design: "):]
    assert "warning: no candidate settles the tie" in shown
    assert "the verdict's proposal, a longer hold, is 'long hold' here" in shown
    text = (tmp_path / "separate.yaml").read_text()
    assert text.startswith("# WARNING: no candidate settles the tie")
    proto = load_protocol(tmp_path / "separate.yaml")
    if any(s.kind == "hold" for s in proto.steps):
        assert "without a hold" not in (proto.description or "")


# --- the tutorials teach one path; the detail is on the explanation pages they link to ----------

# words of a reference or an explanation, not of a first walk through
_DETAIL = ("NL2SOL", "Jacobian", "Newton", "AR(p)", "structure function", "variable projection", "sandwich",
           "effective samples", "orthonormal", "banded", "solve_ivp")


@pytest.mark.parametrize(("tutorial", "explained"), [
    ("afm-curve.md", {"records.md": "NL2SOL", "elastic-contact.md": "## Against nanite",
                      "reading-a-fit.md": "## The noise and adequacy"}),
    ("model-comparison.md", {"reading-a-fit.md": "AR(p)", "models.md": "## The paper's negative damping"}),
])
def test_a_tutorial_is_one_path_and_links_to_its_detail(tutorial, explained):
    text = (DOCS / "tutorials" / tutorial).read_text()
    words = len(text.split())
    assert words < 1000, f"{tutorial}: {words} words; a tutorial is one path a newcomer follows"
    assert text.count("```console") == 1, f"{tutorial}: one command block, the path"
    found = [w for w in _DETAIL if w in text]
    assert not found, f"{tutorial} explains what belongs on an explanation page: {found}"
    for page, detail in explained.items():
        assert f"](../explanation/{page}" in text, f"{tutorial} does not link to {page}"
        assert detail in (DOCS / "explanation" / page).read_text(), (page, detail)
