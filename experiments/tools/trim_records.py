"""Copies of DEM records cut to their first window: what a rollout from the first window needs.

    python experiments/tools/trim_records.py DATA OUT --window 7 --dt 2e-4
    python experiments/tools/trim_records.py DATA OUT --model runs/contact_charge/touch [...] \
        [--names heldout_00 ...] [--seeds 104 ...]

Every record ``DATA/NAME/seed_K.npz`` is written to ``OUT/NAME/seed_K.npz`` in the same format
(``sgn_jax.records.trajectory``; every array per sample, the meta and its config) with only its
first samples: ``window + 2`` at the surrogate's step ``dt`` (a record sampled finer, 1e-4 s
against the 2e-4 s contact models, keeps ``(window + 1) * factor + 1`` of its own samples, so
``load_trajectory(path).at_step(dt)`` gives the full record's first ``window + 2`` samples
exactly). With ``--model`` (repeatable) the window and step are the models' (the most samples
any of them needs). The collision table (one row per contact event) is left out, as
``Trajectory.slice`` does.

A trimmed record is rolled out by experiments/charges/evaluate.py from its first window with
``--dem-reference`` an evaluation of the full record (the DEM's numbers and the steps): a
later model is evaluated on packings made elsewhere without moving the full records. Prints
one line per record (samples kept, size).
"""

from __future__ import annotations

import argparse
from pathlib import Path

import sgn_jax.api as sj


def kept_samples(window: int, dt: float, record_dt: float) -> int:
    """The record samples (at ``record_dt``, s) that hold ``window + 2`` samples at the
    surrogate's step ``dt`` (s), an integer multiple of ``record_dt``."""
    factor = max(1, round(dt / record_dt))
    return (window + 1) * factor + 1


def trim_record(src: str | Path, dst: str | Path, needs: list[tuple[int, float]]) -> int:
    """Write ``src``'s first samples to ``dst``: the most :func:`kept_samples` of any
    ``(window, dt)`` in ``needs``; returns how many."""
    traj = sj.load_trajectory(src)
    n = max(kept_samples(window, dt, traj.dt) for window, dt in needs)
    if n > traj.n_samples:
        raise SystemExit(f"{src} has {traj.n_samples} samples, fewer than the {n} to keep")
    part = traj.slice(0, n)
    Path(dst).parent.mkdir(parents=True, exist_ok=True)
    sj.save_trajectory(dst, part.arrays, part.meta)
    return n


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("data", help="folder of NAME/seed_K.npz records")
    ap.add_argument("out", help="folder for the trimmed copies (same layout)")
    ap.add_argument("--window", type=int, default=None, help="surrogate window (samples)")
    ap.add_argument("--dt", type=float, default=None, help="surrogate step (s)")
    ap.add_argument("--model", action="append", default=[],
                    help="a checkpoint whose window and step to keep (repeatable)")
    ap.add_argument("--names", nargs="*", default=None, help="only these NAME folders")
    ap.add_argument("--seeds", type=int, nargs="*", default=None, help="only these seeds")
    args = ap.parse_args()
    needs = []   # (window, dt) pairs
    if args.window is not None or args.dt is not None:
        if args.window is None or args.dt is None:
            ap.error("--window and --dt go together")
        needs.append((args.window, args.dt))
    if args.model:
        from sgn_jax.experiment_tools import load_trained_model, resolve_checkpoint
        for path in args.model:
            cfg = load_trained_model(resolve_checkpoint(path), which="latest").config
            needs.append((int(cfg.graph.window), float(cfg.dem.dt)))
    if not needs:
        ap.error("give --window and --dt, or --model")
    data, out = Path(args.data), Path(args.out)
    records = [r for r in sorted(data.glob("*/seed_*.npz"))
               if (args.names is None or r.parent.name in args.names)
               and (args.seeds is None or int(r.stem.split("_")[1]) in args.seeds)]
    if not records:
        raise SystemExit(f"no records DATA/NAME/seed_K.npz (of the names and seeds) under {data}")
    for src in records:
        dst = out / src.relative_to(data)
        n = trim_record(src, dst, needs)
        print(f"{dst}: {n} samples, {dst.stat().st_size / 1e3:.0f} kB", flush=True)


if __name__ == "__main__":
    main()
