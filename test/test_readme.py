"""The README and the docs against the code: size limits, generated tables, headline numbers, links, and the
`agentdress` command's help (the user's commands at the top, the experiment commands under `lab`)."""
from __future__ import annotations

import re
from pathlib import Path

import pytest

from agentdress_ros import cli, docs_tables

ROOT = Path(__file__).resolve().parents[1]
README = ROOT / "README.md"
USER_COMMANDS = {"run", "view", "demo", "demo-png", "bench", "eval", "build", "lab"}
LAB_COMMANDS = {"floor", "groundtruth-v3", "sequences", "settle", "regressor", "recurrent", "santesteban",
                "shape-residual", "shape-oracle", "overlap-split", "page-shots"}


def _between(text: str, table: str) -> str:
    begin, end = docs_tables.MARKERS[table]
    assert text.count(begin) == 1 and text.count(end) == 1, f"README must hold one pair of {table} markers"
    return text.split(begin)[1].split(end)[0].strip()


def test_readme_is_short():
    text = README.read_text()
    lines = text.split("\n")
    assert len(lines) <= 400, f"README.md has {len(lines)} lines (limit 400): move detail to docs/"
    assert len(text.encode()) <= 40_000, f"README.md is {len(text.encode())} bytes (limit 40,000)"
    long = [i + 1 for i, line in enumerate(lines) if len(line) > 200 and not line.startswith("|")]
    assert not long, f"README.md lines over 200 characters outside tables: {long}"


def test_parameter_table_matches_the_code():
    """Rewrite it with `python -m agentdress_ros.docs_tables parameters --write` after changing a parameter."""
    assert _between(README.read_text(), "parameters") == docs_tables.parameters_table()


def test_parameter_table_lists_every_parameter_once():
    from agentdress_ros.ros.params import PARAMETERS

    names = re.findall(r"^\| `([^`]+)` \|", docs_tables.parameters_table(), flags=re.M)
    assert names == list(PARAMETERS)


def test_parameter_table_renders_defaults_as_ros_types():
    """A double default keeps its decimal point (90.0, not 90: ROS parameters are typed), a bool is YAML's."""
    table = docs_tables.parameters_table()
    assert "| `rate_hz` | `90.0` |" in table
    assert "| `publish_body` | `false` |" in table
    assert "| `shape` | `[0.5, 0.6667, 0.5, 0.5, 0.5, 0.5]` |" in table


def test_replace_between_needs_both_markers():
    with pytest.raises(ValueError, match="expected one"):
        docs_tables.replace_between("no markers here", "<!-- a -->", "<!-- b -->", "x")
    assert docs_tables.replace_between("x\n<!-- a -->\nold\n<!-- b -->\ny", "<!-- a -->", "<!-- b -->", "new") == \
        "x\n<!-- a -->\nnew\n<!-- b -->\ny"


def test_headline_numbers_are_the_committed_measurements():
    """Each headline number is read from committed benchmark or evaluation JSON; rewrite the table with
    `python -m agentdress_ros.docs_tables headline --write` after committing a new measurement."""
    headline = _between(README.read_text(), "headline")
    assert headline == docs_tables.headline_table()
    rows = docs_tables.headline_rows()
    assert len(rows) <= 8
    for _, _, _, source in rows:
        for garment, _ in docs_tables.GARMENTS:
            assert (ROOT / source.replace("<garment>", garment)).is_file(), source


def test_headline_benchmarks_record_when_where_and_how():
    """Every benchmark file behind a headline row says its date, commit, command and configuration."""
    import json

    for path in sorted((ROOT / "docs" / "bench").glob("*.json")):
        record = json.loads(path.read_text())
        assert re.fullmatch(r"\d{4}-\d{2}-\d{2}", record["date"]), path.name
        assert re.fullmatch(r"[0-9a-f]{7,40}", record["commit"]), path.name
        assert record["command"].startswith("taskset -c 0 agentdress bench "), path.name
        assert record["configuration"] and "result" in record, path.name


def _links(path: Path):
    for target in re.findall(r"\]\(([^)#\s]+)(?:#[^)]*)?\)", path.read_text()):
        if not re.match(r"[a-z]+:", target):  # relative links only
            yield (path.parent / target).resolve()


def test_links_in_readme_and_docs_resolve():
    pages = [README, *sorted((ROOT / "docs").rglob("*.md"))]
    missing = sorted({str(t.relative_to(ROOT)) for page in pages for t in _links(page) if not t.exists()})
    # Written beside this change and linked from the README; every other target must exist.
    pending = {"docs/viewer.md", "docs/architecture.md"}
    assert set(missing) <= pending, f"broken links: {sorted(set(missing) - pending)}"


def test_every_old_readme_section_is_mapped():
    """docs/notes/README.md maps each part of the old README to a page or a dated note that exists."""
    index = (ROOT / "docs" / "notes" / "README.md").read_text()
    spans = [tuple(map(int, m)) for m in re.findall(r"^\| (\d+)-(\d+) \|", index, flags=re.M)]
    assert spans[0][0] == 1 and spans[-1][1] == 2480, "the map must cover the old README from its first line"
    assert all(a == b_prev + 1 for (_, b_prev), (a, _) in zip(spans, spans[1:])), "gaps or overlaps in the map"


def test_notes_are_dated_with_question_and_decision():
    notes = sorted(p for p in (ROOT / "docs" / "notes").glob("*.md") if p.name != "README.md")
    assert notes
    for note in notes:
        assert re.match(r"\d{4}-\d{2}-\d{2}-[a-z0-9-]+\.md$", note.name), note.name
        text = note.read_text()
        assert "- **Question:**" in text and "- **Decision:**" in text, note.name


def _help(capsys, argv) -> str:
    with pytest.raises(SystemExit) as exit_:
        cli.main(argv)
    assert exit_.value.code == 0
    return capsys.readouterr().out


def _listed_commands(text: str) -> dict[str, str]:
    """{command: its one-line summary} from argparse's subcommand list."""
    block = text.split("positional arguments:")[1].split("options:")[0]
    entries = re.findall(r"^    (\S+)(?:\s+(.*))?$", block, flags=re.M)
    return {name: summary or "" for name, summary in entries}


def test_top_help_lists_only_the_users_commands(capsys):
    listed = _listed_commands(_help(capsys, ["--help"]))
    assert set(listed) == USER_COMMANDS
    assert not set(listed) & LAB_COMMANDS


def test_lab_help_lists_the_experiment_commands(capsys):
    listed = _listed_commands(_help(capsys, ["lab", "--help"]))
    assert set(listed) == LAB_COMMANDS


def test_every_command_has_a_one_line_summary():
    for name, _, _, summary in (*cli.PASSTHROUGH, *cli.LAB_PASSTHROUGH):
        assert summary and "\n" not in summary and len(summary) <= 110, name


@pytest.mark.parametrize("name", sorted(LAB_COMMANDS))
def test_lab_commands_run_their_module(capsys, name):
    """`agentdress lab <name> --help` reaches the module's own parser, named as the user types it."""
    text = _help(capsys, ["lab", name, "--help"])
    assert text.startswith(f"usage: agentdress lab {name}")


def test_experiment_commands_are_not_top_level(capsys):
    with pytest.raises(SystemExit) as exit_:
        cli.main(["floor"])
    assert exit_.value.code == 2
    assert "invalid choice: 'floor'" in capsys.readouterr().err


def test_bench_help_names_every_benchmark(capsys):
    text = _help(capsys, ["bench", "--help"])
    for target in ("body", "synth", *cli.BENCH_PASSTHROUGH):
        assert target in text


def test_cold_start_refuses_a_missing_database(tmp_path):
    from agentdress_ros.evaluate.bench_cold_start import bench_cold_start

    with pytest.raises(FileNotFoundError, match="not found"):
        bench_cold_start(str(tmp_path / "none.h5"), "tshirt")
    with pytest.raises(ValueError, match="at least 2"):
        bench_cold_start(str(ROOT / "data" / "tshirt_default.h5"), "tshirt", repeats=1)


def test_cold_start_uses_the_node_defaults():
    from agentdress_ros.evaluate.bench_cold_start import node_engine_knobs

    assert node_engine_knobs("tshirt") == {"pose_model": "regressor", "fold": False, "projection": 8}
    assert node_engine_knobs("anything_else") == {"pose_model": "examples", "projection": 8}


def _resolve(reference: str):
    """agentdress_ros.<reference> as module[.attribute[.attribute]]; the offline package may still be named build."""
    import importlib

    parts = reference.split(".")
    for cut in range(len(parts), 0, -1):
        for package in ({parts[0], "build"} if parts[0] == "offline" else {parts[0]}):
            try:
                target = importlib.import_module(".".join(["agentdress_ros", package, *parts[1:cut]]))
            except ModuleNotFoundError:
                continue
            for name in parts[cut:]:
                target = getattr(target, name)
            return target
    raise ModuleNotFoundError(reference)


def test_engine_page_names_functions_that_exist():
    """Every `package.module.function` that docs/engine.md maps an equation to is in the code."""
    text = (ROOT / "docs" / "engine.md").read_text()
    table = text.split("## The runtime engine")[0]
    references = set(re.findall(r"`((?:engine|offline|body|kdsm)\.[A-Za-z_.]+)`", table))
    assert len(references) > 20
    for reference in sorted(references):
        assert _resolve(reference) is not None, reference
