"""``magcal fleet SOURCES… -o RESULTS``: every log of a fleet, each compass's history and the
flights where it changed.

SOURCES are folders (walked for flight logs, captures and tables), globs, and manifests (CSV of
``path,vehicle[,notes]``). Each file is analysed as ``magcal fit`` analyses it (a flight log:
every magnetometer, or ``--mag N``, against the expected field with its current term judged on
held-out blocks) on a local process pool, or with ``--scheduler ADDRESS`` on a Dask cluster.
Each log's rows go to ``RESULTS/rows/`` (Parquet, keyed by the file's sha256 and magcal's
version) the moment it finishes, so an interrupted run started again goes on where it stopped
and a re-run analyses only new files. Then every (vehicle, compass) history is judged for
changes (``magcal.logic.fleet``: a hard-iron step, a current term that appeared or changed, each
against both sides' σ, and whether the sibling compasses moved too), and ``RESULTS/fleet.json``
and ``RESULTS/index.html`` (the fleet page) are written. ``--json`` prints the document
(``magcal.fleet/1``): ``logs`` (counts), ``vehicles`` → ``compasses`` → ``flights`` and
``changes``, a flat ``changes`` list, ``failures`` (rows without a calibration, with why).

Exit status: 0 when every file was analysed (files that could not be read or fitted are rows
with their reason, listed under ``failures``), 2 for a bad command line or a missing extra,
6 when SOURCES hold nothing to read or RESULTS cannot be written, 130 when interrupted (what
finished is kept).
"""

from __future__ import annotations

import sys

from .exits import Exit
from .options import add, directory, fraction, positive_int

HELP = "analyse every log of a fleet (pool or Dask cluster): each compass's history and the flights where it changed"


def add_arguments(p) -> None:
    p.add_argument("sources", metavar="SOURCES", nargs="+",
                   help="folders of logs, globs, or a manifest CSV (path,vehicle[,notes])")
    p.add_argument("-o", "--results", metavar="RESULTS", type=directory, required=True,
                   help="the results folder: rows/ (Parquet), fleet.json, index.html")
    p.add_argument("--scheduler", metavar="ADDRESS",
                   help="run on the Dask cluster at ADDRESS (tcp://host:8786; `dask scheduler`, `dask worker`) "
                   "instead of the local process pool")
    p.add_argument("--workers", type=positive_int, help="local processes (default: every core)")
    p.add_argument("--alpha", type=fraction, default=0.01,
                   help="family-wise false-change level per vehicle")
    add(p, "json")
    add(p, "quiet", help="no progress on stderr (redrawn on a terminal; otherwise a line per tenth of the run)")
    add(p, "mag", help="only this magnetometer of each flight log, 0-based in the log's order "
        "(default: every magnetometer)")


class _ResultCounter:
    """Each analysed log counted as it arrives, with its failed rows and an ETA: redrawn on a
    terminal, a line every tenth of the run otherwise (called once per result, not a clock)."""

    def __init__(self, total: int, quiet: bool):
        from .common import Progress

        self.progress, self.total, self.quiet = Progress(quiet=quiet), total, quiet
        self.done = self.failed = 0
        self._next_line = 0.1

    def __call__(self, result: dict) -> None:
        from .common import rate_eta

        self.done += 1
        self.failed += sum(r["status"] != "ok" for r in result["rows"])
        text = f"fleet  {rate_eta(self.done, self.total, self.progress.elapsed(), 'logs')}  {self.failed} rows failed"
        if self.progress.active:
            self.progress.show(text)
        elif not self.quiet and self.done >= self._next_line * self.total:
            print(text, file=sys.stderr)
            self._next_line += 0.1


def _hashing(quiet: bool):
    from .common import Progress

    progress = Progress(quiet=quiet)
    return lambda i, n: progress.count("hashing", i, n, "files")


def format_text(doc: dict) -> str:
    """The summary: counts, then one line per change (pure)."""
    from ..app.fleet.page import KIND_WORDS

    c = doc["logs"]
    lines = [f"logs        {c['total']} ({c['analysed']} analysed now, {c['done_before']} done before, "
             f"{c['duplicates']} duplicates)",
             f"rows        {doc['rows']} ({doc['failed_rows']} without a calibration)",
             f"vehicles    {len(doc['vehicles'])}, {sum(len(v['compasses']) for v in doc['vehicles'])} compasses",
             f"changes     {len(doc['changes'])} (family-wise level {doc['alpha']:g} per vehicle)"]
    for ch in doc["changes"]:
        sib = "" if ch["alone"] is None else ("; this compass alone" if ch["alone"] else "; its siblings moved too")
        lines.append(f"  {ch['vehicle']} {ch['compass']}: {KIND_WORDS[ch['kind']]} at {ch['flight']} (after "
                     f"{ch['previous_flight']}): ({', '.join(f'{v:+.3g}' for v in ch['step'])}) ± "
                     f"({', '.join(f'{v:.2g}' for v in ch['sigma_step'])}), p {ch['p_value']:.2g}{sib}")
    lines.append(f"page        {doc['results']}/index.html")
    return "\n".join(lines)


def run(args) -> int:
    from ..app.fleet import job, store
    from .common import document, print_json
    from .fit import MAX_FIT_SAMPLES

    results = store.ResultStore(args.results)
    p = job.plan(args.sources, results, args.mag, MAX_FIT_SAMPLES, on_hash=_hashing(args.quiet or args.json))
    counter = _ResultCounter(len(p.tasks), args.quiet)
    try:
        job.execute(p, results, args.scheduler, args.workers, on_result=counter)
    finally:
        counter.progress.done()
    counts = {"total": p.files, "analysed": counter.done, "done_before": p.done_before, "duplicates": p.duplicates}
    doc = job.conclude(results, counts, args.alpha)
    if args.json:
        print_json(document("fleet", doc))
    else:
        print(format_text(doc))
    return Exit.OK
