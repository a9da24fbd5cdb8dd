"""The live view in a real browser: how fast the page loads and how often it is updated.

Run: python bench/view.py [--pace N] [--seed S]     (default pace 1: a board's own time)

Starts ``magcal calibrate --port sim://?pace=N --view``, opens its URL in a headless Chromium
(Debian's, under Selenium through chromium-driver: ``tests/browser_support.py``) and measures:

1. page load: from navigation start to the load event, and to the first state drawn (both
   from the browser's own clock, ``performance``) — target < 1 s;
2. updates per second the page received while collecting (states counted by the page over the
   middle of the collection, from the browser's clock) — target ≥ 10;

and saves two screenshots in ``bench/results/``: ``view_half.png`` (the first state with at
most half the direction cells empty) and ``view_done.png`` (the write VERIFIED). Look at them.
"""

import argparse
import os
import sys
import tempfile
import time

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, os.path.join(HERE, ".."))
sys.path.insert(0, os.path.join(HERE, "..", "tests"))

from browser_support import chromium, missing, start_view  # noqa: E402

RESULTS = os.path.join(HERE, "results")
LOAD_TARGET_S, UPDATES_TARGET_HZ = 1.0, 10.0

PAGE_CLOCK = ("const v = window.magcalView || {}; const s = v.state; return {t: performance.now(),"
              " updates: v.updates || 0, first: v.firstStateMs, status: s ? s.status : null,"
              " gaps: s ? s.motioncal.gaps_pct : null, write: s ? s.write : null, ended: !!v.ended};")


def load_times(driver) -> tuple[float, float]:
    """(navigation → load event, navigation → first state) in seconds, the browser's clock."""
    nav = driver.execute_script("return performance.getEntriesByType('navigation')[0].toJSON();")
    first = None
    while first is None:
        first = driver.execute_script(PAGE_CLOCK)["first"]
        time.sleep(0.01)
    return nav["loadEventEnd"] / 1000.0, first / 1000.0


def watch(driver, timeout_s: float = 300.0) -> tuple[list[dict], bool]:
    """Page states every 50 ms until the command has ended; the half-filled screenshot on the way."""
    seen, half_saved = [], False
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        s = driver.execute_script(PAGE_CLOCK)
        seen.append(s)
        if not half_saved and s["gaps"] is not None and s["gaps"] <= 50.0 and s["status"] == "collecting":
            time.sleep(0.3)  # the frame after the state
            driver.save_screenshot(os.path.join(RESULTS, "view_half.png"))
            half_saved = True
        if s["ended"]:
            break
        time.sleep(0.05)
    return seen, half_saved


def update_rate(seen: list[dict]) -> float:
    """States received per second over the middle half of the collection (page clock)."""
    coll = [s for s in seen if s["status"] == "collecting"]
    if len(coll) < 4:
        return float("nan")
    a, b = coll[len(coll) // 4], coll[3 * len(coll) // 4]
    return (b["updates"] - a["updates"]) / ((b["t"] - a["t"]) / 1000.0)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--pace", type=float, default=1.0, help="sim:// pace (1: real time)")
    ap.add_argument("--seed", type=int, default=4)
    a = ap.parse_args()
    problem = missing()
    if problem:
        print(f"cannot run: {problem}")
        return 1
    os.makedirs(RESULTS, exist_ok=True)
    with tempfile.TemporaryDirectory() as tmp:
        driver = chromium(os.path.join(tmp, "profile"))
        try:
            proc, url = start_view(["calibrate", "--port", f"sim://?pace={a.pace:g}&seed={a.seed}&eeprom={tmp}/e.bin"])
            driver.get(url)
            load_s, first_s = load_times(driver)
            seen, half = watch(driver)
            time.sleep(0.3)
            driver.save_screenshot(os.path.join(RESULTS, "view_done.png"))
            code = proc.wait(timeout=60)
        finally:
            driver.quit()
    rate = update_rate(seen)
    print(f"pace {a.pace:g}, seed {a.seed}; calibrate exit {code}; last state: {seen[-1]['write']}")
    print(f"page load (navigation → load event)  {load_s:.3f} s   target < {LOAD_TARGET_S:g} s")
    print(f"navigation → first state drawn       {first_s:.3f} s")
    print(f"updates received while collecting    {rate:.1f} /s   target ≥ {UPDATES_TARGET_HZ:g}")
    print(f"screenshots: {'view_half.png, ' if half else '(no half-filled state seen) '}view_done.png in {RESULTS}")
    ok = load_s < LOAD_TARGET_S and rate >= UPDATES_TARGET_HZ and seen[-1]["write"] == "verified"
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
