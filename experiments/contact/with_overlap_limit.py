"""A trained contact model with the rigid limit of its contact law switched on (or changed),
no retraining: the same parameters, its config's ``[model] overlap_limit`` (and
``overlap_law_factor``) set (``sj.derive_contact_model``; docs/contact.md, "One step", item 7).

    python experiments/contact/with_overlap_limit.py --model runs/contact_t16 \
        --limit 1e-4 --out runs/contact_t16_lim100

The new checkpoint's meta records where it came from (``derived_from``).
"""
from __future__ import annotations

import argparse

import sgn_jax.experiment_tools as tools


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--model", required=True, help="training run or checkpoint directory")
    ap.add_argument("--limit", type=float, required=True, help="m; 0 = off")
    ap.add_argument("--law-factor", type=float, default=0.0,
                    help="[model] overlap_law_factor: the limit grows with the approach speed "
                         "as this times the DEM law's deepest overlap (0 = off)")
    ap.add_argument("--out", required=True, help="a new run directory")
    args = ap.parse_args()
    try:
        tools.derive_contact_model(args.model, args.out, overlap_limit=args.limit,
                                overlap_law_factor=args.law_factor)
    except (FileExistsError, ValueError) as exc:
        raise SystemExit(str(exc)) from None
    print(f"{args.out}: {args.model} with overlap_limit = {args.limit} m, "
          f"overlap_law_factor = {args.law_factor}")


if __name__ == "__main__":
    main()
