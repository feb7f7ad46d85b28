"""A trained contact model with the per-contact dissipation target (docs/contact.md, "The
dissipation target"): the same weights, ``[model] damping_target = "contact"``, and the DEM's
tangential damping shares of the records its last stage trained on.

    python experiments/contact/derive_contact_target.py --model RUN_OR_CHECKPOINT --out DIR \
        [--config experiments/contact/rebound_fine_train.toml] [--data data]

The records are the ``records`` globs of the config's last ``[[train.stages]]`` under ``--data``
(by default the model's own config); prints the shares and writes DIR/checkpoints/best.
"""

from __future__ import annotations

import argparse
import glob
import json
import os

import sgn_jax.experiment_tools as tools
from sgn_jax.api import load_config, load_trajectory


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--model", required=True, help="a contact run or checkpoint directory")
    ap.add_argument("--out", required=True, help="the new run directory (must not exist)")
    ap.add_argument("--config", default=None, help="the training config (default: the model's)")
    ap.add_argument("--data", default="data")
    args = ap.parse_args()
    cfg = (load_config(args.config) if args.config
           else tools.load_trained_model(tools.resolve_checkpoint(args.model)).config)
    stage = cfg.train.stages[-1]
    files = sorted({f for pattern in stage.records
                    for f in glob.glob(os.path.join(args.data, pattern))})
    if not files:
        raise SystemExit(f"no records match {stage.records} under {args.data}")
    shares = tools.tangential_damping_shares([load_trajectory(f) for f in files])
    out = tools.derive_contact_model(tools.resolve_checkpoint(args.model), args.out,
                                     shares=shares, damping_target="contact")
    print(json.dumps({"out": out, "records": len(files), "tangential_damping_shares":
                      {"pp": shares[0], "pw": shares[1]}}))


if __name__ == "__main__":
    main()
