"""Issue 19's per-motion bars read off ``evaluate_contact.py``'s case summaries.

    python experiments/contact/bar_check.py contact_t21 [--dir runs/contact_eval]

Reads ``DIR/NAME_heldout.json``, ``NAME_unseen.json``, ``NAME_standard.json`` and
``NAME_fresh.json`` (``experiments/contact/fresh.toml``; those that exist) and prints, per case,
the power error against its bar (held-out and fresh motions: the summary's max(10 %, 2 SE); Motion 1 and 2: 15 %; the post jar: 20 %; the standard case:
max(5 %, 2 SE)), the mean jar-frame speed (15 %), the touching ball-ball and ball-wall
contacts per step (25 %), the deepest ball-ball overlap (0.5 mm), snapped ball-steps (1 %),
balls outside and non-finite runs (0), and which of them it misses. (The held-out rule "5 of
6 within their bar, the sixth within 20 %" and Spearman are left to the reader.)
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

SPEED, CONTACTS, OVERLAP_M, SNAPPED = 0.15, 0.25, 5e-4, 0.01


def power_bar(case: str, summary_bar: float) -> float:
    if case in ("motion1", "motion2"):
        return 0.15
    if case.startswith("post"):
        return 0.20
    if case == "standard":
        return max(0.05, summary_bar)
    return summary_bar


def misses(s: dict) -> list[str]:
    out = []
    bar = power_bar(s["case"], s["power_bar"])
    if abs(s["power_error"]) > bar:
        out.append(f"power {s['power_error']:+.1%} (bar {bar:.0%})")
    if abs(s["speed_error"]) > SPEED:
        out.append(f"speed {s['speed_error']:+.1%}")
    for kind in ("pp", "pw"):
        if abs(s[f"{kind}_touching_error"]) > CONTACTS:
            out.append(f"{kind} contacts {s[f'{kind}_touching_error']:+.1%}")
    if s["deepest_pp_overlap_m"] > OVERLAP_M:
        out.append(f"overlap {s['deepest_pp_overlap_m'] * 1e3:.2f} mm")
    if s["snapped_fraction"] > SNAPPED:
        out.append(f"snapped {s['snapped_fraction']:.2%}")
    if s["outside_ball_steps"] or s["non_finite_runs"]:
        out.append("outside or non-finite")
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("name")
    ap.add_argument("--dir", default="runs/contact_eval")
    args = ap.parse_args()
    print("| case | power (bar) | speed | pp contacts | pw contacts | deepest pp overlap | "
          "misses |")
    print("|---|---|---|---|---|---|---|")
    for part in ("heldout", "unseen", "standard", "fresh"):
        path = Path(args.dir) / f"{args.name}_{part}.json"
        if not path.exists():
            continue
        for s in json.loads(path.read_text())["summaries"]:
            bar = power_bar(s["case"], s["power_bar"])
            print(f"| {s['case']} | {s['power_error']:+.1%} ({bar:.0%}) | "
                  f"{s['speed_error']:+.1%} | {s['pp_touching_error']:+.1%} | "
                  f"{s['pw_touching_error']:+.1%} | {s['deepest_pp_overlap_m'] * 1e3:.2f} mm | "
                  f"{', '.join(misses(s)) or '-'} |")


if __name__ == "__main__":
    main()
