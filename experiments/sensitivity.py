#!/usr/bin/env python
"""The paper's appendix sensitivity study, at a budget this machine allows (issue 6, item 3).

    python experiments/sensitivity.py [--variants baseline,hidden_64,...] [--epochs 3]
        [--train-data data/standard_seed0.npz] [--duration 2.0] [--jobs 2] [--out runs/sensitivity]

Each variant is the standard config (``experiments/configs/emax_300rpm.toml``) with one change
of the paper's appendix (``VARIANTS`` below). Every variant, and a baseline without change, is

1. trained on the same data (default: the paper's one trajectory, seed 0) with the same
   shortened schedule (``--epochs``, the learning-rate decay compressed to it) into
   ``OUT/VARIANT/`` (``sgn-jax train``; an interrupted run resumes);
2. rolled out for ``--duration`` s from the first window of every held-out packing of the
   standard case and evaluated against its DEM (``experiments/run_experiments.py --cases
   standard``, into ``runs/experiments/sensitivity_VARIANT``).

The summary ``OUT/summary.json`` has per variant the best validation losses, the training
time, and the ensemble numbers of the rollouts (MSE_t plateau, final energy error, Pearson r,
power of the ensemble means, balls outside), and ``OUT/summary.png`` plots them. The comparison
that counts is each variant against the baseline *at the same budget*: the absolute numbers are
those of a short schedule, not of the shipped model.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from pathlib import Path

from sgn_jax.experiment_tools import sgn_jax_command

HERE = Path(__file__).resolve().parent

# variant -> {section: {field: value}}; the paper's appendix, Table 3 being the baseline
VARIANTS: dict[str, dict[str, dict[str, float | int]]] = {
    "baseline": {},
    "window_3": {"graph": {"window": 3}},
    "window_9": {"graph": {"window": 9}},
    "hidden_64": {"model": {"hidden": 64}},
    "mlp_layers_2": {"model": {"mlp_layers": 2}},
    "interaction_layers_2": {"model": {"interaction_layers": 2}},
    # phi_sb follows phi_pw + 0.3 mm, as in the paper's appendix
    "phi_pw_-0.0049": {"graph": {"phi_pw": -0.0049, "phi_sb": -0.0046}},
    "phi_pw_-0.0055": {"graph": {"phi_pw": -0.0055, "phi_sb": -0.0052}},
    "no_global_loss": {"train": {"global_loss_weight": 0.0}},
}

# what the paper reports for each variant (appendix), for the table of docs/results.md
PAPER: dict[str, str] = {
    "baseline": "stable, 2.78 % energy error (Table 3 settings)",
    "window_3": "stable dynamics, less accurate energy (Fig. A.1)",
    "window_9": "unstable dynamics (Fig. A.2)",
    "hidden_64": "stable dynamics, energy inaccurate (Fig. A.5)",
    "mlp_layers_2": "highly unstable dynamics (Fig. A.6)",
    "interaction_layers_2": "chaotic, energy grows without bound (Fig. A.3)",
    "phi_pw_-0.0049": "stable, energy +15.45 % (Fig. A.7)",
    "phi_pw_-0.0055": "stable, energy -4.18 % (Fig. A.8)",
    "no_global_loss": "stable kinematics, energy +514.35 % (Fig. A.9)",
}


def variant_config(name: str, base: Path, out: Path, epochs: int) -> Path:
    from sgn_jax.api import load_config, replace_section
    from sgn_jax.experiment_tools import save_config

    cfg = load_config(base)
    for section, changes in VARIANTS[name].items():
        cfg = replace_section(cfg, section, **changes)
    cfg = replace_section(cfg, "train", epochs=epochs)
    path = out / "configs" / f"{name}.toml"
    path.parent.mkdir(parents=True, exist_ok=True)
    save_config(cfg, path)
    return path


def _run(argv: list[str], log: Path) -> int:
    log.parent.mkdir(parents=True, exist_ok=True)
    with log.open("a") as fh:
        fh.write("$ " + " ".join(argv) + "\n")
        fh.flush()
        return subprocess.run(argv, stdout=fh, stderr=subprocess.STDOUT).returncode


def main(argv: list[str] | None = None) -> int:
    from sgn_jax.experiment_tools import git_commit, machine_info, write_json

    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--variants", default=",".join(VARIANTS),
                   help=f"comma-separated, from: {', '.join(VARIANTS)}")
    p.add_argument("--epochs", type=int, default=3)
    p.add_argument("--train-data", default="data/standard_seed0.npz")
    p.add_argument("--duration", type=float, default=2.0, help="seconds of each rollout")
    p.add_argument("--jobs", type=int, default=2)
    p.add_argument("--base", default=str(HERE / "configs" / "emax_300rpm.toml"))
    p.add_argument("--out", default="runs/sensitivity")
    args = p.parse_args(argv)
    names = [v.strip() for v in args.variants.split(",") if v.strip()]
    unknown = [v for v in names if v not in VARIANTS]
    if unknown:
        print(f"sensitivity: unknown variant(s) {unknown}; choose from {list(VARIANTS)}",
              file=sys.stderr)
        return 2
    out = Path(args.out)
    cli = sgn_jax_command()
    summary_path = out / "summary.json"
    summary = json.loads(summary_path.read_text()) if summary_path.is_file() else {}
    summary.setdefault("variants", {})
    for name in names:
        cfg_path = variant_config(name, Path(args.base), out, args.epochs)
        run_dir = out / name
        t0 = time.perf_counter()
        if not (run_dir / "summary.json").is_file():
            resume = ["--resume"] if (run_dir / "checkpoints").is_dir() else []
            print(f"train {name} ({args.epochs} epochs)", flush=True)
            rc = _run([*cli, "train", "--config", str(cfg_path), "--data", args.train_data,
                       "--out", str(run_dir), "--quiet", *resume], out / "logs" / f"{name}.log")
            if rc != 0:
                print(f"sensitivity: training {name} failed; see {out}/logs/{name}.log",
                      file=sys.stderr)
                continue
        train_summary = json.loads((run_dir / "summary.json").read_text())
        print(f"rollouts {name}", flush=True)
        rc = _run([sys.executable, str(HERE / "run_experiments.py"), "--model", str(run_dir),
                   "--name", f"sensitivity_{name}", "--cases", "standard", "--duration",
                   repr(args.duration), "--jobs", str(args.jobs), "--skip-runtime"],
                  out / "logs" / f"{name}.log")
        results_path = Path("runs/experiments") / f"sensitivity_{name}" / "results.json"
        if rc != 0 or not results_path.is_file():
            print(f"sensitivity: rollouts of {name} failed; see {out}/logs/{name}.log",
                  file=sys.stderr)
            continue
        case = json.loads(results_path.read_text())["cases"]["standard"]
        summary["variants"][name] = {
            "changes": VARIANTS[name], "paper": PAPER[name], "config": str(cfg_path),
            "train": {k: train_summary.get(k) for k in
                      ("best_epoch", "best_loss", "epochs", "final", "n_params")},
            "rollout_seconds": args.duration,
            "mse_plateau_m2": case["mse_plateau_m2"],
            "energy_relative_error_final": case["energy_relative_error_final"],
            "pearson_r": case["pearson_r"],
            "power_pred_W": case["ensemble"]["power"]["pred_W"]["mean"],
            "power_ref_W": case["ensemble"]["power"]["ref_W"]["mean"],
            "power_relative_error_of_means":
                case["ensemble"]["power"]["relative_error_of_means"],
            "balls_outside_total": case["balls_outside_total"],
            "results": str(results_path),
            "wall_time_s": time.perf_counter() - t0,
        }
        summary.update({"epochs": args.epochs, "train_data": args.train_data,
                        "commit": git_commit(), "machine": machine_info()})
        write_json(summary_path, summary)
    _plot(summary, out / "summary.png")
    print(json.dumps({n: {"energy_err": v["energy_relative_error_final"]["mean"],
                          "mse": v["mse_plateau_m2"]["mean"],
                          "outside": v["balls_outside_total"]}
                      for n, v in summary["variants"].items()}))
    return 0


def _plot(summary: dict, path: Path) -> None:
    import numpy as np

    from sgn_jax.experiment_tools import new_figure, save_figure

    rows = summary.get("variants", {})
    if not rows:
        return
    names = list(rows)
    fig = new_figure(11.0, 4.0, layout="constrained")
    left, right = fig.subplots(1, 2)
    y = np.arange(len(names))
    err = [100 * (rows[n]["power_pred_W"] - rows[n]["power_ref_W"]) / rows[n]["power_ref_W"]
           for n in names]
    left.barh(y, err, color="tab:orange")
    left.set_yticks(y, names)
    left.axvline(0, color="k", lw=0.8)
    left.set_xlabel("ensemble mean power, SGN vs DEM (%)")
    right.barh(y, [rows[n]["mse_plateau_m2"]["mean"] or np.nan for n in names])
    right.set_yticks(y, [""] * len(names))
    right.set_xlabel("mean MSE_t plateau (m²)")
    fig.suptitle(f"Sensitivity at {summary.get('epochs')} epochs, "
                 f"{next(iter(rows.values()))['rollout_seconds']:g}-s rollouts, 8 held-out packings")
    save_figure(fig, path)


if __name__ == "__main__":
    sys.exit(main())
