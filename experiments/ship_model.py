#!/usr/bin/env python
"""Copy a trained model into the package (``sgn_jax/data/models/CASE/``) with its provenance.

    python experiments/ship_model.py --run runs/standard_4traj --data data/standard_seed0.npz,...
        --train-command "sgn-jax train ..." [--results runs/experiments/standard_4traj/results.json]
        [--case emax_300rpm] [--what "..."]

Replaces the shipped model of CASE with the best checkpoint of the training run RUN (its
``checkpoints/best/<step>`` orbax directory, a few MB) and writes next to it:

- ``PROVENANCE.json``: what the model is, the training command, the sha256 of every training
  file, the commit at training, the best and last epochs' losses, the parameter count, the
  numbers of windows, the wall time, and (with ``--results``) the held-out evaluation headline
  of ``experiments/run_experiments.py`` and its command;
- ``loss.png`` and ``metrics.csv`` of the run.

The step's ``sgn_digest.json`` (sha256 of every file) is copied with it, or written if the run
predates it. The new model is loaded back (``sgn_jax.records.checkpoint.load_trained_model``, which
verifies every file) before the old one is removed, so a failed copy never leaves the package
without a model.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def main(argv: list[str] | None = None) -> int:
    from sgn_jax.api import SGNJaxError
    from sgn_jax.experiment_tools import (
        best_checkpoint_step,
        git_commit,
        sha256_file,
        ship_checkpoint,
    )

    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--run", required=True, help="training run directory")
    p.add_argument("--data", required=True, help="comma-separated training files")
    p.add_argument("--train-command", required=True, help="the command that trained it")
    p.add_argument("--results", default=None, help="results.json of run_experiments.py")
    p.add_argument("--case", default="emax_300rpm")
    p.add_argument("--what", default="SGN of the standard case")
    p.add_argument("--manifest", default=None,
                   help="the data manifest.json of generate_data.py (its sha256 is recorded)")
    p.add_argument("--report", action="append", default=[],
                   help="an experiments/envelope/report.py JSON (held-out table); repeatable")
    args = p.parse_args(argv)

    run = Path(args.run)
    try:
        step_dir = best_checkpoint_step(run)
    except SGNJaxError as exc:
        print(f"ship_model: {exc}", file=sys.stderr)
        return 2
    summary = json.loads((run / "summary.json").read_text())
    history = [json.loads(line) for line in (run / "metrics.jsonl").read_text().splitlines()
               if line.strip()]
    best_row = next(r for r in history if r["epoch"] == summary["best_epoch"])
    data_files = [Path(f) for f in args.data.split(",") if f]
    provenance = {
        "what": args.what,
        "train_command": args.train_command,
        "datasets": [{"file": str(f), "sha256": sha256_file(f)} for f in data_files],
        "code_commit_at_training": summary.get("git_commit"),
        "code_commit_at_shipping": git_commit(),
        "best_epoch": summary["best_epoch"],
        "epochs": summary["epochs"],
        "final_losses_best_epoch": {k: best_row.get(k) for k in
                                    ("train_loss", "train_node", "train_global", "val_loss",
                                     "val_node", "val_global")},
        "last_epoch": {k: history[-1].get(k) for k in ("epoch", "train_loss", "val_loss")},
        "n_params": summary["n_params"],
        "n_train": summary["n_train"],
        "n_val": summary["n_val"],
        "train_wall_time_s": sum(r.get("epoch_seconds", 0.0) for r in history),
    }
    if args.manifest:
        provenance["data_manifest"] = {"file": args.manifest, "sha256": sha256_file(args.manifest)}
    config_file = run / "config.toml"
    if config_file.is_file():
        provenance["config"] = config_file.read_text()
    if args.report:
        provenance["held_out_reports"] = [json.loads(Path(r).read_text()) | {"file": r}
                                          for r in args.report]
    if args.results:
        results = json.loads(Path(args.results).read_text())
        provenance["held_out_evaluation"] = {
            "results": args.results, "command": results.get("command"),
            "cases": {name: {"runs": len(c["runs"]),
                             "mse_plateau_m2_mean": c["mse_plateau_m2"]["mean"],
                             "energy_relative_error_final_mean":
                                 c["energy_relative_error_final"]["mean"],
                             "power_relative_error_of_means":
                                 c["ensemble"]["power"]["relative_error_of_means"],
                             "balls_outside_total": c["balls_outside_total"]}
                      for name, c in results["cases"].items()}}

    target = ship_checkpoint(step_dir, args.case, provenance,
                             extra_files=[run / "loss.png", run / "metrics.csv"])
    print(json.dumps({"shipped": str(target), "step": step_dir.name,
                      "best_epoch": provenance["best_epoch"],
                      "val_loss": provenance["final_losses_best_epoch"]["val_loss"]}))
    return 0


if __name__ == "__main__":
    sys.exit(main())
