"""The planted-bug table of bench/mutants.py still fits today's code (issue 37).

No mutant is run here (that is the script's job, about an hour): only the table is
checked, so that a search string that no longer matches, or matches twice, fails
the suite the day the code moves instead of silently dropping a planted bug.
"""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path

import pytest

pytestmark = pytest.mark.quick

REPO = Path(__file__).resolve().parents[1]


def _load():
    spec = importlib.util.spec_from_file_location("bench_mutants", REPO / "bench" / "mutants.py")
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module   # dataclasses looks the module up by name
    spec.loader.exec_module(module)
    return module


mutants = _load()


def test_every_search_string_matches_exactly_once_and_every_target_exists():
    assert mutants.table_problems(REPO) == {}


@pytest.mark.parametrize("m", mutants.MUTANTS, ids=lambda m: m.id)
def test_each_mutant_is_a_plausible_bug_not_a_syntax_error(m):
    path = REPO / m.file
    original = path.read_text(encoding="utf-8")
    mutated = original.replace(m.search, m.replace, 1)
    assert mutated != original
    compile(mutated, str(path), "exec")   # a planted bug must import: a SyntaxError would be "error", not a kill


def test_the_table_covers_every_area_of_the_issue_and_the_trust_issue_bugs():
    ids = [m.id for m in mutants.MUTANTS]
    assert len(ids) == len(set(ids)) >= 30
    packages = {m.package for m in mutants.MUTANTS}
    assert packages >= {"interlock", "signal checks", "command authorisation", "learning", "AFC", "history",
                        "dashboard", "physics", "drivers", "OPC UA"}
    trust = {m.file: m for m in mutants.MUTANTS if m.trust}
    assert set(trust) == {"daemon/publish/command_auth.py", "daemon/dashboard/server.py", "daemon/learning/monitor.py",
                          "daemon/runtime/runner.py", "daemon/runtime/interlock.py"}
    assert "compare_digest" in trust["daemon/publish/command_auth.py"].search
    assert "_host_refused" in trust["daemon/dashboard/server.py"].search
    assert '"overload"' in trust["daemon/learning/monitor.py"].search
    assert "afc.safe" in trust["daemon/runtime/runner.py"].search
    assert ">= self.crash_current_a" in trust["daemon/runtime/interlock.py"].search


def test_a_search_string_that_matches_twice_or_never_is_refused(tmp_path):
    (tmp_path / "a.py").write_text("x = 1\nx = 1\n")
    (tmp_path / "t.py").write_text("")
    twice = mutants.Mutant("twice", "p", "d", "a.py", "x = 1", "x = 2", ("t.py",))
    never = mutants.Mutant("never", "p", "d", "a.py", "y = 1", "y = 2", ("t.py",))
    once = mutants.Mutant("once", "p", "d", "a.py", "x = 1\nx = 1", "x = 1\nx = 2", ("t.py",))
    problems = mutants.table_problems(tmp_path, (twice, never, once))
    assert set(problems) == {"twice", "never"}
    assert "2 times" in problems["twice"] and "0 times" in problems["never"]
    with pytest.raises(ValueError):
        mutants.Planted(tmp_path, twice).__enter__()
    assert (tmp_path / "a.py").read_text() == "x = 1\nx = 1\n"


def test_a_failing_target_under_the_projects_pytest_options_is_a_kill_in_the_tables_order(tmp_path):
    """The script's own pytest run, under the project's options (pyproject's addopts: 4 xdist workers): a failing
    test is `killed`, the first of the targets in their order. Run in workers, `-x` ends the session "Interrupted"
    with exit code 2, which the script records as `error`, and the targets run in no set order: every kill of the
    table read as an error once the suite went parallel (issue 37)."""
    import subprocess

    first, second = tmp_path / "test_a.py", tmp_path / "test_b.py"
    first.write_text("def test_fails():\n    assert 1 == 2\n")
    second.write_text("def test_fails_too():\n    assert 1 == 3\n\n\ndef test_passes():\n    pass\n")
    p = subprocess.run([sys.executable, "-m", "pytest", *mutants.PYTEST_ARGS, "-c", str(REPO / "pyproject.toml"),
                        "--rootdir", str(tmp_path), str(second), str(first)], cwd=tmp_path, capture_output=True,
                       text=True, timeout=120)
    assert mutants.classify(p.returncode, p.stdout) == ("killed", "test_b.py::test_fails_too"), p.stdout[-2000:]
    assert "1 failed" in p.stdout and "passed" not in p.stdout.splitlines()[-1], p.stdout[-2000:]   # -x stopped there
