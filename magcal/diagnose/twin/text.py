"""The twin comparison as text lines for ``magcal diagnose --twin`` (pure: dict in, str out)."""

from __future__ import annotations


def step_label(steps: list, step: dict) -> str:
    """A step's name; the final one also says which effect it adds to the step before it
    (``final`` would otherwise hide the last effect learned, e.g. repeated reads)."""
    i = next(k for k, s in enumerate(steps) if s is step)
    if step["step"] != "final" or i == 0 or steps[i - 1]["step"] == "baseline":
        return step["step"]
    added = [e for e in step.get("effects", ()) if e not in steps[i - 1].get("effects", ())]
    return f"final (+{'+'.join(added)})" if added else "final"


def format_twin(t: dict) -> str:
    """One line per step (statistics inside the twins' band), then the final mismatches."""
    lo, hi = t["band_pct"]
    lines = [f"twin        {t['draws']} draws per step; a statistic fits when the recording lies in the "
             f"twins' {lo:g}–{hi:g} % band"]
    takes = (t.get("model") or {}).get("takes")
    if takes:
        lines.append(f"  takes     {takes['count']} placements (the recorder paused between them), each in its own hard-iron "
                     f"surroundings: a level per take removed with the calibration in every refit, real and twin "
                     f"(levels spread {takes['level_sd_ut']:.2f} µT)")
    for step in t["steps"]:
        missed = [k for k, b in step["bands"].items() if not b["inside"]]
        tail = ("   misses " + ", ".join(missed)) if missed else ""
        lines.append(f"  {step_label(t['steps'], step):<21} {step['inside']:>2}/{step['statistics']} inside{tail}")
    final = t["steps"][-1]
    for m in final["mismatches"]:
        lines.append(f"  mismatch  {m['statistic']} ({m['effect']}): {m['summary']}")
    if not final["mismatches"]:
        lines.append("  the final model's twins hold every statistic of the recording")
    return "\n".join(lines)
