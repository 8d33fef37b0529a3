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
                          "daemon/pipeline/runner.py", "daemon/pipeline/interlock.py"}
    assert "compare_digest" in trust["daemon/publish/command_auth.py"].search
    assert "_host_refused" in trust["daemon/dashboard/server.py"].search
    assert '"overload"' in trust["daemon/learning/monitor.py"].search
    assert "_afc_safe" in trust["daemon/pipeline/runner.py"].search
    assert ">= self.crash_current_a" in trust["daemon/pipeline/interlock.py"].search


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
