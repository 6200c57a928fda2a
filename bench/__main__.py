"""`covey bench` / `python -m bench`: run every benchmark, write JSON and a markdown summary.

    python -m bench                  # everything (< 15 min on 2 cores)
    python -m bench --quick          # smoke-sized (< 2 min), into bench/results/quick
    python -m bench --only mesh      # one section (repeatable); the summary keeps the others
    python -m bench --list           # what would run, and how

Sections are the modules in bench/. Each runs in its own child process, in order:
- a module with `main(quick: bool) -> dict` runs through `python -m bench --run-one NAME`,
  which writes bench/results/NAME.json from the returned dict;
- any other module with a `__main__` block runs as `python -m bench.NAME` (with `--quick`
  only if the module accepts it; without it the module is skipped in a quick run) and writes
  its own results (into bench/results, so such scripts are skipped when --out points elsewhere).
Then bench/report.py turns every JSON in the results folder into SUMMARY.md.
"""

from __future__ import annotations

import argparse
import ast
import json
import os
import subprocess
import sys
import threading
import time
from dataclasses import dataclass
from pathlib import Path

BENCH = Path(__file__).resolve().parent
RESULTS = BENCH / "results"
OWN_ORDER = ("inference", "training", "mesh", "agent_cpu")
NOT_SECTIONS = {"__init__", "__main__", "common", "report", "agent_profile"}
"""Not sections: shared code, and agent_profile (a profiling aid that needs py-spy, no dependency)."""


@dataclass(frozen=True)
class Section:
    """One benchmark module and how to run it."""

    name: str
    """Module name under bench/."""
    convention: bool
    """Exposes `main(quick: bool) -> dict` (run in-process of a child, JSON written for it)."""
    script: bool
    """Has an `if __name__ == "__main__":` block (run as `python -m bench.NAME`)."""
    takes_quick: bool
    """Its command line accepts --quick."""

    @property
    def runnable(self) -> bool:
        return self.convention or self.script

    def how(self, quick: bool, default_out: bool = True) -> str:
        if self.convention:
            return f"main(quick={quick})"
        if not self.script:
            return "skipped: no main(quick) and no __main__ block"
        if not default_out:
            return "skipped: it writes into bench/results itself, and this run writes elsewhere"
        if quick and not self.takes_quick:
            return "skipped in --quick: its command line has no --quick"
        return f"python -m bench.{self.name}" + (" --quick" if quick else "")


def inspect(path: Path) -> Section:
    """Read a module's source (never import it) to see which convention it follows."""
    src = path.read_text()
    tree = ast.parse(src)
    convention = False
    for node in tree.body:
        if isinstance(node, ast.FunctionDef) and node.name == "main":
            args = [a.arg for a in (*node.args.posonlyargs, *node.args.args, *node.args.kwonlyargs)]
            convention = "quick" in args
    script = "__name__" in src and "__main__" in src
    return Section(path.stem, convention, script, '"--quick"' in src)


def discover() -> list[Section]:
    found = {p.stem: inspect(p) for p in sorted(BENCH.glob("*.py")) if p.stem not in NOT_SECTIONS}
    order = [n for n in OWN_ORDER if n in found] + sorted(n for n in found if n not in OWN_ORDER)
    return [found[n] for n in order]


def _env(out: Path) -> dict:
    from bench.common import OUT_ENV

    env = dict(
        os.environ, PYTHONUNBUFFERED="1", OMP_WAIT_POLICY="PASSIVE", OPENBLAS_NUM_THREADS="1"
    )
    env.setdefault("OMP_NUM_THREADS", "1")
    env["PYTHONPATH"] = os.pathsep.join(
        filter(None, [str(BENCH.parent), env.get("PYTHONPATH", "")])
    )
    env[OUT_ENV] = str(out)
    return env


def run_section(sec: Section, quick: bool, out: Path, timeout_s: float) -> dict:
    """Run one section in a child process, showing elapsed time; returns its run record."""
    from kit.procs import Child

    if sec.convention:
        cmd = [sys.executable, "-m", "bench", "--run-one", sec.name] + (
            ["--quick"] if quick else []
        )
    else:
        cmd = [sys.executable, "-m", f"bench.{sec.name}"] + (["--quick"] if quick else [])
    t0, started = time.monotonic(), time.time()
    log_path = out / "logs" / f"{sec.name}.log"
    log_path.parent.mkdir(exist_ok=True)
    done = threading.Event()

    def ticker() -> None:
        while not done.wait(30.0):
            print(
                f"    ... {sec.name} still running, {time.monotonic() - t0:.0f} s",
                file=sys.stderr,
                flush=True,
            )

    threading.Thread(target=ticker, daemon=True).start()
    with open(log_path, "w") as log:
        # Its own process group: a section that times out is stopped with whatever it started.
        child = Child(cmd, cwd=BENCH.parent, env=_env(out), output=log, grace_s=10.0)
        try:
            with child:
                rc = child.wait(timeout_s)
            status = "ok" if rc == 0 else f"failed (exit {rc})"
        except subprocess.TimeoutExpired:
            status = f"timed out after {timeout_s:.0f} s"
        finally:
            done.set()
    rec = {
        "section": sec.name,
        "how": sec.how(quick),
        "status": status,
        "wall_s": round(time.monotonic() - t0, 1),
        "log": f"logs/{log_path.name}",
    }
    # Scripts pick their own file names (or print only): note what this one wrote.
    wrote = sorted(
        {
            p.name
            for d in (out, RESULTS)
            for p in d.glob("*.json")
            if p.stat().st_mtime >= started and p.name != "run.json"
        }
    )
    rec["wrote"] = wrote
    if not wrote:
        rec["output_tail"] = log_path.read_text(errors="replace").splitlines()[-15:]
    return rec


def run_one(name: str, quick: bool) -> int:
    """Child side of a convention section: call main(quick) and make sure the JSON exists."""
    import importlib

    from bench import common

    mod = importlib.import_module(f"bench.{name}")
    result = mod.main(quick=quick)
    path = common.out_dir() / f"{name}.json"
    if not path.is_file() or json.loads(path.read_text()).get("section") != name:
        common.write_json(name, dict(result or {}))
    return 0


def parser() -> argparse.ArgumentParser:
    from cli.options import finite

    ap = argparse.ArgumentParser(
        prog="covey bench",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    ap.add_argument("--quick", action="store_true", help="smoke-sized runs (< 2 min)")
    ap.add_argument(
        "--only",
        action="append",
        default=None,
        metavar="SECTION",
        help="run only this section (repeatable)",
    )
    ap.add_argument(
        "--out",
        type=Path,
        default=None,
        help="results folder (default bench/results, quick: bench/results/quick)",
    )
    ap.add_argument("--list", action="store_true", help="list the sections and exit")
    ap.add_argument(
        "--timeout-s",
        type=finite("seconds"),
        default=None,
        help="per-section limit (default 600, quick 120)",
    )
    ap.add_argument("--run-one", default=None, help=argparse.SUPPRESS)
    return ap


def cli(argv: list[str] | None = None) -> int:
    ap = parser()
    args = ap.parse_args(argv)
    if args.run_one:
        return run_one(args.run_one, args.quick)
    from bench import common, report

    # A quick run must not replace the full run's results that the README quotes.
    out = (args.out or (common.RESULTS / "quick" if args.quick else common.RESULTS)).resolve()
    out.mkdir(parents=True, exist_ok=True)
    default_out = out == RESULTS.resolve()
    sections = discover()
    if args.list:
        for s in sections:
            print(f"{s.name:20s} {s.how(args.quick, default_out)}")
        return 0
    if args.only:
        unknown = set(args.only) - {s.name for s in sections}
        if unknown:
            ap.error(f"unknown section(s) {sorted(unknown)}; have {[s.name for s in sections]}")
        sections = [s for s in sections if s.name in args.only]
    timeout_s = args.timeout_s or (120.0 if args.quick else 600.0)
    t0 = time.monotonic()
    records = []
    for i, sec in enumerate(sections, 1):
        how = sec.how(args.quick, default_out)
        print(
            f"[{i}/{len(sections)}] {sec.name}: {how}  (elapsed {time.monotonic() - t0:.0f} s)",
            file=sys.stderr,
            flush=True,
        )
        if how.startswith("skipped"):
            records.append({"section": sec.name, "how": how, "status": "skipped", "wall_s": 0.0})
            continue
        rec = run_section(sec, args.quick, out, timeout_s)
        records.append(rec)
        print(f"      {rec['status']} in {rec['wall_s']:.0f} s", file=sys.stderr, flush=True)
    wall_s = round(time.monotonic() - t0, 1)
    run = {
        "quick": args.quick,
        "only": args.only,
        "wall_s": wall_s,
        "machine": common.machine(),
        "sections": records,
    }
    run_path = out / "run.json"
    if args.only and run_path.is_file():  # keep the last full run's record of the other sections
        last = json.loads(run_path.read_text())
        ran = {r["section"] for r in records}
        last["sections"] = [
            r for r in last.get("sections", []) if r["section"] not in ran
        ] + records
        last.setdefault("partial_reruns", []).append(
            {k: run[k] for k in ("quick", "only", "wall_s")}
        )
        run = last
    run_path.write_text(json.dumps(run, indent=2) + "\n")
    summary = report.write_summary(out)
    print(f"done in {wall_s:.0f} s; wrote {summary}", file=sys.stderr)  # this run, even with --only
    return 0 if all(r["status"] in ("ok", "skipped") for r in records) else 1


if __name__ == "__main__":
    sys.exit(cli())
