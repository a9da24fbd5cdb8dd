"""The twin comparison as text lines for ``magcal diagnose --twin`` (pure: dict in, str out)."""

from __future__ import annotations


def format_twin(t: dict) -> str:
    """One line per step (statistics inside the twins' band), then the final mismatches."""
    lo, hi = t["band_pct"]
    lines = [f"twin        {t['draws']} draws per step; a statistic fits when the recording lies in the "
             f"twins' {lo:g}–{hi:g} % band"]
    for step in t["steps"]:
        missed = [k for k, b in step["bands"].items() if not b["inside"]]
        tail = ("   misses " + ", ".join(missed)) if missed else ""
        lines.append(f"  {step['step']:<17} {step['inside']:>2}/{step['statistics']} inside{tail}")
    final = t["steps"][-1]
    for m in final["mismatches"]:
        lines.append(f"  mismatch  {m['statistic']} ({m['effect']}): {m['summary']}")
    if not final["mismatches"]:
        lines.append("  the final model's twins hold every statistic of the recording")
    return "\n".join(lines)
