"""One ``magcal fleet`` run end to end: find the files, hash them, analyse those not yet in the
results (pool or cluster), keep each log's rows as it finishes, then judge every compass's
history and write the fleet document (``fleet.json``) and page (``index.html``) beside the rows."""

from __future__ import annotations

import hashlib
import json
import os
from dataclasses import dataclass
from typing import Callable

from ... import __version__
from ...core.errors import InputError
from ...logic.fleet import ALPHA, detect
from ...recordings.atomic import write_atomic
from . import page, runner, sources, store, summary


@dataclass(frozen=True)
class Plan:
    """What a run will do: every file named, and the tasks of those not done yet."""

    files: int
    tasks: tuple[dict, ...]
    done_before: int
    duplicates: int


def plan(specs: list[str], results: store.ResultStore, mag: int | None = None, max_samples: int = 250_000,
         on_hash: Callable[[int, int], None] | None = None) -> Plan:
    found = sources.expand(specs)
    if not found:
        raise InputError("no logs, captures or tables found in " + ", ".join(specs))
    tasks, seen, done, dup = [], set(), 0, 0
    for i, s in enumerate(found):
        sha = sources.file_sha256(s.path) if os.path.isfile(s.path) else _missing_key(s.path)
        if on_hash:
            on_hash(i + 1, len(found))
        if sha in seen:
            dup += 1
            continue
        seen.add(sha)
        if results.has(sha, __version__):
            done += 1
            continue
        tasks.append({**s.to_dict(), "sha256": sha, "version": __version__, "mag": mag, "max_samples": max_samples})
    return Plan(files=len(found), tasks=tuple(tasks), done_before=done, duplicates=dup)


def _missing_key(path: str) -> str:
    """The key of a file a manifest names that is not there: its row says so, and once the file
    is there its content gives it another key, so it is analysed then."""
    return hashlib.sha256(("missing file " + os.path.abspath(path)).encode()).hexdigest()


def execute(p: Plan, results: store.ResultStore, scheduler: str | None = None, workers: int | None = None,
            on_result: Callable[[dict], None] | None = None) -> None:
    """Every task of the plan run, each result written to the store the moment it arrives."""

    def keep(result: dict) -> None:
        sha, version = result["key"]
        results.write(sha, version, result["rows"])
        if on_result:
            on_result(result)

    if scheduler:
        runner.run_dask(list(p.tasks), keep, scheduler)
    else:
        runner.run_local(p.tasks, keep, workers)


def conclude(results: store.ResultStore, counts: dict, alpha: float = ALPHA) -> dict:
    """The fleet document of every row of this magcal version in the results, written as
    ``fleet.json`` and ``index.html``."""
    rows = [r for r in results.rows() if r["magcal_version"] == __version__]
    report = detect(rows, alpha)
    doc = summary.document(report, rows, counts, results.root, __version__)
    write_atomic(os.path.join(results.root, "fleet.json"), (json.dumps(doc, indent=1, allow_nan=False) + "\n").encode())
    write_atomic(os.path.join(results.root, "index.html"), page.render(doc).encode())
    return doc
