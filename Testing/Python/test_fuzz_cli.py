"""The fuzz run of every ``fluo`` subcommand (``fuzz_cli.py``) under pytest.

``test_every_subcommand_is_fuzzed`` is fast: a subcommand added to the parser
without a base invocation in ``fuzz_cli.BASES`` fails it at once. The run
itself is slow (over a thousand cases: the hostile ones, and the commands that
make the fixtures, forked from one process that imported the stack and the
module files, each command's valid base as a real process; measured times are
in docs/reliability.md).
"""

import json
import os
import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).parent))
import fuzz_cli  # noqa: E402


def test_every_subcommand_is_fuzzed():
    missing = fuzz_cli.missing_bases()
    assert not missing, (f"subcommands without a base invocation in fuzz_cli.BASES: {missing}; "
                         "declare a valid, quick one so the fuzz covers them")
    stale = sorted(" ".join(p) for p in fuzz_cli.BASES if p not in fuzz_cli.command_options())
    assert not stale, f"BASES names commands the parser does not have: {stale}"
    cases = fuzz_cli.make_cases()
    assert len(cases) > 300
    # every option of every command gets hostile values
    for path, (_, opts) in fuzz_cli.command_options().items():
        fuzzed = {c.option for c in cases if c.command == path}
        assert {o for o, _ in opts} <= fuzzed, (path, {o for o, _ in opts} - fuzzed)


@pytest.mark.slow
def test_fuzz_every_subcommand(tmp_path):
    jobs = int(os.environ.get("FLUO_FUZZ_JOBS", "2"))
    cases = fuzz_cli.run(jobs=jobs, work=tmp_path)
    bad = [c for c in cases if not c.result.get("ok")]
    report = [{"command": c.command, "option": c.option, "value": c.value, **c.result}
              for c in cases]
    (tmp_path / "fuzz.json").write_text(json.dumps(report, indent=1))
    peak = max(c.result.get("peak_mb", 0) for c in cases)
    print(f"{len(cases) - len(bad)} of {len(cases)} clean; largest peak {peak} MB")
    assert not bad, "\n".join(fuzz_cli.describe(c) for c in bad[:40])
