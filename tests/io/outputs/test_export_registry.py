"""The exporter registry: the command, the docs and the README list exactly its formats, and a
format is a writer module plus one registry line."""

from __future__ import annotations

import re
from pathlib import Path
from types import SimpleNamespace

import pytest
from conftest import ROOT, write_gt_run

from pipeline.app.cli import build_parser, main
from pipeline.extras import EXTRA_OF_MODULE
from pipeline.io.outputs.exports import EXPORTERS
from pipeline.io.outputs.exports.job import ExportJob
from pipeline.io.outputs.run_folder import RunFolder

DOCS_TABLE_HEADER = "| format | written to (in the run folder) | what it is | needs |"
README_FORMATS = "Export formats (`--to`): "


def _expected_rows() -> list[str]:
    """docs/exports.md's table rows, as the registry has them."""
    rows = []
    for name, exporter in EXPORTERS.items():
        needs = f"the `{EXTRA_OF_MODULE[exporter.NEEDS]}` extra" if exporter.NEEDS else "-"
        rows.append(f"| `{name}` | `{exporter.DEFAULT_NAME}` | {exporter.FOR} | {needs} |")
    return rows


def test_the_docs_table_of_formats_is_the_registry() -> None:
    lines = (ROOT / "docs" / "exports.md").read_text().splitlines()
    start = lines.index(DOCS_TABLE_HEADER) + 2  # past the header and its rule
    end = next(i for i in range(start, len(lines)) if not lines[i].startswith("|"))
    expected = _expected_rows()
    assert lines[start:end] == expected, "docs/exports.md's table should read:\n" + "\n".join(expected)


def test_the_readme_lists_the_registrys_formats() -> None:
    (line,) = [line for line in (ROOT / "README.md").read_text().splitlines() if line.startswith(README_FORMATS)]
    assert re.findall(r"`([^`]+)`", line.removeprefix(README_FORMATS)) == list(EXPORTERS)


def test_the_export_commands_choices_and_help_are_the_registrys(
    capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setenv("COLUMNS", "10000")  # one line per option: argparse wraps at hyphens too
    parser = build_parser()
    with pytest.raises(SystemExit):
        parser.parse_args(["export", "--help"])
    help_text = capsys.readouterr().out
    for name, exporter in EXPORTERS.items():
        assert f"{name}: {exporter.FOR}" in help_text
    with pytest.raises(SystemExit):
        parser.parse_args(["export", "run", "--to", "no-such-format"])
    refused = capsys.readouterr().err
    assert all(repr(name) in refused for name in EXPORTERS)


def test_a_writer_module_and_one_registry_line_make_a_format(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    """What a contributor adds for a new format, and nothing else: the command takes it, writes
    it where the run folder keeps it and records it in exports.json."""
    run = write_gt_run(tmp_path)

    def export(job: ExportJob) -> str:
        job.target.write_text(f"{len(job.checkpoint.gaussians)} Gaussians\n")
        return "a count"

    writer = SimpleNamespace(DEFAULT_NAME="map.count", FOR="a test's format", NEEDS=None, export=export)
    monkeypatch.setitem(EXPORTERS, "count", writer)  # type: ignore[arg-type]
    assert main(["export", str(run), "--to", "count"]) == 0
    gaussians = len(RunFolder(run).read_checkpoint()[0].gaussians)
    assert (run / "map.count").read_text() == f"{gaussians} Gaussians\n"
    assert capsys.readouterr().out.strip() == f"wrote {run / 'map.count'}: a count"
    assert RunFolder(run).exports_made()["count"]["path"] == "map.count"
