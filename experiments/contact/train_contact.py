"""Train the contact-impulse surrogate (issue 19) on DEM trajectories of the motion envelope.

    python experiments/contact/train_contact.py --data data/envelope --out runs/contact_a \
        --steps 6000 --minutes 55

Training files: every ``train_*.npz`` of ``--data`` (the envelope's training motions; the
held-out motions and packings are never read), and the files of each ``--also GLOB`` (e.g. the
kicked beds of experiments/contact/kicks.toml: ``--also 'data/kicks/*.npz'``). ``--val`` names files for the validation loss
(default: none). A killed run continues with ``--resume``. The options are recorded in the
run's run_info.json; docs/contact.md has the runs and their numbers.
"""

from __future__ import annotations

import argparse
import glob
import os

import sgn_jax.api as sj
import sgn_jax.experiment_tools as tools

HERE = os.path.dirname(os.path.abspath(__file__))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--config", default=os.path.join(HERE, "contact.toml"))
    ap.add_argument("--data", default="data/envelope")
    ap.add_argument("--pattern", default="train_*.npz")
    ap.add_argument("--also", action="append", default=[],
                    help="glob of further training files (repeatable)")
    ap.add_argument("--val", default="", help="comma-separated validation files")
    ap.add_argument("--out", required=True)
    ap.add_argument("--steps", type=int, default=6000)
    ap.add_argument("--minutes", type=float, default=None)
    ap.add_argument("--batch", type=int, default=32)
    ap.add_argument("--unroll", type=int, default=4)
    ap.add_argument("--pushforward", action="store_true")
    ap.add_argument("--noise", type=float, default=0.0, help="position random-walk std (m)")
    ap.add_argument("--relative-floor", type=float, default=1e-3,
                    help="m/s; per-ball relative loss with this floor (0: squared error)")
    ap.add_argument("--impact-weight", type=float, default=0.0,
                    help="weight of the isolated-impact loss (DEM contact law's answer; 0: off)")
    ap.add_argument("--impacts", type=int, default=64, help="isolated impacts in that loss")
    ap.add_argument("--lr", type=float, default=1e-3)
    ap.add_argument("--lr-final", type=float, default=3e-5)
    ap.add_argument("--hidden", type=int, default=None)
    ap.add_argument("--passes", type=int, default=None,
                    help="impulse passes ([model] interaction_layers; 2: a learned Jacobi pass)")
    ap.add_argument("--spin", action="store_true",
                    help="the balls' spins as rollout state ([model] spin = true)")
    ap.add_argument("--overlap-limit", type=float, default=None,
                    help="m: the rigid limit of the contact law ([model] overlap_limit; 0 = off)")
    ap.add_argument("--overlap-sweeps", type=int, default=None,
                    help="[model] overlap_sweeps: Jacobi sweeps of the limit over all contacts")
    ap.add_argument("--friction-sweeps", type=int, default=None,
                    help="[model] friction_sweeps: projected Jacobi sweeps of Coulomb sticking "
                         "over all contacts (a model with spin)")
    ap.add_argument("--overlap-law-factor", type=float, default=None,
                    help="[model] overlap_law_factor: the limit grows with the approach speed "
                         "as this times the DEM law's deepest overlap (0 = off)")
    ap.add_argument("--spin-weight", type=float, default=1.0,
                    help="weight of the spin error (R |w - w_DEM|) beside the velocity's")
    ap.add_argument("--init", default=None,
                    help="checkpoint directory to warm-start matching parameters from")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--checkpoint-every", type=int, default=250,
                    help="steps between checkpoints (and the log lines)")
    ap.add_argument("--resume", action="store_true")
    ap.add_argument("--no-progress", action="store_true")
    args = ap.parse_args()

    cfg = sj.load_config(args.config)
    if args.hidden is not None:
        cfg = sj.replace_section(cfg, "model", hidden=args.hidden)
    if args.passes is not None:
        cfg = sj.replace_section(cfg, "model", interaction_layers=args.passes)
    if args.spin:
        cfg = sj.replace_section(cfg, "model", spin=True)
    if args.overlap_limit is not None:
        cfg = sj.replace_section(cfg, "model", overlap_limit=args.overlap_limit)
    if args.overlap_sweeps is not None:
        cfg = sj.replace_section(cfg, "model", overlap_sweeps=args.overlap_sweeps)
    if args.friction_sweeps is not None:
        cfg = sj.replace_section(cfg, "model", friction_sweeps=args.friction_sweeps)
    if args.overlap_law_factor is not None:
        cfg = sj.replace_section(cfg, "model", overlap_law_factor=args.overlap_law_factor)
    files = sorted(glob.glob(os.path.join(args.data, args.pattern)))
    if not files:
        raise SystemExit(f"no {args.pattern} files in {args.data}")
    for pattern in args.also:
        more = sorted(glob.glob(pattern))
        if not more:
            raise SystemExit(f"--also {pattern!r} matches no file")
        files += more
    print(f"{len(files)} training files")
    trajs = [sj.load_trajectory(f) for f in files]
    val = [sj.load_trajectory(f) for f in args.val.split(",") if f]
    summary = tools.train_contact(
        cfg, trajs, args.out, val_trajectories=val, steps=args.steps, batch_size=args.batch,
        unroll=tools.UnrollSpec(unroll=args.unroll, pushforward=args.pushforward,
                             position_noise=args.noise,
                             relative_floor=args.relative_floor,
                             spin_weight=args.spin_weight),
        lr_init=args.lr, lr_final=args.lr_final, seed=args.seed, minutes=args.minutes,
        impact_weight=args.impact_weight, n_impacts=args.impacts, init_from=args.init,
        checkpoint_every=args.checkpoint_every,
        resume=args.resume, progress=not args.no_progress)
    print({k: summary[k] for k in ("steps_done", "best_loss", "seconds")})


if __name__ == "__main__":
    main()
