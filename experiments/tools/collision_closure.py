"""How the DEM records' collision events add up to their energy ledgers.

For every trajectory record given, the events' energy per contact type (ball-ball, ball-wall)
and kind (normal, tangential, slip, rolling, stiffness) against the ledger's, relative to the
record's total dissipation; prints the largest difference per kind over the records.

    python experiments/tools/collision_closure.py 'data/envelope/heldout_*.npz'
"""

from __future__ import annotations

import argparse
import glob
import json

import numpy as np

KINDS = ("normal", "tangential", "slip", "rolling", "stiffness")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("records", nargs="+", help="trajectory records (globs)")
    args = ap.parse_args()
    paths = sorted({p for pattern in args.records for p in glob.glob(pattern)})
    if not paths:
        raise SystemExit(f"no records match {args.records}")
    worst = {f"{w}_{k}": 0.0 for w in ("pp", "pw") for k in KINDS}
    for path in paths:
        with np.load(path) as data:
            total = sum(float(np.sum(data[f"diss_{w}_{k}"])) for w in ("pp", "pw") for k in KINDS)
            wall = data["collision_wall"]
            for w, mask in (("pp", ~wall), ("pw", wall)):
                for i, k in enumerate(KINDS):
                    events = float(np.sum(data["collision_energy"][mask, i]))
                    rel = abs(events - float(np.sum(data[f"diss_{w}_{k}"]))) / total
                    worst[f"{w}_{k}"] = max(worst[f"{w}_{k}"], rel)
    print(json.dumps({"records": len(paths), "largest_relative_difference": worst}))


if __name__ == "__main__":
    main()
