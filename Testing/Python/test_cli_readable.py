"""The ``fluo`` command for people: help on every option, readable text without
``--json``, progress on stderr, ``fluo demo --only`` that knows its stages."""

import argparse
import json
import os
import re
import subprocess
import sys

import numpy as np

import pytest

from fluoapp.cli import build_parser, main
from fluoapp.demo.run import STAGE_NAMES, run_demo, stages_to_run
from small_cases import SMALL_TUBE
from fluoapp.format import CELL_WIDTH, LINE_WIDTH, format_result, has_unit
from fluoguide.errors import FluoInputError
from fluoguide.progress import TqdmProgress, mark_command_start, scaled


# ------------------------------------------------------------------ help

def _options(parser, path=("fluo",)):
    """(command path, action, expanded help) of every option in the parser tree,
    and (path, missing help) of every subcommand without one."""
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            helps = {c.dest: c.help for c in action._choices_actions}
            for name, sub in action.choices.items():
                yield (*path, name), None, helps.get(name)
                yield from _options(sub, (*path, name))
        elif not isinstance(action, (argparse._HelpAction, argparse._VersionAction)):
            text = parser._get_formatter()._expand_help(action) if action.help else ""
            yield path, action, text


def test_every_option_has_a_sentence_and_its_default():
    # walks whatever is in the parser, so subcommands added later are held to it too
    problems = []
    commands = 0
    for path, action, text in _options(build_parser()):
        where = " ".join(path)
        if action is None:
            commands += 1
            if not text:
                problems.append(f"{where}: subcommand without help")
            continue
        name = "/".join(action.option_strings) or action.dest
        if len(text.split()) < 2:
            problems.append(f"{where} {name}: no help sentence")
            continue
        flag = isinstance(action, (argparse._StoreTrueAction, argparse._StoreFalseAction,
                                   argparse._StoreConstAction, argparse._CountAction))
        if flag or action.required or not action.option_strings:
            continue
        if action.default is not None and str(action.default) not in text:
            problems.append(f"{where} {name}: default {action.default!r} not stated")
        elif action.default is None and "default" not in text.lower():
            problems.append(f"{where} {name}: what happens without it not stated")
    assert commands > 20
    assert not problems, "\n".join(problems)


def test_the_walk_sees_a_bad_option():
    # the walk must fail on an option without help: a parser built to have one
    parser = argparse.ArgumentParser(prog="fluo")
    sub = parser.add_subparsers()
    p = sub.add_parser("x", help="a command")
    p.add_argument("--size", type=float, default=1.6)
    found = [(path, a) for path, a, text in _options(parser) if a is not None and not text]
    assert [a.dest for _, a in found] == ["size"]


def _parsers(parser, path=("fluo",)):
    """(command path, parser) of the parser and every subcommand under it."""
    yield path, parser
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for name, sub in action.choices.items():
                yield from _parsers(sub, (*path, name))


# a year, a date, "measured on" / "measured:" and a machine: numbers of one run on
# one machine, which belong in docs/ next to the command that measures them
DATED = re.compile(r"\b20\d\d\b|measured( on|:)|\d-core machine", re.IGNORECASE)


def test_no_help_prints_dated_measurements(monkeypatch):
    monkeypatch.setenv("COLUMNS", "1000")     # one line per paragraph: no match split
    found = [f"{' '.join(path)}: ...{m.group(0)}..." for path, p in _parsers(build_parser())
             for m in re.finditer(r".{0,40}(" + DATED.pattern + r").{0,40}", p.format_help(),
                                  re.IGNORECASE)]
    assert len(list(_parsers(build_parser()))) > 30
    assert not found, "\n".join(found)


def test_the_dated_pattern_finds_a_measurement():
    # the pattern above must catch the forms that were printed before
    for text in ("HP 88 s on a shared 2-core machine", "run of 2026-11-24",
                 "Measured on the issue's ellipsoid scene", "(measured: HP +0.2 %)"):
        assert DATED.search(text), text
    for text in ("20000 photons per run", "beyond the measured range", "default 100000"):
        assert not DATED.search(text), text


def test_demo_help_lists_the_stages():
    text = build_parser()._subparsers._group_actions[0].choices["demo"].format_help()
    for name in STAGE_NAMES:
        assert name in text.replace("\n", " ").replace("- ", "")


# ------------------------------------------------------------------ readable results

NUMBER = re.compile(r"^-?\d+(\.\d+)?(e[+-]\d+)?$")


def _check_readable(text):
    """Every number has at most 4 significant digits and a unit in its key (or in the
    key of the block it sits in); no JSON."""
    assert not text.lstrip().startswith("{")
    parents = []
    for line in text.splitlines():
        depth = (len(line) - len(line.lstrip())) // 2
        body = line.strip()
        parents = parents[:depth]
        if re.match(r"^[^:]+:$", body):
            parents.append(body[:-1])
            continue
        key, sep, value = body.partition(": ")
        if not sep:
            continue
        for v in value.strip("[]").split(", "):
            if NUMBER.match(v) and ("." in v or "e" in v):
                digits = v.lstrip("-").split("e")[0].replace(".", "").lstrip("0")
                assert len(digits) <= 4, line
                assert any(has_unit(k) for k in [key.strip(), *parents]), f"no unit: {line}"


def test_analytic_prints_lines_with_units(capsys):
    assert main(["analytic", "--mua", "0.016", "--musp", "0.89", "--rho", "3,10",
                 "--yield", "0.00052", "--mua-m", "0.0068", "--musp-m", "0.81"]) == 0
    text = capsys.readouterr().out
    _check_readable(text)
    assert "R_rho" not in text and "reflectance_per_mm2" in text
    from FluoTomoLib.analytic import total_diffuse_reflectance

    rd = float(total_diffuse_reflectance(0.016, 0.89, 1.33))
    assert f"diffuse_reflectance_Rd (dimensionless): {rd:.4g}" in text
    # rho, R(rho), the exact surface fluence, its log and the diffusive flag side by
    # side: one row per distance
    rows = [ln.split() for ln in text.splitlines() if ln.startswith(("3 ", "10 "))]
    assert [r[0] for r in rows] == ["3", "10"] and all(len(r) == 5 for r in rows)
    assert [r[-1] for r in rows] == ["no", "yes"]     # 3 mm is within 4 MFP' (4.4 mm)


def test_json_is_unchanged_by_the_text_form(capsys):
    args = ["analytic", "--mua", "0.016", "--musp", "0.89", "--rho", "3,10"]
    assert main(args + ["--json"]) == 0
    doc = json.loads(capsys.readouterr().out)
    assert set(doc) == {"mua_per_mm", "musp_per_mm", "n", "Rd", "mueff",
                        "penetration_depth_mm", "D", "A", "rho_mm", "R_rho",
                        "robin_surface_fluence", "ln_robin_surface_fluence", "rho_diffusive",
                        "diffusion_valid", "warnings"}
    from FluoTomoLib.analytic import spatially_resolved_reflectance

    # the numbers are the library's, to the last digit (the text form rounds, JSON never)
    expected = spatially_resolved_reflectance(np.array([3.0, 10.0]), 0.016, 0.89, 1.33)
    assert doc["R_rho"] == pytest.approx(expected.tolist(), rel=1e-15)


def test_long_commands_report_their_peak_memory(capsys, tmp_path):
    """A long command's result says the process's peak resident memory (what a
    laptop user sizes the next run by); a quick one's result is unchanged."""
    from fluoapp.cli import MEMORY_REPORTED
    from fluoguide.memory import peak_resident_bytes

    assert "tomo" in MEMORY_REPORTED and "demo" in MEMORY_REPORTED
    assert main(["phantom", "slab", "--voxel-mm", "1.0", "--out", str(tmp_path / "p"),
                 "--json"]) == 0
    doc = json.loads(capsys.readouterr().out)
    assert 0.05 < doc["peak_memory_gb"] <= peak_resident_bytes() / 1e9 + 0.01
    assert main(["analytic", "--mua", "0.016", "--musp", "0.89", "--json"]) == 0
    assert "peak_memory_gb" not in json.loads(capsys.readouterr().out)


def test_rows_become_tables_and_long_data_a_summary():
    result = {
        "rows": [{"case": "A: 2.5 mm disc", "method": m, "lambda": 10.0, "peak": p,
                  "peak_error_pct": e} for m, p, e in (("NP", 3.8e-4, -68.04321),
                                                       ("SP", 8.1e-4, -32.0),
                                                       ("HP", 1.19e-3, -0.5))],
        "detector_fluence": [[0.001 * (i + j + 1) for j in range(16)] for i in range(16)],
        "seconds": 12.345678,
    }
    text = format_result(result)
    _check_readable(text)
    lines = text.splitlines()
    # lambda is the same in every row: printed once, above the table
    assert sum("lambda" in ln for ln in lines) == 1
    header = next(ln for ln in lines if "method" in ln)
    assert "peak_per_mm" in header and "peak_error_pct" in header
    assert any(ln.split()[:2] == ["NP", "0.00038"] for ln in lines)
    assert "-68.04" in text and "-68.043" not in text
    assert "16 x 16 values" in text and "--json" in text
    assert max(len(ln) for ln in lines) < 120


def test_warnings_are_always_printed_last():
    text = format_result({"peak_per_mm": 1e-3, "warnings": ["mesh coarse for mueff"],
                          "seconds": 1.0})
    assert text.splitlines()[-1] == "warning: mesh coarse for mueff"
    assert format_result({"warnings": []}).splitlines()[-1] == "warnings: none"


def test_no_printed_line_is_longer_than_the_limit():
    """A long value (a path without spaces, a long message), a wide table and a
    long cell: every line within LINE_WIDTH, nothing lost but the cut cell."""
    path = "/data/" + "a_very_long_folder_name_" * 20 + "labels.nrrd"
    message = "the region of interest was cut below the target " * 8
    rows = [{"case": f"case {i}", **{f"quantity_{j}_mm": 1000.5 * j + i for j in range(30)},
             "stop_reason": f"{i} " + "x" * 300} for i in range(35)]
    text = format_result({"labels": path, "rows": rows, "warnings": [message.strip()]})
    lines = text.splitlines()
    assert max(len(ln) for ln in lines) <= LINE_WIDTH, max(lines, key=len)
    # the long values continue on indented lines, every character kept
    at = next(i for i, ln in enumerate(lines) if ln.startswith("labels:"))
    assert path in lines[at].split()[-1] + "".join(ln.strip() for ln in lines[at + 1:at + 3])
    assert " ".join(message.split()) in " ".join(text.split())
    # the wide table in parts, each opening with the row's name; every column printed
    assert sum(ln.lstrip().startswith("case 7 ") for ln in lines) >= 2
    assert all(f"quantity_{j}_mm" in text for j in range(30))
    # a cell too long for a table is cut, and says so
    cut = [c for ln in lines for c in ln.split() if c.startswith("xxx")]
    assert cut and all(c.endswith("...") and len(c) < CELL_WIDTH for c in cut)


def test_study_table_reads_on_a_terminal():
    rows = [{"case": f"B: 6 mm disc, top {t} mm", "method": m, "lambda": 10.0,
             "true_peak": 0.0012, "peak": 0.0012, "peak_error_pct": 1.0,
             "true_centroid_mm": t + 3, "centroid_mm": t + 3, "centroid_error_pct": 0.0,
             "seconds": 0.5, "iterations": 11, "residual_ss": 0.01,
             "stop_reason": "residual change < 2%"}
            for t in (2.5, 3.5, 4.5, 5.5, 6.5) for m in ("NP", "SP", "HP")]
    text = format_result({"study": "B", "rows": rows, "forward_mesh": [6161, 12000]}, "study")
    _check_readable(text)
    assert max(len(ln) for ln in text.splitlines()) < 100
    assert text.count("B: 6 mm disc, top 4.5 mm") == 1


# ------------------------------------------------------------------ progress

def test_progress_lines_only_after_a_while(capsys):
    mark_command_start()                         # a command that starts now
    quick = TqdmProgress("x", after_s=60.0)
    quick(0.5, "step")
    quick.close()
    assert capsys.readouterr().err == ""         # stderr is not a terminal under pytest
    slow = TqdmProgress("fluo demo", after_s=0.0)
    part = scaled(slow, 0.5, 1.0, "tomography")
    part(0.0, "case 1 of 3")
    part(0.5, "case 2 of 3")
    slow.close()
    err = capsys.readouterr().err.splitlines()
    assert err[0].startswith("fluo demo:  50% tomography: case 1 of 3 (")
    assert err[1].startswith("fluo demo:  75% tomography: case 2 of 3 (")


def test_long_command_reports_progress_on_stderr_and_json_on_stdout(tmp_path):
    # synth-boards renders one board view after another (20 s with its defaults);
    # two small views here, with progress lines from the first call on
    env = {**os.environ, "FLUO_PROGRESS_AFTER_S": "0"}
    r = subprocess.run([sys.executable, "-m", "fluoapp", "calib", "synth-boards", "--out",
                        str(tmp_path / "b"), "--views", "2", "--width", "160", "--height", "120",
                        "--json"], capture_output=True, text=True, timeout=300, env=env)
    assert r.returncode == 0, r.stderr
    assert len(json.loads(r.stdout)["images"]) == 2      # stdout: one JSON object, nothing else
    progress = [ln for ln in r.stderr.splitlines() if ln.startswith("calib synth-boards: ")]
    steps = [ln.split("% ")[1].split(" (")[0] for ln in progress]
    # the sample rays first (in parts, issue #33: a report at least every 2 s), then
    # one line per view
    assert steps[0].startswith("sample rays, part 1 of ")
    assert [t for t in steps if t.startswith("rendering")][:2] == ["rendering view 1/2",
                                                                   "rendering view 2/2"]


# ------------------------------------------------------------------ demo --only

def test_only_runs_the_stages_a_stage_needs():
    assert stages_to_run(["tomography"]) == ["phantoms", "tomography"]
    assert stages_to_run(["oral_tomography", "surface_mapping"]) == [
        "phantoms", "surface_mapping", "oral_tomography"]
    assert stages_to_run(None) == STAGE_NAMES
    with pytest.raises(FluoInputError, match="unknown stage"):
        stages_to_run(["tomo"])


def test_only_with_an_unknown_stage_is_refused_before_anything_is_written(tmp_path, capsys):
    out = tmp_path / "demo"
    assert main(["demo", "--out", str(out), "--only", "tomo"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--only" in err[0] and "tomo" in err[0] and "tomography" in err[0]
    assert not out.exists()
    assert main(["demo", "--out", str(out), "--only", ","]) == 2


@pytest.mark.slow
def test_only_tomography(tmp_path):
    # failed with KeyError 'tube_phantoms' before the stages knew their needs; the
    # tube cases at the coarser settings of test_demo_cases.py (the quick demo's
    # own run in test_demo.py grades the tomography at its real resolution)
    metrics = run_demo(tmp_path / "out", quick=True, only=["tomography"],
                       case_options=SMALL_TUBE)
    assert metrics["stages_completed"] == ["phantoms", "tomography"]
    assert metrics["tomography"]["HP mean |yield error| %"] < 20
    with pytest.raises(FluoInputError, match="unknown case option"):
        run_demo(tmp_path / "bad", quick=True, only=["tomography"], case_options={"fine": 1})
    assert not (tmp_path / "bad").exists()
