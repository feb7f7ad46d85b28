#!/usr/bin/env python
"""Ship a trained contact model inside the package (``sgn_jax/data/models/NAME/``).

    python experiments/contact/ship_contact.py --run runs/contact_t3 --name contact \\
        --train-command "python experiments/contact/train_contact.py ..." \\
        [--report runs/contact_eval/contact_t3_heldout.json ...]

Copies the run's best checkpoint (``checkpoints/best/<step>``) with its file digests and
writes ``PROVENANCE.json`` beside it: what the model is, the training command, the sha256 of
every training file (from the run's record of them), the commit at training and at shipping,
the run's settings and wall time, and the evaluation reports of
``experiments/contact/evaluate_contact.py`` (their case summaries). The model is loaded back
before the old one is replaced, so a failed copy never leaves the package without a model.
It is then loaded by name: ``sj.load_surrogate("contact")``, ``--checkpoint contact``.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import sgn_jax.api as sj
import sgn_jax.experiment_tools as tools


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--run", required=True)
    p.add_argument("--name", default="contact")
    p.add_argument("--train-command", required=True)
    p.add_argument("--data", default="data/envelope", help="folder of the training files")
    p.add_argument("--report", action="append", default=[])
    p.add_argument("--what", default="contact-impulse surrogate (issue 19), trained over the "
                                     "motion envelope")
    args = p.parse_args(argv)

    run = Path(args.run)
    try:
        step_dir = tools.best_checkpoint_step(run)
    except sj.SGNJaxError as exc:
        print(f"ship_contact: {exc}", file=sys.stderr)
        return 2
    info = json.loads((run / "run_info.json").read_text())
    summary = json.loads((run / "summary.json").read_text())
    # the run's own list of its training files (older runs: the folder's train_*.npz, which
    # must then be what the run read)
    files = [Path(f) for f in info.get("train_files", []) if f] or sorted(
        Path(args.data).glob("train_*.npz"))
    if len(files) != info["n_train_trajectories"]:
        print(f"ship_contact: {len(files)} training files found, the run read "
              f"{info['n_train_trajectories']}", file=sys.stderr)
        return 2
    provenance = {
        "what": args.what,
        "train_command": args.train_command,
        "datasets": [{"file": str(f), "sha256": tools.sha256_file(f)} for f in files],
        "code_commit_at_training": info.get("git_commit"),
        "code_commit_at_shipping": tools.git_commit(),
        "checkpoint_step": int(step_dir.name),
        "run_info": info,
        "steps_done": summary["steps_done"],
        "train_wall_time_s": summary["seconds"],
        "config": (run / "config.toml").read_text(),
        "held_out_reports": [{"file": r, "settings": json.loads(Path(r).read_text()).get("settings"),
                              "summaries": json.loads(Path(r).read_text()).get("summaries")}
                             for r in args.report],
    }
    target = tools.ship_checkpoint(step_dir, args.name, provenance,
                                extra_files=[run / "metrics.csv"])
    print(json.dumps({"shipped": str(target), "step": step_dir.name}))
    return 0


if __name__ == "__main__":
    sys.exit(main())
