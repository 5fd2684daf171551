"""The README is a front door: short, and every link in it and in docs/ resolves."""

import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
LINK = re.compile(r"\]\(([^)\s]+)\)")
PAGES = [ROOT / "README.md", *sorted((ROOT / "docs").rglob("*.md"))]


def _relative_links(page: Path):
    text = page.read_text()
    text = re.sub(r"```.*?```", "", text, flags=re.S)  # code blocks are not links
    for target in LINK.findall(text):
        if re.match(r"[a-z]+:", target) or target.startswith("#"):
            continue  # http(s), mailto, anchors
        yield target.split("#")[0]


def test_readme_is_short():
    lines = (ROOT / "README.md").read_text().count("\n")
    assert lines < 300, f"README.md has {lines} lines; detail belongs in docs/"


@pytest.mark.parametrize("page", PAGES, ids=[str(p.relative_to(ROOT)) for p in PAGES])
def test_every_relative_link_resolves(page):
    missing = [t for t in _relative_links(page) if not (page.parent / t).exists()]
    assert not missing, f"{page.relative_to(ROOT)} links to missing files: {missing}"


def test_the_checker_finds_a_broken_link(tmp_path):
    page = tmp_path / "page.md"
    page.write_text(
        "[ok](page.md) [broken](nowhere.md) [web](https://drake.mit.edu)\n"
        "```\n[in code](not_a_link.md)\n```\n"
    )
    assert [t for t in _relative_links(page) if not (page.parent / t).exists()] == ["nowhere.md"]


def test_readme_states_the_bad_input_corpus_count():
    """The README's corpus count is the number of cases pytest collects from the corpus."""
    import subprocess
    import sys

    m = re.search(r"holds (\d+) cases", (ROOT / "README.md").read_text())
    assert m, "README.md should state the bad-input corpus count ('holds N cases')"
    files = sorted(str(p) for p in (ROOT / "tests").glob("test_bad_input_*.py"))
    out = subprocess.run(
        [sys.executable, "-m", "pytest", "--collect-only", "-q", "-p", "no:cacheprovider", *files],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=300,
    ).stdout
    collected = re.search(r"(\d+) tests? collected", out)
    assert collected, out[-2000:]
    assert int(m.group(1)) == int(collected.group(1)), (
        f"README says {m.group(1)} bad-input cases, pytest collects {collected.group(1)}"
    )


def test_no_command_writes_where_make_demo_does_by_default():
    """`make demo` writes its scan to runs/demo; a command run afterwards with its default
    output folder must not overwrite that scan's summary.json."""
    from drake_rus.cli import build_parser

    make_demo_out = re.search(r"scan --patient \S+ --out (\S+)", (ROOT / "Makefile").read_text())
    assert make_demo_out, "the Makefile's demo target no longer names its output folder"
    parser = build_parser()
    subparsers = next(a for a in parser._actions if a.dest == "command")
    clashes = [
        name
        for name, sub in subparsers.choices.items()
        for action in sub._actions
        if action.dest == "out" and action.default == make_demo_out.group(1)
    ]
    assert not clashes, (
        f"default --out {make_demo_out.group(1)} of {clashes} clashes with make demo"
    )


def test_the_control_docs_state_the_configured_force_filter_cutoff():
    """docs/control.md and docs/design.md name the force low-pass the controller runs."""
    from drake_rus.control.config import ControllerConfig

    cutoff = ControllerConfig().force_filter_cutoff_hz
    for page, pattern in (
        ("control.md", r"force PD on the ([\d.]+) Hz low-passed"),
        ("design.md", r"eq\. 6 on the ([\d.]+) Hz low-passed"),
    ):
        m = re.search(pattern, (ROOT / "docs" / page).read_text())
        assert m, f"docs/{page} should state the force filter's cut-off"
        assert float(m.group(1)) == cutoff, f"docs/{page}: {m.group(1)} Hz, config {cutoff} Hz"


def test_the_exploration_length_is_not_described_as_l_m_alone():
    """EXPLORE ends after ER x the estimated kidney length by default
    (``controller.exploration_length: estimated``), not ER x L_m: a page that names the
    rule says so."""
    from drake_rus.control.config import ControllerConfig

    assert ControllerConfig().exploration_length == "estimated"
    for page in ("control.md", "design.md"):
        text = (ROOT / "docs" / page).read_text()
        assert "ER x L_m" not in text, f"docs/{page} says EXPLORE ends after ER x L_m"
