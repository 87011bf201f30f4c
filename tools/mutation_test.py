"""Mutation testing of one library module with cosmic-ray: do its tests fail when its code is changed?

Install the development extra once (``pip install -e ".[dev]"``), then, from the repository root::

    python tools/mutation_test.py colmap_pvs/consistency.py                   # every mutant
    python tools/mutation_test.py colmap_pvs/io/maps.py --sample 150 --seed 0  # a random 150 of them
    python tools/mutation_test.py colmap_pvs/stereo/geometric.py --tests tests/test_stereo.py -k geometric

The repository's files (``git ls-files``) are copied to a temporary folder and cosmic-ray mutates the
copy, one mutant at a time, running the module's tests (:data:`TESTS`, or ``--tests``) against each; the
worktree is never touched. It prints the killed / survived counts, the score, and each surviving mutant
(file:line, operator, diff). Mutants inside annotations are left out (``from __future__ import
annotations``: annotations are never evaluated, so changing them changes nothing). Slow (a pytest run per
mutant): not part of CI.
"""

from __future__ import annotations

import argparse
import ast
import os
import random
import shutil
import sqlite3
import subprocess
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]

#: The tests that cover each module: what a mutant of that module must fail.
TESTS = {
    "colmap_pvs/consistency.py": ["tests/test_consistency.py"],
    "colmap_pvs/views/depth_range.py": ["tests/test_views.py", "tests/test_robustness_views.py"],
    "colmap_pvs/io/maps.py": ["tests/test_io_maps.py"],
    "colmap_pvs/stereo/geometric.py": ["tests/test_completion.py", "tests/test_stereo.py"],
}


def annotation_lines(source: str) -> set[tuple[int, int, int]]:
    """``(line, first col, last col)`` spans of every annotation in ``source`` (arguments, returns,
    annotated assignments)."""
    spans = set()
    for node in ast.walk(ast.parse(source)):
        found = []
        if isinstance(node, ast.arg | ast.AnnAssign) and node.annotation is not None:
            found.append(node.annotation)
        if isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef) and node.returns is not None:
            found.append(node.returns)
        for a in found:
            for line in range(a.lineno, a.end_lineno + 1):
                first = a.col_offset if line == a.lineno else 0
                last = a.end_col_offset if line == a.end_lineno else 10**6
                spans.add((line, first, last))
    return spans


def in_annotation(pos: tuple[int, int], spans: set[tuple[int, int, int]]) -> bool:
    return any(line == pos[0] and first <= pos[1] < last for line, first, last in spans)


def copy_repository(dest: Path) -> None:
    files = subprocess.run(["git", "ls-files", "-co", "--exclude-standard", "-z"], cwd=ROOT, check=True,
                           capture_output=True, text=True).stdout.split("\0")
    for name in filter(None, files):
        src = ROOT / name
        if src.is_file():
            (dest / name).parent.mkdir(parents=True, exist_ok=True)
            shutil.copy2(src, dest / name)


def cosmic_ray(*args: str, cwd: Path, env: dict) -> None:
    cmd = [sys.executable, "-m", "cosmic_ray.cli", *args]
    done = subprocess.run(cmd, cwd=cwd, env=env, capture_output=True, text=True)
    if done.returncode != 0:
        sys.exit(f"`{' '.join(cmd)}` failed ({done.returncode}):\n{done.stdout[-3000:]}{done.stderr[-3000:]}")


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("module", help="module file from the repository root (colmap_pvs/consistency.py)")
    p.add_argument("--tests", nargs="+", help="test files to run on each mutant (default: TESTS[module])")
    p.add_argument("-k", dest="keyword", help="pytest -k expression to narrow the tests")
    p.add_argument("--sample", type=int, help="run a random sample of this many mutants (default: all)")
    p.add_argument("--seed", type=int, default=0, help="seed of --sample")
    p.add_argument("--exclude_operators", nargs="*", default=[],
                   help="regular expressions of operator names to leave out ('core/NumberReplacer')")
    p.add_argument("--per_site", type=int,
                   help="at most this many mutants (chosen at random) per code position and operator family "
                        "(e.g. 1: one of the eleven replacements of each binary operator)")
    p.add_argument("--lines", help="only mutants on these lines, e.g. 150-210")
    p.add_argument("--timeout", type=float, default=120.0, help="seconds per test run (a timeout kills)")
    p.add_argument("--keep", type=Path, help="work in this folder and keep it (session.sqlite for cr-report)")
    p.add_argument("--retest", action="store_true",
                   help="with the --keep folder of an earlier run: copy the current tests in, rerun only the "
                        "mutants that survived there (the score after new tests, on the same sample)")
    args = p.parse_args(argv)

    module = args.module.replace(os.sep, "/")
    tests = args.tests or TESTS.get(module)
    if not tests:
        p.error(f"no tests known for {module}: pass --tests")
    if not (ROOT / module).is_file():
        p.error(f"no such module: {module}")
    work = args.keep.resolve() if args.keep else Path(tempfile.mkdtemp(prefix="mutation_"))
    work.mkdir(parents=True, exist_ok=True)
    try:
        copy_repository(work)
        env = dict(os.environ, PYTHONPATH=str(work), PYTHONDONTWRITEBYTECODE="1")
        if args.retest:
            with sqlite3.connect(work / "session.sqlite") as db:
                db.execute("DELETE FROM work_results WHERE test_outcome = 'SURVIVED'")
            cosmic_ray("exec", "cr.toml", "session.sqlite", cwd=work, env=env)
            return report(work, module)
        env = dict(os.environ, PYTHONPATH=str(work), PYTHONDONTWRITEBYTECODE="1")
        test_cmd = [sys.executable, "-m", "pytest", "-x", "-q", "-p", "no:cacheprovider", *tests]
        if args.keyword:
            test_cmd += ["-k", repr(args.keyword)]
        (work / "cr.toml").write_text(
            "[cosmic-ray]\n"
            f'module-path = "{module}"\n'
            f"timeout = {args.timeout}\n"
            "excluded-modules = []\n"
            f"test-command = {' '.join(test_cmd)!r}\n"
            "[cosmic-ray.distributor]\n"
            'name = "local"\n', encoding="utf-8")
        cosmic_ray("init", "cr.toml", "session.sqlite", cwd=work, env=env)
        cosmic_ray("baseline", "cr.toml", cwd=work, env=env)  # the tests pass on the unmutated copy
        return run_and_report(work, module, args, env)
    finally:
        if not args.keep:
            shutil.rmtree(work, ignore_errors=True)


def run_and_report(work: Path, module: str, args, env: dict) -> int:
    import re

    from cosmic_ray.work_db import WorkDB, use_db
    from cosmic_ray.work_item import WorkerOutcome, WorkResult

    spans = annotation_lines((ROOT / module).read_text(encoding="utf-8"))
    lines = tuple(int(x) for x in args.lines.split("-")) if args.lines else None
    exclude = re.compile("|".join(args.exclude_operators)) if args.exclude_operators else None
    with use_db(str(work / "session.sqlite"), WorkDB.Mode.open) as db:
        items = list(db.pending_work_items)
        kept = [i for i in items if not (
            in_annotation(i.mutations[0].start_pos, spans)
            or (exclude and exclude.search(i.mutations[0].operator_name))
            or (lines and not lines[0] <= i.mutations[0].start_pos[0] <= lines[-1]))]
        rng = random.Random(args.seed)
        if args.per_site:
            sites = {}
            for i in kept:
                m = i.mutations[0]
                sites.setdefault((m.start_pos, m.operator_name.split("_")[0]), []).append(i)
            kept = [i for group in sites.values() for i in rng.sample(group, min(len(group), args.per_site))]
        if args.sample and args.sample < len(kept):
            kept = rng.sample(kept, args.sample)
        chosen = {i.job_id for i in kept}
        for i in items:
            if i.job_id not in chosen:
                db.set_result(i.job_id, WorkResult(worker_outcome=WorkerOutcome.SKIPPED, output="left out"))
        tests = args.tests or TESTS[module]
        print(f"{module}: {len(items)} mutants, {len(kept)} to run with {tests}", flush=True)
    cosmic_ray("exec", "cr.toml", "session.sqlite", cwd=work, env=env)
    return report(work, module)


def report(work: Path, module: str) -> int:
    from cosmic_ray.work_db import WorkDB, use_db
    from cosmic_ray.work_item import TestOutcome, WorkerOutcome

    survived, killed, incompetent = [], 0, 0
    with use_db(str(work / "session.sqlite"), WorkDB.Mode.open) as db:
        for item, result in db.completed_work_items:
            if result.worker_outcome == WorkerOutcome.SKIPPED:
                continue
            if result.test_outcome == TestOutcome.SURVIVED:
                survived.append((item.mutations[0], result))
            elif result.test_outcome == TestOutcome.INCOMPETENT:
                incompetent += 1
            else:
                killed += 1
    total = killed + incompetent + len(survived)
    for m, result in sorted(survived, key=lambda x: (x[0].start_pos, x[0].operator_name, x[0].occurrence)):
        print(f"\nSURVIVED {module}:{m.start_pos[0]} {m.operator_name} (occurrence {m.occurrence})")
        print("\n".join(result.diff.splitlines()[2:]) if result.diff else "(no diff)")
    score = 100.0 * (total - len(survived)) / total if total else float("nan")
    print(f"\n{module}: {total} mutants run: killed {killed}, incompetent (error, counted as killed) "
          f"{incompetent}, survived {len(survived)}; score {score:.1f} %")
    return 0


if __name__ == "__main__":
    sys.exit(main())
