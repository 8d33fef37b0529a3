"""The layering, locked statically (issue 38): who may import whom, read from every import in the source.

Every import counts, wherever it is written: at module level, inside a function, under `TYPE_CHECKING`,
relative ones resolved, `importlib.import_module("...")`, and a module named in a lazy-import table
(`"millsense.drivers.tcp_driver:TcpDriver"`, the dotted name of a module file as in `cli.COMMANDS`; a
package's bare name is a resource root, `resources.files`, not an import). Each folder of `daemon/` is one
node, and so is each top-level module of `daemon/`; `drivers` and `sim` are one node each.

The floors, bottom to top, are docs/architecture.md's "Layers".
"""

from __future__ import annotations

import ast
import functools
import re
import tomllib

import pytest

from tests.conftest import REPO

pytestmark = pytest.mark.quick

MAX_LINES = 800
# The shared top-level modules of daemon/: what several floors use, below learning, history and pipeline.
SHARED = ("events", "guarded", "state_dir", "local_socket", "controls", "status_text")
SHARED_NODES = {f"daemon.{m}" for m in SHARED}
BELOW_LEARNING = {"daemon.physics", *SHARED_NODES}

# (importing file, imported module or its prefix) -> why it is allowed for good.
EXEMPT = {
    ("drivers/sim_driver.py", "millsense.sim"):
        "the in-process simulated driver (daq.transport = \"sim\") runs the plant and the emulated DAQ itself",
}
# PENDING: exemptions that a change in flight satisfies once it lands (the lead empties it at merge; an entry
# that no import needs any more fails, so none is left behind).
PENDING: dict[tuple[str, str], str] = {}
PENDING_LONG: dict[str, str] = {}


def _daemon(t: str) -> bool:
    return t == "daemon" or t.startswith("daemon.")


def _package(t: str) -> bool:
    return t.startswith("daemon.") and (REPO / t.replace(".", "/")).is_dir()


# (rule, applies to the importing node, forbids the imported node)
RULES = (
    ("drivers never import the daemon or the simulator", lambda s: s == "drivers", lambda t: _daemon(t) or t == "sim"),
    ("the simulator never imports the daemon", lambda s: s == "sim", _daemon),
    ("physics imports nothing of the daemon", lambda s: s == "daemon.physics", _daemon),
    ("learning imports only physics and the shared modules " + ", ".join(SHARED),
     lambda s: s == "daemon.learning", lambda t: _daemon(t) and t not in BELOW_LEARNING),
    ("a shared module imports no package of the daemon", lambda s: s in SHARED_NODES, _package),
    ("history imports no pipeline, runtime, afc or commands", lambda s: s == "daemon.history",
     lambda t: t in ("daemon.pipeline", "daemon.runtime", "daemon.afc", "daemon.commands")),
    ("pipeline imports no runtime, publish, afc or commands", lambda s: s == "daemon.pipeline",
     lambda t: t in ("daemon.runtime", "daemon.publish", "daemon.afc", "daemon.commands")),
    ("publish imports no runtime", lambda s: s == "daemon.publish", lambda t: t == "daemon.runtime"),
)


def _modules() -> dict[str, str]:
    """Dotted module name -> its file, relative to the repository, for every package of pyproject.toml."""
    with open(REPO / "pyproject.toml", "rb") as fh:
        dirs = tomllib.load(fh)["tool"]["setuptools"]["package-dir"]
    found = {}
    for package, folder in dirs.items():
        for path in sorted((REPO / folder).rglob("*.py")):
            parts = [p for p in path.relative_to(REPO / folder).with_suffix("").parts if p != "__init__"]
            found[".".join([package, *parts])] = path.relative_to(REPO).as_posix()
    return found


def node(module: str) -> str:
    parts = module.split(".")
    return parts[1] if parts[1] != "daemon" else ".".join(parts[1:3])


def imports_of(module: str, path: str, source: str, known: dict[str, str]) -> set[tuple[int, str, str]]:
    """(line, imported module, the import as written) for every import in `source`."""
    found = set()
    package = module if path.endswith("__init__.py") else module.rpartition(".")[0]
    for n in ast.walk(ast.parse(source)):
        if isinstance(n, ast.Import):
            found |= {(n.lineno, a.name) for a in n.names}
        elif isinstance(n, ast.ImportFrom):
            base = n.module or ""
            if n.level:   # relative: from the importing module's package, one level up per extra dot
                base = ".".join([*package.split(".")[:len(package.split(".")) - n.level + 1], *filter(None, [n.module])])
            found |= {(n.lineno, f"{base}.{a.name}" if f"{base}.{a.name}" in known else base) for a in n.names}
        elif (isinstance(n, ast.Call) and n.args and isinstance(n.args[0], ast.Constant)
              and getattr(n.func, "attr", getattr(n.func, "id", None)) in ("import_module", "__import__")):
            found.add((n.lineno, str(n.args[0].value)))
        elif isinstance(n, ast.Constant) and isinstance(n.value, str) and n.value.startswith("millsense."):
            m = re.fullmatch(r"(millsense(?:\.\w+)+)(:\w+)?", n.value)
            if m and m[1] in known and (m[2] or not known[m[1]].endswith("__init__.py")):
                found.add((n.lineno, m[1]))
    lines = source.splitlines()
    return {(line, target, lines[line - 1].strip()) for line, target in found if target.startswith("millsense.")}


@functools.cache
def _edges() -> tuple[tuple[str, int, str, str, str], ...]:
    """(file, line, importing node, imported module, the import as written), between different nodes."""
    known = _modules()
    out = []
    for module, path in known.items():
        for line, target, text in imports_of(module, path, (REPO / path).read_text(encoding="utf-8"), known):
            if node(target) != node(module):
                out.append((path, line, node(module), target, text))
    return tuple(sorted(out))


def _allowed(path: str, target: str, table: dict) -> bool:
    return any(path == f and (target == t or target.startswith(t + ".")) for f, t in table)


def test_no_import_breaks_a_floor():
    broken = [f"{path}:{line}: `{text}`: {rule}"
              for path, line, src, target, text in _edges()
              if not _allowed(path, target, EXEMPT) and not _allowed(path, target, PENDING)
              for rule, applies, forbids in RULES if applies(src) and forbids(node(target))]
    assert not broken, "imports across the layers (docs/architecture.md, Layers):\n" + "\n".join(broken)


def test_no_import_loop_between_the_daemons_packages():
    edges = [e for e in _edges() if _daemon(e[2]) and _daemon(node(e[3]))
             and not _allowed(e[0], e[3], EXEMPT) and not _allowed(e[0], e[3], PENDING)]
    graph: dict[str, set[str]] = {}
    for _, _, src, target, _ in edges:
        graph.setdefault(src, set()).add(node(target))

    def reach(start: str) -> set[str]:
        seen, todo = set(), [start]
        while todo:
            for nxt in graph.get(todo.pop(), ()):
                if nxt not in seen:
                    seen.add(nxt)
                    todo.append(nxt)
        return seen

    reached = {n: reach(n) for n in graph}
    looped = [f"{path}:{line}: `{text}` ({src} -> {node(target)})" for path, line, src, target, text in edges
              if src in reached.get(node(target), ())]
    assert not looped, "imports that close a loop between the daemon's packages:\n" + "\n".join(looped)


def test_no_module_over_the_line_limit():
    long = [f"{path}: {n} lines" for path in _modules().values() if path not in PENDING_LONG
            and (n := len((REPO / path).read_text(encoding="utf-8").splitlines())) > MAX_LINES]
    assert not long, f"modules over {MAX_LINES} lines (split them along their seams):\n" + "\n".join(long)


def test_every_exemption_is_still_needed():
    edges = _edges()
    stale = [f"{f} -> {t}: {why}" for table in (EXEMPT, PENDING) for (f, t), why in table.items()
             if not any(_allowed(path, target, {(f, t): why}) for path, _, _, target, _ in edges)]
    stale += [f"{f} (long): {why}" for f, why in PENDING_LONG.items() if not (REPO / f).is_file()
              or len((REPO / f).read_text(encoding="utf-8").splitlines()) <= MAX_LINES]
    assert not stale, "exemptions nothing needs any more (remove them):\n" + "\n".join(stale)


def test_the_reader_sees_every_kind_of_import():
    """The reader itself: an import the rules never see would let a floor break unnoticed."""
    known = {"millsense.daemon.pipeline": "daemon/pipeline/__init__.py",
             "millsense.daemon.pipeline.alarms": "daemon/pipeline/alarms.py",
             "millsense.daemon.learning.monitor": "daemon/learning/monitor.py",
             "millsense.drivers.tcp_driver": "drivers/tcp_driver.py",
             "millsense.daemon": "daemon/__init__.py"}
    source = (
        "import millsense.daemon.events\n"
        "from typing import TYPE_CHECKING\n"
        "if TYPE_CHECKING:\n"
        "    from millsense.daemon.runtime.runner import Runner\n"
        "def later():\n"
        "    from ..pipeline import alarms\n"
        "    from . import monitor\n"
        "    importlib.import_module('millsense.daemon.afc.controller')\n"
        "TABLE = {'tcp': 'millsense.drivers.tcp_driver:TcpDriver', 'res': 'millsense.daemon'}\n")
    found = {(line, target) for line, target, _ in
             imports_of("millsense.daemon.learning.monitor", "daemon/learning/monitor.py", source, known)}
    assert found == {(1, "millsense.daemon.events"), (4, "millsense.daemon.runtime.runner"),
                     (6, "millsense.daemon.pipeline.alarms"), (7, "millsense.daemon.learning.monitor"),
                     (8, "millsense.daemon.afc.controller"), (9, "millsense.drivers.tcp_driver")}
