#!/usr/bin/env python
"""Copy a trained model into the package (``sgn_jax/data/models/NAME/``) with its provenance.

    python experiments/tools/ship_model.py --run runs/contact_train --name contact \\
        --train-command "sgn-jax train --config contact_train --data data --out runs/contact_train" \\
        [--data data/envelope/train_c00_seed1000.npz,...] \\
        [--report runs/contact_eval/heldout.json ...] [--results runs/experiments/NAME/results.json] \\
        [--manifest data/envelope/manifest.json] [--what "..."]

Replaces the shipped model NAME with the best checkpoint of the training run RUN (its
``checkpoints/best/<step>`` orbax directory, a few hundred kB to a few MB) and writes next to it
``PROVENANCE.json``: what the model is, the training command, the sha256 of every training file,
the commit at training and at shipping, the run's losses, settings and wall time, the run's
config, and the evaluations given:

- ``--report JSON`` (repeatable): a result file of ``experiments/tools/evaluate_contact.py`` or of
  ``experiments/reproduce/envelope_heldout/report.py`` (held-out tables), kept whole with its path;
- ``--results JSON``: a ``results.json`` of ``experiments/tools/run_experiments.py`` (the paper's
  protocol): its command and per case the headline numbers.

Two kinds of run are read. An SGN run of ``sgn-jax train`` (``summary.json`` with epochs and
``metrics.jsonl``): the best and last epochs' losses, parameter and window counts; its training
files are ``--data``. A contact run (``run_info.json`` beside ``summary.json``): the run's own
record of its settings and training files (``--data`` overrides it).

The run's ``loss.png`` and ``metrics.csv`` are copied when present, the step's
``sgn_digest.json`` (sha256 of every file) with it, or written if the run predates it. The new
model is loaded back (every file verified) before the old one is removed, so a failed copy never
leaves the package without a model. It is then loaded by name: ``sgn_jax.load_surrogate(NAME)``,
``--checkpoint NAME``.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import sgn_jax.api as sj
import sgn_jax.experiment_tools as xt


def sgn_provenance(run: Path, summary: dict) -> dict:
    """The training facts of an SGN run of ``sgn-jax train`` (epochs, losses, sizes)."""
    history = [json.loads(line) for line in (run / "metrics.jsonl").read_text().splitlines()
               if line.strip()]
    best_row = next(r for r in history if r["epoch"] == summary["best_epoch"])
    return {
        "code_commit_at_training": summary.get("git_commit"),
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


def contact_provenance(run: Path, summary: dict, info: dict, step_dir: Path) -> dict:
    """The training facts of a contact run (its ``run_info.json`` and ``summary.json``)."""
    return {
        "code_commit_at_training": info.get("git_commit"),
        "checkpoint_step": int(step_dir.name),
        "run_info": info,
        "steps_done": summary.get("steps_done"),
        "train_wall_time_s": summary.get("seconds"),
    }


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--run", required=True, help="training run directory")
    p.add_argument("--name", required=True,
                   help="shipped model name (contact, emax_300rpm, envelope, or a new one)")
    p.add_argument("--train-command", required=True, help="the command that trained it")
    p.add_argument("--data", default=None,
                   help="comma-separated training files (an SGN run: required; a contact run: "
                   "default the run's own record of them)")
    p.add_argument("--what", default=None, help="one line: what the model is")
    p.add_argument("--report", action="append", default=[],
                   help="an evaluation result JSON (evaluate_contact.py or report.py); repeatable")
    p.add_argument("--results", default=None, help="results.json of run_experiments.py")
    p.add_argument("--manifest", default=None,
                   help="the data manifest.json of generate_data.py (its sha256 is recorded)")
    args = p.parse_args(argv)

    run = Path(args.run)
    try:
        step_dir = xt.best_checkpoint_step(run)
    except sj.SGNJaxError as exc:
        print(f"ship_model: {exc}", file=sys.stderr)
        return 2
    summary = json.loads((run / "summary.json").read_text())
    info_path = run / "run_info.json"
    info = json.loads(info_path.read_text()) if info_path.is_file() else None
    if args.data:
        files = [Path(f) for f in args.data.split(",") if f]
    elif info is not None and (info.get("train_files") or info.get("records")):
        # a contact run lists "train_files", a charge run (contact_charge_train_run) "records",
        # a file listed twice (weighted) once
        files = [Path(f) for f in dict.fromkeys(info.get("train_files") or info["records"])]
    else:
        print("ship_model: --data is required (the run does not list its training files)",
              file=sys.stderr)
        return 2
    missing = [str(f) for f in files if not f.is_file()]
    if missing:
        print(f"ship_model: training files not found: {missing[:5]}", file=sys.stderr)
        return 2

    provenance = {
        "what": args.what or ("contact-impulse surrogate" if info is not None else "SGN"),
        "train_command": args.train_command,
        "datasets": [{"file": str(f), "sha256": xt.sha256_file(f)} for f in files],
        "code_commit_at_shipping": xt.git_commit(),
    }
    if info is not None:
        provenance |= contact_provenance(run, summary, info, step_dir)
    else:
        provenance |= sgn_provenance(run, summary)
    if args.manifest:
        provenance["data_manifest"] = {"file": args.manifest,
                                       "sha256": xt.sha256_file(args.manifest)}
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

    extra = [f for f in (run / "loss.png", run / "metrics.csv") if f.is_file()]
    target = xt.ship_checkpoint(step_dir, args.name, provenance, extra_files=extra)
    print(json.dumps({"shipped": str(target), "step": step_dir.name}))
    return 0


if __name__ == "__main__":
    sys.exit(main())
