"""The ``sparsecomm reproduce`` entry: run the selected parts, record where and how long each
ran (``timings.json``), then write the report."""

from __future__ import annotations

import datetime
import shlex
import sys
import time
from pathlib import Path

import jax

from sparsecomm import claims
from sparsecomm.jsonfile import write_json
from sparsecomm.reproduce.plan import PARTS, Reproduce
from sparsecomm.reproduce.provenance import git_commit, hardware, source_digest
from sparsecomm.reproduce.report import read_json, write_report
from sparsecomm.reproduce.runs import fast_compile, run_part
from sparsecomm.sharding import is_primary


def reproduce(args: Reproduce) -> dict:
    """Run the selected parts (in ``PARTS`` order), then write the figures and the report."""
    args.distributed.initialize()
    primary = is_primary()
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    timings_path = out / "timings.json"
    timings = read_json(timings_path) or {}
    timings["_meta"] = {"quick": args.quick}
    fast = bool(args.resolved("fast_compile"))
    previous = fast_compile(True) if fast else None
    try:
        for part in (p for p in PARTS if p in args.parts):
            print(f"== {part}")
            t0 = time.time()
            budget = run_part(args, part)
            timings[part] = {
                "wall_clock_s": time.time() - t0,
                "budget": budget,
                "hardware": hardware(),
                "fast_compile": fast,
                "commit": git_commit(),
                "source_sha256": source_digest(),
                "finished": datetime.datetime.now().isoformat(timespec="seconds"),
                "processes": jax.process_count(),
            }
            if primary:
                write_json(timings_path, timings)
    finally:
        if previous is not None:
            fast_compile(previous)
    if not primary:
        return {}
    summary = write_report(out, shlex.join(sys.argv))
    print(f"report -> {out / 'report.md'}")
    for c in claims.decide_claims(summary):
        print(f"  claim {c.number or 'extra'}: {c.verdict}")
    return summary
