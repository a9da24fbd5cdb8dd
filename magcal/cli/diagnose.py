"""``magcal diagnose FILE [--json] [--report DIR]``: find the physics a sphere calibration left
out, model it, and show the improvement on held-out data.

FILE is a capture, a MotionCal log or a table: magcal's CSV (``t`` s, ``mx,my,mz`` µT, optional
``temp_c``, ``current_a`` and any other numeric column as a candidate covariate) or another
delimited file read with the table options (``--columns``, ``--unit``, ``--time``, ``--channels``,
``--temp``, ``--current``; ``magcal.recordings.table``). Besides the diagnosis, the JSON carries
``warnings`` (e.g. a fitted field no Earth field could be) and, for a table, ``input`` (how it
was read). ``--json`` prints ``magcal.diagnose/1``. Exit status: 0 when the recording was
diagnosed (whatever was found), 6 when it could not be read or analysed.

FILE may be a flight log (PX4 ULog, ArduPilot DataFlash; ``--mag N``). |m| alone cannot test an
interference term on a flight (the board turns while the current changes), so the JSON gains
``"flight_log"`` (``magcal.diagnose.log/1``, ``magcal.app.flightlog.diagnose_flight_log``): the
motors-running step and the current (else throttle) term judged against the expected field
vector — the log's attitude and the World Magnetic Model — on held-out time blocks, as ``magcal
fit`` does, each with its coefficient, σ, floor, p-value and verdict under ``findings``. Where
|m| alone cannot be diagnosed at all (a mostly level flight) the JSON has ``magnitude_failure``
(the reason) instead of the |m| diagnosis, and the flight-log section still runs.

The JSON has ONE ``calibration``: the one ``write`` puts on a device, ``export`` turns into
parameters and the report shows. On a flight log whose fit against the expected field succeeded
it is that fit's — ``magcal fit LOG``'s, with ``"calibration_from": "flight_log"`` and
``calibration_model`` — and the |m| diagnosis's own is kept under ``alternatives`` (``[{name,
model, why, calibration}]``); where diagnosis added channel terms to fit's calibration, fit's is
there too, with both fields. The calibration is in fit's convention (det W = 1), so where it is
fit's its numbers are fit's.

``--model-out M.yaml`` writes the sensor model learned around the final calibration (noise,
quantum, offset wander, glitches, nonlinearity …; ``magcal simulate --model M.yaml`` draws from
it); ``model_out`` in the JSON says why its field (the mean calibrated |m|) is not the
calibration's radius. ``--twin`` compares the recording with ``--draws`` twins of that model, step by step from
the baseline (hard iron + white noise), in the text, as ``"twin"`` in the JSON and, with
``--report``, as twin.html beside the report (magcal.diagnose.twin, docs/sensor-model.md).
"""

from __future__ import annotations

import os
import sys

from ..core.errors import ConfigError
from .common import calibration_lines, field_warning, reading_report
from .options import add, add_table_options, directory, fraction, output_file, positive_int, table_format

HELP = "find what a sphere calibration leaves out of a recording, model it, show held-out gain"


def add_arguments(p) -> None:
    p.add_argument("file", metavar="FILE", help="a capture, a CSV (t, mx, my, mz, optional channels) or a flight log (--mag N)")
    add(p, "json", "quiet")
    p.add_argument("--report", metavar="DIR", type=directory,
                   help="write the evidence as an HTML page (index.html) with its pictures into DIR")
    p.add_argument("--alpha", type=fraction, default=0.01, help="family-wise false-alarm level")
    p.add_argument("--model-out", type=output_file, metavar="M.yaml",
                   help="write the learned sensor model (YAML, or JSON when the name ends in .json)")
    p.add_argument("--twin", action="store_true", help="compare the recording with twins of the learned model")
    p.add_argument("--draws", type=positive_int, default=50, help="twin draws per step with --twin (at least 10)")
    p.add_argument("--seed", type=int, default=0, help="first seed of the twin draws")
    add_table_options(p)
    add(p, "mag")


def format_text(d: dict) -> str:
    """The human-readable summary of a diagnosis dict (pure). On a flight log, a limit on a
    channel that the log section below tests against the expected field says so."""
    b, f = d["baseline"], d["final"]
    lines = [f"input       {d['input']}"] if d.get("input") else []
    lines += [
        f"samples     {d['n_samples']}",
        f"baseline    {b['model']:<28} rms {b['rms_ut']:.3f} µT   held-out {b['heldout_rms_ut']:.3f} µT",
    ]
    suspected = any(k.get("suspected") for k in d.get("limits", []))
    if not d["findings"]:
        lines.append(
            "findings    none proven — but see the limit below"
            if suspected
            else "findings    none — the sphere (hard iron) model explains the recording"
        )
    for k in d["findings"]:
        lines.append(f"finding     {k['effect']}: {k['summary']}")
    lines += left_out_lines(d.get("limits", []))
    tested_below = {f["channel"] for f in (d.get("flight_log") or {}).get("findings", [])}
    for k in d.get("limits", []):
        if not k.get("left_out"):
            below = " (from |m| alone; tested against the expected field below)" if k.get("channel") in tested_below else ""
            lines.append(f"limit       {k['effect']}{below}: {k['summary']}")
    source = {"fit": "   (magcal fit's calibration)", "fit+channels": "   (magcal fit's, with the channel terms)"}
    from_log = d.get("calibration_from") == "flight_log"
    lines.append(f"final       {f['model']:<28} rms {f['rms_ut']:.3f} µT   held-out {f['heldout_rms_ut']:.3f} µT"
                 + ("   (|m| alone: an alternative; the calibration is below)" if from_log
                    else _source_label(f.get("from", ""), source)))
    if not from_log:
        lines += coefficient_lines(d["calibration"], d.get("clock", True)) + alternative_lines(d)
    return "\n".join(lines)


def _source_label(origin: str, source: dict) -> str:
    base = origin.removesuffix("+located")
    label = source.get(base, "")
    return label[:-1] + ", with the located effects)" if label and base != origin else label


def alternative_lines(d: dict) -> list[str]:
    """One line per calibration set aside: its offset and field, and why it is not the one (pure)."""
    lines = []
    for a in d.get("alternatives", []):
        c = a["calibration"]
        lines.append(f"alternative {a['name']}: offset (" + ", ".join(f"{v:.3f}" for v in c["offset_ut"])
                     + f") µT, field {c['field_ut']:.3f} µT — {a['why']}")
    return lines


def coefficient_lines(cal: dict, clock: bool = True, sigma: dict | None = None) -> list[str]:
    """A calibration's rows: offset, field, soft iron (± ``sigma`` where given) and each channel term (pure)."""
    from ..diagnose.channels import unit_of

    lines = calibration_lines(cal, sigma)
    units = {"motors_on": "motors-running step", "current_a": "A"}
    for name, coef in (cal.get("coef_ut_per_unit") or {}).items():
        unit = units.get(name) or unit_of(name, clock)
        lines.append(f"coef_{name:<7}" + " ".join(f"{v:9.4f}" for v in coef) + f"   µT per {unit}")
    return lines


def log_calibration_lines(d: dict) -> list[str]:
    """On a flight log, the calibration (the flight-log fit's) and the alternative set aside (pure)."""
    if d.get("calibration_from") != "flight_log":
        return []
    lines = [f"calibration {d['calibration_model']}: the flight-log fit's, the one write, export and the report use"]
    lines += coefficient_lines(d["calibration"], d.get("clock", True),
                               {"offset_ut": d["flight_log"].get("uncertainty", {}).get("offset_ut")})
    return lines + alternative_lines(d)


def left_out_lines(limits: list) -> list[str]:
    """One line per reason for the channels diagnosis left out of its candidates."""
    by_why: dict[str, list[str]] = {}
    for k in limits:
        if k.get("left_out"):
            by_why.setdefault(k["reason"], []).append(k["channel"])
    return [f"left out    {', '.join(names)}: {why} (--channels to test them)" for why, names in by_why.items()]


# the share of diagnose's time each step takes (measured on simulated recordings of 15 000 and
# 50 000 samples, with the locate step and fit's held-out model choice: the held-out comparison
# and the locate step take most of it), for the progress display's ETA
STEP_SHARE = {"set_aside_glitches": 0.04, "fit_baseline": 0.02, "select_terms": 0.09, "refit": 0.01,
              "compare_heldout": 0.55, "locate": 0.28, "compare_with_simulation": 0.005, "describe": 0.005}


def _done_before(step: str) -> float:
    shares = list(STEP_SHARE.items())
    k = next((i for i, (name, _) in enumerate(shares) if name == step), len(shares))
    return sum(v for _, v in shares[:k]) / sum(STEP_SHARE.values())


MANY_CHANNELS = 8


def many_channels_hint(n_channels: int, d: dict) -> str | None:
    """A wide log makes every column a candidate, and the family-wise test stricter for each."""
    channel_findings = [f for f in d["findings"] if f["effect"] not in ("soft_iron", "outliers")]
    if n_channels < MANY_CHANNELS or channel_findings:
        return None
    return (f"all {n_channels} other numeric columns were candidate covariates, and the family-wise "
            "test gets stricter with each; name the plausible ones with --channels (and the die "
            "temperature with --temp) for a sharper test")


def _report_dir(path: str) -> None:
    import os

    from ..core.errors import InputError

    try:
        os.makedirs(path, exist_ok=True)
    except OSError as exc:
        raise InputError(f"--report {path}: cannot create the folder: {exc.strerror or exc}") from None
    if not os.access(path, os.W_OK | os.X_OK):
        raise InputError(f"--report {path}: this user cannot write into the folder")


def run(args) -> int:
    from ..app.load import load_recording
    from .common import Progress

    if args.draws < 10:
        raise ConfigError(f"--draws must be at least 10 (a 2.5–97.5 % band needs them), got {args.draws}")
    if args.report:
        _report_dir(args.report)  # a folder that cannot be written is said now, not after the work
    with Progress(quiet=args.quiet).working(f"diagnose {os.path.basename(str(args.file))}") as ticker:
        ticker.doing("reading")
        series, notes, flight_log = load_recording(args.file, table_format(args), args.mag)
        for w in notes:
            print(f"magcal: warning: {args.file}: {w}", file=sys.stderr)
        series = series.only_valid()
        d, diagnosis = _diagnose_magnitude(args, series, flight_log, ticker)
        if diagnosis is not None and flight_log is None:  # on a log, magcal fit's is the flight-log fit's
            add_fit_alternative(d, series)
        if series.source:
            d["input"] = series.source
        d["reading"] = reading_report(series, args.file)
        d["clock"] = series.clock  # false: the source gave no time, and "per sample" replaces "per s"
        if flight_log is not None:  # the terms |m| cannot test, against the expected field
            from ..app.flightlog import diagnose_flight_log

            ticker.doing("testing the interference terms against the expected field")
            d["flight_log"] = diagnose_flight_log(flight_log)
            take_log_calibration(d)
        d["warnings"] = list(notes) + (field_warning(d["calibration"]["field_ut"]) if "calibration" in d else [])
        add_evidence(d, series, args.file)
        twin = _twin(args, series, d, diagnosis, ticker) if diagnosis else None
        if args.report and (diagnosis or d.get("calibration_from") == "flight_log"):
            ticker.doing(f"drawing the report in {args.report}")
            _write_report(args, diagnosis, d, flight_log)
            if twin is not None:
                from ..app.report_twin import write_twin_panels

                write_twin_panels(twin, args.report)
    reported = bool(args.report) and (diagnosis is not None or d.get("calibration_from") == "flight_log")
    _print(args, d, series, twin, written=bool(diagnosis), reported=reported)
    if diagnosis is None:
        if (args.report and not reported) or args.model_out or args.twin:
            print(f"magcal diagnose: {args.file}: no {'report, ' if not reported else ''}sensor model or twin: "
                  "they need the |m| diagnosis", file=sys.stderr)
        if "failure" in d["flight_log"]:
            from .exits import Exit

            print(f"magcal diagnose: {args.file}: {d['magnitude_failure']}; {d['flight_log']['message']}",
                  file=sys.stderr)
            return Exit.GATE  # the data did not support either analysis, as fit says with 3
    return 0


def add_evidence(d: dict, series, path) -> None:
    """The recording, and what the write gates judge of the result's calibration on it
    (``fit.evidence``), so that ``magcal write`` judges every gate."""
    from ..core.calibration import Calibration
    from ..fit.evidence import evidence

    d["recording"] = str(path)
    if "calibration" in d:
        d["evidence"] = evidence(series.field_ut, Calibration.from_dict(d["calibration"]), series.channels)


def add_fit_alternative(d: dict, series) -> None:
    """Where diagnosis's calibration is not magcal fit's own (channel terms added, or its own
    model), fit's on the same samples joins ``alternatives`` with what differs and why."""
    from ..fit import fit_calibration

    if d["final"].get("from") == "fit":
        return  # fit's calibration itself, in fit's numbers
    result = fit_calibration(series, model="auto")
    if not result:
        return
    fit, own = result.to_dict()["calibration"], d["calibration"]
    terms = sorted(own.get("coef_ut_per_unit") or {})
    what = (f"adds the {', '.join(terms)} term(s), and the geometry fitted around them" if terms
            else "was changed by the effects the locate step modelled" if "located" in d["final"]["from"]
            else "is diagnosis's own model")
    d.setdefault("alternatives", []).append({
        "name": "fit",
        "model": result.model,
        "why": f"magcal fit's calibration of the same samples ({result.model}); diagnosis's {what} "
               f"({d['final']['from']}): field {own['field_ut']:.3f} µT against fit's {fit['field_ut']:.3f} µT",
        "calibration": fit,
    })


def take_log_calibration(d: dict) -> None:
    """On a flight log whose fit against the expected field succeeded, that fit's calibration is
    THE calibration of the result (as ``magcal fit LOG`` gives it: what ``write``, ``export`` and
    the report use); the |m| diagnosis's own moves under ``alternatives``, with why."""
    log = d["flight_log"]
    if "calibration" not in log:
        return
    own = d.pop("calibration", None)
    d["calibration"] = log.pop("calibration")
    d["calibration_from"] = "flight_log"
    d["calibration_model"] = log["model"]
    if own is not None:
        from ..app.flightlog import against_text

        against = "against " + against_text(log["mode"], log.get("earth_field"), log.get("earth_model"), log.get("earth_field_ut"))
        d["alternatives"] = [*d.get("alternatives", []), {
            "name": "magnitude",
            "model": d["final"]["model"],
            "why": f"the diagnosis of |m| alone ({d['final']['model']}): not used, because |m| cannot test the terms "
                   f"that follow the flight (a board that turns while the motors and current change); the "
                   f"calibration is the flight-log fit's ({log['model']}, {against}), as magcal fit gives it",
            "calibration": own,
        }]


def _write_report(args, diagnosis, d: dict, flight_log) -> None:
    """The page, with the result's calibration and, on a flight log, the fit against the
    expected field: its terms and the expected against the measured field per axis."""
    from ..app.report import write_log_report, write_report

    sections = ()
    if d.get("calibration_from") == "flight_log":
        from ..app.flightlog import vector_traces
        from ..app.report.flightlog import flight_log_section

        traces = vector_traces(flight_log, d["calibration"], d["flight_log"].get("earth_field"))
        if diagnosis is None:  # |m| alone not diagnosed: the page of the flight-log fit alone
            write_log_report(d, traces, args.report, title=str(args.file))
            return
        sections = (flight_log_section(d, traces),)
    write_report(diagnosis, args.report, title=str(args.file), sections=sections, result=d)


def _diagnose_magnitude(args, series, flight_log, ticker):
    """(the diagnosis dict, the Diagnosis) — or, on a flight log whose |m| alone cannot be
    diagnosed (a mostly level flight), (a dict saying why, None): its vector section still runs."""
    from ..core.errors import InputError
    from ..diagnose import diagnose

    n = f"{len(series):,}".replace(",", " ")
    try:
        # channels the user named are tested as named; otherwise those that follow the orientation
        # or the reading are left out (magcal.diagnose.hygiene)
        diagnosis = diagnose(series, alpha=args.alpha, screen=args.channels is None,
                             on_step=lambda name: ticker.share(_done_before(name), f"{n} samples: {name}"))
    except InputError as exc:
        if flight_log is None:
            raise
        return {"n_samples": len(series), "magnitude_failure": str(exc)}, None
    return diagnosis.to_dict(), diagnosis


def _print(args, d: dict, series, twin, written: bool, reported: bool) -> None:
    if args.json:
        from .common import document, print_json

        print_json(document("diagnose", d))
        sys.stdout.flush()
        return
    if "magnitude_failure" in d:
        print(f"input       {d.get('input', args.file)}\nsamples     {d['n_samples']}\n"
              f"|m| alone   not diagnosed: {d['magnitude_failure']}")
    else:
        print(format_text(d))
    if "flight_log" in d:
        from .fitlog import format_log_diagnosis

        print(format_log_diagnosis(d["flight_log"]))
        for line in log_calibration_lines(d):
            print(line)
    hint = many_channels_hint(len(series.channels), d) if "findings" in d else None
    if hint:
        print(f"note        {hint}")
    if twin is not None:
        from ..diagnose.twin.text import format_twin

        print(format_twin(d["twin"]))
    if args.model_out and written:
        print(f"model       {args.model_out}: {d['model_out']['why']}")
    if args.report and reported:
        print(f"report      {args.report}/index.html")
    sys.stdout.flush()


def model_out_note(path: str, model_field_ut: float, radius_ut: float, from_log: bool) -> dict:
    """What --model-out wrote, and why its field is not the calibration's radius (pure)."""
    why = (f"a sensor model; its field {model_field_ut:.3f} µT is the mean calibrated |m| of the samples it was "
           f"learned on (what its twins draw), against the calibration's fitted radius {radius_ut:.3f} µT")
    if from_log:
        why += "; learned around the |m| diagnosis's calibration (the alternative), not the flight-log fit's"
    return {"file": str(path), "field_ut": model_field_ut, "radius_ut": radius_ut, "why": why}


def _twin(args, series, d: dict, diagnosis, ticker):
    """The sensor model around the final calibration (written with --model-out) and, with
    --twin, its step-by-step comparison with the recording (added to ``d`` as "twin";
    magcal.diagnose.twin, docs/sensor-model.md)."""
    if not (args.model_out or args.twin):
        return None
    from ..core.calibration import Calibration
    from ..diagnose import twin
    from ..diagnose.diagnosis import calibration_dict

    ticker.doing("learning the sensor model")
    source = {"recording": str(args.file), **({} if series.clock else {"clock": False})}  # no time: rates per sample
    around = calibration_dict(diagnosis.final)  # the |m| diagnosis's: on a flight log, its alternative
    model = twin.learn(series, Calibration.from_dict(around), source=source)
    if args.model_out:
        from ..app.sensor_file import save_model

        save_model(model, args.model_out)
        d["model_out"] = model_out_note(args.model_out, float(model.calibration.field_ut), around["field_ut"],
                                        d.get("calibration_from") == "flight_log")
    if not args.twin:
        return None
    ticker.doing(f"comparing with {args.draws} twins per step")
    report = twin.compare_steps(model, series, draws=args.draws, seed=args.seed,
                                on_step=lambda i, n, name: (ticker.step(i, n, name),
                                                            ticker.doing(f"twins of step {name}")))
    d["twin"] = report.to_dict()
    return report
