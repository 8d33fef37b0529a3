"""Fuzz the stream decoder and the Modbus reader's response handling; print inputs, inputs/s, findings.

The targets and what must hold for every input are in tests/faults/fuzz_targets.py
(a spec-literal reference decoder, chunking invariance, counters, shapes; for
Modbus, only `LinkDown` may come out, and what comes out is well-formed).
tests/faults/test_corpus.py replays tests/faults/corpus/ and a short hypothesis
run of the same targets on every `pytest`.

Engines:

- `random` (default): plausible inputs (frames of a small DAQ; answers of a
  plausible Modbus DAQ), mutated (bit flips, cuts, insertions, sync patterns,
  self-splices), plus plain random bytes and mutations of the corpus. Runs on
  `--jobs` processes.
- `atheris`: libFuzzer, coverage-guided, on the instrumented driver modules,
  started from the corpus (`pip install atheris`; one child process per target).
  `--corpus-out DIR` adds libFuzzer's final corpus to DIR/<target>/ and
  minimises it: the hand-made inputs stay, and of the rest the fewest that reach
  every line arc of the driver modules they reach together (greedy set cover;
  `--minimise DIR` does only that). That is how tests/faults/corpus/ was made.

Any input that breaks a property is written to `--save` (default
bench/out/fuzz-findings/) and counted; the exit code is 1 if there was one.

Run: .venv/bin/python bench/fuzz.py [--target all] [--inputs 1000000] [--engine random] [--jobs 1]
"""

from __future__ import annotations

import argparse
import hashlib
import multiprocessing
import random
import re
import shutil
import subprocess
import sys
import tempfile
import time
import traceback
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

CORPUS = REPO / "tests" / "faults" / "corpus"
TARGETS = ("decoder", "modbus")
ATHERIS_BATCH = 100_000


def _target(name: str):
    from tests.faults import fuzz_targets as ft

    ft.quiet_logs()
    return {"decoder": (ft.decoder_target, ft.stream_input), "modbus": (ft.modbus_target, ft.modbus_input)}[name]


def _corpus(name: str) -> list[bytes]:
    d = CORPUS / name
    return [p.read_bytes() for p in sorted(d.glob("*")) if p.is_file()] if d.is_dir() else []


def _save(save: Path, name: str, data: bytes) -> Path:
    save.mkdir(parents=True, exist_ok=True)
    path = save / f"{name}-{hashlib.sha1(data).hexdigest()[:16]}.bin"
    path.write_bytes(data)
    return path


def _random_job(args: tuple) -> dict:
    name, n, seed, save = args
    from tests.faults.fuzz_targets import mutate

    target, generate = _target(name)
    corpus = _corpus(name)
    rng = random.Random(seed)
    findings: list[str] = []
    t0 = time.perf_counter()
    for _ in range(n):
        r = rng.random()
        if r < 0.4:
            data = generate(rng)
        elif r < 0.7:
            data = mutate(generate(rng), rng)
        elif r < 0.9 or not corpus:
            data = rng.randbytes(rng.randrange(0, 512))
        else:
            data = mutate(rng.choice(corpus), rng)
        try:
            target(data)
        except Exception as exc:  # noqa: BLE001 - a finding, whatever it is
            path = _save(Path(save), name, data)
            if len(findings) < 5:
                findings.append(f"{path}: {type(exc).__name__}: {str(exc)[:200]}\n{traceback.format_exc(limit=4)}")
            else:
                findings.append(str(path))
    return {"n": n, "s": time.perf_counter() - t0, "findings": findings}


def run_random(name: str, n: int, jobs: int, seed: int, save: Path) -> dict:
    per = [n // jobs + (1 if i < n % jobs else 0) for i in range(jobs)]
    t0 = time.perf_counter()
    if jobs == 1:
        results = [_random_job((name, n, seed, str(save)))]
    else:
        with multiprocessing.get_context("spawn").Pool(jobs) as pool:
            results = pool.map(_random_job, [(name, k, seed + 1000 * i, str(save)) for i, k in enumerate(per)])
    wall = time.perf_counter() - t0
    findings = [f for r in results for f in r["findings"]]
    return {"target": name, "engine": f"random x{jobs}", "inputs": sum(r["n"] for r in results), "wall_s": wall,
            "findings": findings}


# --------------------------------------------------------------------------- atheris
def _atheris_child(name: str, runs: int, corpus_dir: str, save: str, max_len: int) -> None:
    import atheris

    target, _ = _instrumented(name)

    def one(data: bytes) -> None:
        target(data)

    argv = [sys.argv[0], f"-runs={runs}", f"-max_len={max_len}", "-print_final_stats=1",
            f"-artifact_prefix={save}/{name}-", corpus_dir]
    Path(save).mkdir(parents=True, exist_ok=True)
    atheris.Setup(argv, one)
    atheris.Fuzz()


def run_atheris(name: str, n: int, save: Path, corpus_out: Path | None, max_len: int) -> dict:
    try:
        import atheris  # noqa: F401
    except ImportError:
        return {"target": name, "engine": "atheris", "skipped": "atheris is not installed (pip install atheris)"}
    work = Path(tempfile.mkdtemp(prefix=f"fuzz-{name}-"))
    live = work / "corpus"
    live.mkdir()
    for p in sorted((CORPUS / name).glob("*")) if (CORPUS / name).is_dir() else []:
        shutil.copy(p, live / p.name)
    t0 = time.perf_counter()
    execs, findings, cov = 0, [], []
    # In batches: the atheris process grows (its own bookkeeping, not the target: the random
    # engine runs 10^6 inputs in flat memory) past libFuzzer's 2 GB limit after ~180 k runs.
    # Each batch starts from the corpus the last one left.
    while execs < n and not findings:
        runs = min(ATHERIS_BATCH, n - execs)
        proc = subprocess.run([sys.executable, __file__, "--atheris-child", name, "--inputs", str(runs),
                               "--corpus-dir", str(live), "--save", str(save), "--max-len", str(max_len)],
                              capture_output=True, text=True)
        out = proc.stdout + proc.stderr
        m = re.search(r"stat::number_of_executed_units:\s*(\d+)", out)
        done = int(m.group(1)) if m else 0
        execs += done
        cov += re.findall(r"cov: (\d+) ft: (\d+) corp: (\d+)", out)
        if proc.returncode != 0 or not done:
            findings.append(out[-3000:])
    wall = time.perf_counter() - t0
    result = {"target": name, "engine": "atheris", "inputs": execs, "wall_s": wall, "findings": findings,
              "coverage": cov, "corpus_found": len(list(live.iterdir()))}
    if corpus_out is not None:
        # libFuzzer's corpus at the end: each input reached something the others did not
        # (it replaces an input by a smaller one that reaches the same). New ones are kept.
        dest = corpus_out / name
        dest.mkdir(parents=True, exist_ok=True)
        have = {hashlib.sha1(p.read_bytes()).hexdigest() for p in dest.iterdir() if p.is_file()}
        added = 0
        for p in sorted(live.iterdir()):
            data = p.read_bytes()
            digest = hashlib.sha1(data).hexdigest()
            if digest not in have and len(data) <= max_len:
                (dest / f"atheris-{digest[:12]}.bin").write_bytes(data)
                have.add(digest)
                added += 1
        before, after = minimise(name, dest)
        result["corpus_added"] = added - (before - after)
    shutil.rmtree(work, ignore_errors=True)
    return result


def _instrumented(name: str):
    """The target, with the driver modules instrumented for coverage.

    `atheris.instrument_imports` does not reach modules loaded through the editable
    install's finder, so every function of the modules under test is instrumented
    in place instead (what `atheris.instrument_all` does, limited to these modules).
    """
    import inspect

    import atheris

    from millsense.drivers import base, decoder, modbus_driver, protocol

    target = _target(name)
    for module in (decoder, protocol, modbus_driver, base):
        for attr, value in list(vars(module).items()):
            if inspect.isfunction(value) and value.__module__ == module.__name__:
                setattr(module, attr, atheris.instrument_func(value))
            elif inspect.isclass(value) and value.__module__ == module.__name__:
                for mname, meth in list(vars(value).items()):
                    if inspect.isfunction(meth):
                        setattr(value, mname, atheris.instrument_func(meth))
    return target


# --------------------------------------------------------------------------- corpus minimisation
def _arcs(name: str, data: bytes) -> set:
    """The (file, line, next line) arcs of the driver modules one input runs through."""
    from millsense.drivers import base, decoder, modbus_driver, protocol

    files = {m.__file__ for m in (base, decoder, modbus_driver, protocol)}
    target, _ = _target(name)
    arcs: set = set()
    prev: dict = {}

    def local(frame, event, _arg):
        if event == "line":
            arcs.add((frame.f_code.co_filename, prev.get(frame), frame.f_lineno))
            prev[frame] = frame.f_lineno
        return local

    def called(frame, _event, _arg):
        if frame.f_code.co_filename in files:
            prev[frame] = -frame.f_code.co_firstlineno
            return local
        return None

    sys.settrace(called)
    try:
        target(data)
    except Exception:  # noqa: BLE001 - a finding is reported by the fuzz run, not here
        pass
    finally:
        sys.settrace(None)
    return arcs


def minimise(name: str, directory: Path) -> tuple[int, int]:
    """Keep the hand-made inputs and the fewest others that reach every arc they reach together.

    Greedy set cover on line arcs, smaller inputs first among equals. Returns (before, after).
    """
    files = sorted(p for p in directory.iterdir() if p.is_file())
    fixed = [p for p in files if not p.name.startswith("atheris-")]
    candidates = [p for p in files if p.name.startswith("atheris-")]
    covered: set = set()
    for p in fixed:
        covered |= _arcs(name, p.read_bytes())
    arcs = {p: _arcs(name, p.read_bytes()) - covered for p in candidates}
    keep: list[Path] = []
    while arcs:
        best = max(arcs, key=lambda p: (len(arcs[p]), -p.stat().st_size))
        if not arcs[best]:
            break
        gained = arcs.pop(best)
        keep.append(best)
        covered |= gained
        arcs = {p: a - gained for p, a in arcs.items()}
    for p in candidates:
        if p not in keep:
            p.unlink()
    return len(files), len(fixed) + len(keep)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--target", choices=(*TARGETS, "all"), default="all")
    ap.add_argument("--inputs", type=int, default=1_000_000, help="inputs per target (default 10^6)")
    ap.add_argument("--engine", choices=("random", "atheris"), default="random")
    ap.add_argument("--jobs", type=int, default=1, help="processes for the random engine")
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--save", type=Path, default=REPO / "bench" / "out" / "fuzz-findings")
    ap.add_argument("--corpus-out", type=Path, default=None, help="atheris: add its final corpus to DIR/<target>/")
    ap.add_argument("--max-len", type=int, default=8192)
    ap.add_argument("--minimise", type=Path, default=None, metavar="DIR",
                    help="only minimise the corpus DIR/<target>/ (greedy cover of the driver modules' line arcs)")
    ap.add_argument("--atheris-child", default=None, help=argparse.SUPPRESS)
    ap.add_argument("--corpus-dir", default=None, help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.atheris_child:
        _atheris_child(args.atheris_child, args.inputs, args.corpus_dir, str(args.save), args.max_len)
        return 0

    names = TARGETS if args.target == "all" else (args.target,)
    if args.minimise is not None:
        for name in names:
            before, after = minimise(name, args.minimise / name)
            print(f"{name}: {before} inputs -> {after}")
        return 0
    total, bad = 0, 0
    for name in names:
        if args.engine == "random":
            r = run_random(name, args.inputs, max(1, args.jobs), args.seed, args.save)
        else:
            r = run_atheris(name, args.inputs, args.save, args.corpus_out, args.max_len)
        if "skipped" in r:
            print(f"{name:8s} {r['engine']}: skipped: {r['skipped']}")
            continue
        total += r["inputs"]
        bad += len(r["findings"])
        extra = ""
        if r.get("coverage"):
            cov, ft, corp = max((tuple(map(int, c)) for c in r["coverage"]), key=lambda c: (c[0], c[1]))
            extra = f", libFuzzer cov {cov} ft {ft} corpus {corp}"
        if "corpus_added" in r:
            extra += f", {r['corpus_added']} inputs added to the corpus"
        print(f"{name:8s} {r['engine']}: {r['inputs']} inputs in {r['wall_s']:.1f} s = "
              f"{r['inputs'] / r['wall_s']:.0f} inputs/s, {len(r['findings'])} findings{extra}", flush=True)
        for f in r["findings"][:5]:
            print("  " + f.replace("\n", "\n  "))
    print(f"total: {total} inputs, {bad} findings")
    return 1 if bad else 0


if __name__ == "__main__":
    sys.exit(main())
