#!/usr/bin/env python
"""How often the rigid limit (``[model] overlap_limit``) sets a contact model's impulses.

    python experiments/contact/floor_activity.py --model runs/contact_t16_lim100 \\
        --name contact_t16_lim100 --ensembles experiments/envelope/heldout_first4.toml \\
        --data data/envelope [--cases heldout_c00,...] [--duration 1.5] [--every 5]

Each held-out packing of each case is rolled out freely as in ``evaluate_contact.py`` (same
seeds and start, ball-ball separation off); then every ``--every``-th step is replayed from the
model's own frames (``sj.floor_activity_run``; what is counted and the replay's check are in
its module, ``sgn_jax/pipelines/contact_replay.py``). Per case, means over the packings and
per contact kind: acting contacts per step, the share at the floor, and the share of the
normal impulse the floor added.

Writes ``experiments/contact/results/floor_NAME.json`` and ``.md``, atomically.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import sgn_jax.api as sj
import sgn_jax.experiment_tools as tools

KINDS = ("pp", "pw")


def table(summaries, header):
    lines = [header, "", "| case | packings | pp acting / step | pp at floor % | pp impulse from "
             "floor % | pw acting / step | pw at floor % | pw impulse from floor % |",
             "|---|---|---|---|---|---|---|---|"]
    for s in summaries:
        cells = [f"{s[f'{k}_acting_per_step']:.1f} | {100 * s[f'{k}_at_floor_share']:.2f} | "
                 f"{100 * s[f'{k}_floor_impulse_share']:.2f}" for k in KINDS]
        lines.append(f"| {s['case']} | {s['runs']} | {' | '.join(cells)} |")
    return "\n".join(lines) + "\n"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    for name in ("--model", "--name", "--ensembles", "--data"):
        ap.add_argument(name, required=True)
    for name, kind, default in (("--cases", str, None), ("--duration", float, 1.5),
                                ("--every", int, 5), ("--out", str, "experiments/contact/results")):
        ap.add_argument(name, type=kind, default=default)
    args = ap.parse_args()

    t_all = time.perf_counter()
    tools.enable_compilation_cache()
    trained = tools.load_trained_model(tools.resolve_checkpoint(args.model))
    phys = getattr(trained.model, "physics", None)
    if getattr(trained.config.model, "kind", "sgn") != "contact":
        raise SystemExit(f"{args.model} is not a contact model")
    settings = {"pp_separation": False}               # as evaluate_contact.py
    runs, summaries, compiled = {}, [], {}
    for case in tools.select_cases(tools.load_ensembles(args.ensembles), args.cases):
        case_cfg = sj.replace_section(sj.load_config(case.config_path), "rollout", **settings)
        # one compilation for all cases of one graph; each case its own config and motion
        replay = tools.make_floor_replay(trained, case_cfg, compiled)
        rows = []
        for seed in (s for s in case.seeds if s not in case.train_seeds):
            run = f"{case.name}_seed{seed}"
            if not (path := Path(args.data) / f"{run}.npz").exists():
                print(f"missing {path}; skipped")
                continue
            rows.append(tools.floor_activity_run(trained, replay, sj.load_trajectory(path),
                                              args.duration, args.every))
            runs[run] = rows[-1]
            print({"run": run, **{k: round(v, 4) for k, v in rows[-1].items()}}, flush=True)
        if rows:
            summary = {"case": case.name, "runs": len(rows)}
            for name in (f"{k}_{q}" for k in KINDS
                         for q in ("acting_per_step", "at_floor_share", "floor_impulse_share")):
                summary[name], summary[name + "_se"] = sj.ensemble_mean([r[name] for r in rows])
            summaries.append(summary)
    worst = max(r["check_max_ulp"] for r in runs.values())
    worst_spin = max(r.get("check_spin_max_ulp", 0.0) for r in runs.values())
    header = (f"Rigid-limit activity of {args.model} (overlap_limit {phys.overlap_limit:g} m, "
              f"overlap_law_factor {phys.overlap_law_factor:g}): free rollouts of "
              f"{args.duration:g} s, every {args.every}th step replayed; means over packings. "
              f"Replay check (snap-backs included): positions within {worst:.3f}, spins within "
              f"{worst_spin:.1f} float32 ulps.")
    result = {"model": args.model, "overlap_limit": phys.overlap_limit,
              "overlap_law_factor": phys.overlap_law_factor, "runs": runs,
              "duration_s": args.duration, "every": args.every, "settings": settings,
              "summaries": summaries, "wall_s": time.perf_counter() - t_all}
    tools.write_json(Path(args.out) / f"floor_{args.name}.json", result)
    with tools.atomic_write(Path(args.out) / f"floor_{args.name}.md", "w") as fh:
        fh.write(table(summaries, header))
    print(table(summaries, header))
    print(f"wall {result['wall_s']:.1f} s")


if __name__ == "__main__":
    main()
