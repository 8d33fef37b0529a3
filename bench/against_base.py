"""Any bench of this folder run on this checkout and on a git revision, turn about, in the same minutes.

A refactor (issue 38: the house's rooms) must not slow the live path, and the box's speed drifts from one
hour to the next, so the bench runs on both codes alternately: base, this checkout, base, this checkout...
The base revision is checked out whole (its own bench/ and tests/, so each side measures with its own
helpers) into a temporary git worktree, and its `daemon/`, `drivers/` (and `sim/`, if it has one) are laid
out as the package `millsense` first on `PYTHONPATH`: every process the bench starts (`python -m
millsense.daemon`, the emulator) runs the base's code with this venv's libraries. Each side's output is
printed whole under its label; lines matching `--grep` are gathered side by side at the end.

Run: .venv/bin/python bench/against_base.py --base REV [--rounds 2] [--grep REGEX] -- bench/crash_latency.py --trips 200
"""

from __future__ import annotations

import argparse
import os
import re
import subprocess
import sys
import tempfile
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
PACKAGES = ("daemon", "drivers", "sim")  # the folders setuptools' package-dir maps under `millsense`


def checkout(rev: str, into: Path) -> Path:
    tree = into / "base"
    subprocess.run(["git", "-C", str(REPO), "worktree", "add", "--detach", "-q", str(tree), rev], check=True)
    return tree


def package_dir(tree: Path, into: Path) -> Path:
    pkg = into / "pkg"
    (pkg / "millsense").mkdir(parents=True)
    for sub in PACKAGES:
        if (tree / sub / "__init__.py").exists():
            (pkg / "millsense" / sub).symlink_to(tree / sub, target_is_directory=True)
    return pkg


def loaded_from(env: dict[str, str]) -> str:
    return subprocess.run([sys.executable, "-c", "import millsense.daemon as d; print(d.__file__)"], check=True,
                          capture_output=True, text=True, env=env).stdout.strip()


def run_side(label: str, tree: Path, env: dict[str, str], bench: list[str]) -> str:
    script = tree / bench[0]
    proc = subprocess.run([sys.executable, str(script), *bench[1:]], cwd=tree, env=env, capture_output=True,
                          text=True)
    out = proc.stdout + (f"\n[stderr]\n{proc.stderr[-2000:]}" if proc.returncode else "")
    print(f"\n===== {label} ({tree}) exit {proc.returncode} =====\n{out}", flush=True)
    return proc.stdout


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--base", required=True, help="the git revision to compare with")
    ap.add_argument("--rounds", type=int, default=2, help="turns per side (alternating, base first)")
    ap.add_argument("--grep", default=None, help="lines of each output to gather side by side at the end")
    ap.add_argument("bench", nargs=argparse.REMAINDER, help="-- bench/<x>.py [its options]")
    args = ap.parse_args()
    bench = args.bench[1:] if args.bench[:1] == ["--"] else args.bench
    if not bench:
        ap.error("name the bench after --, e.g. -- bench/crash_latency.py --trips 200")
    with tempfile.TemporaryDirectory(prefix="millsense-against-") as tmp:
        tmp_path = Path(tmp)
        tree = checkout(args.base, tmp_path)
        try:
            base_env = {**os.environ, "PYTHONPATH": f"{package_dir(tree, tmp_path)}{os.pathsep}{tree}"}
            head_env = {**os.environ, "PYTHONPATH": str(REPO)}
            where = loaded_from(base_env)
            if not where.startswith(str(tmp_path)):
                print(f"the base's millsense is not the one imported ({where}): not comparable", file=sys.stderr)
                return 1
            print(f"base {args.base}: millsense.daemon from {where}\nhead: {loaded_from(head_env)}")
            outputs: dict[str, list[str]] = {"base": [], "head": []}
            for _ in range(args.rounds):
                outputs["base"].append(run_side(f"base {args.base}", tree, base_env, bench))
                outputs["head"].append(run_side("head (this checkout)", REPO, head_env, bench))
        finally:
            subprocess.run(["git", "-C", str(REPO), "worktree", "remove", "--force", str(tree)], check=False)
    if args.grep:
        pattern = re.compile(args.grep)
        print(f"\n===== side by side: lines matching {args.grep!r} =====")
        for i in range(args.rounds):
            for side in ("base", "head"):
                for line in outputs[side][i].splitlines():
                    if pattern.search(line):
                        print(f"round {i + 1} {side:4s} | {line}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
