"""The ``sgn-jax`` command line.

Each subcommand is registered by a ``_add_<name>`` function below and dispatched to a
``_cmd_<name>`` handler that imports its modules lazily, so ``sgn-jax --help`` stays fast.
Errors that are the user's (bad config, bad file) are printed as one clear line, exit code 2.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from sgn_jax import __version__


class UserError(Exception):
    """An error caused by the user's input; printed without a traceback."""


# --------------------------------------------------------------------------------------------
# jar


def _add_jar(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "jar",
        help="write the jar of a config as an STL mesh and print its volume",
        description="Build the jar of CFG as a watertight mesh, write it as STL and print one "
        "JSON line with volume_ml, watertight and the analytic volume.",
    )
    p.add_argument("--config", required=True, help="experiment config (TOML)")
    p.add_argument("--out", required=True, help="output STL file (m units)")
    p.set_defaults(handler=_cmd_jar)


def _cmd_jar(args: argparse.Namespace) -> int:
    from sgn_jax.config import load_config
    from sgn_jax.geometry import jar_mesh_from_config, mesh_report
    from sgn_jax.io_utils import atomic_write

    cfg = load_config(args.config)
    mesh = jar_mesh_from_config(cfg.jar)
    with atomic_write(args.out, "wb") as fh:
        mesh.export(fh, file_type="stl")
    report = mesh_report(mesh, cfg.jar)
    report["out"] = str(Path(args.out))
    print(json.dumps(report))
    return 0


# --------------------------------------------------------------------------------------------


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="sgn-jax",
        description="Differentiable SDF graph-network surrogate and DEM engine for ball mills.",
    )
    parser.add_argument("--version", action="version", version=f"sgn-jax {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name, fn in sorted(globals().items()):
        if name.startswith("_add_") and callable(fn):
            fn(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if not getattr(args, "handler", None):
        parser.print_help()
        return 0
    from sgn_jax.config import ConfigError

    user_errors: tuple[type[BaseException], ...] = (UserError, ConfigError, FileNotFoundError)
    try:
        from sgn_jax.geometry import GeometryError

        user_errors += (GeometryError,)
    except ImportError:
        pass
    try:
        from sgn_jax.dataset import DatasetError

        user_errors += (DatasetError,)
    except ImportError:
        pass
    try:
        return int(args.handler(args) or 0)
    except user_errors as exc:
        print(f"sgn-jax {args.command}: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"sgn-jax {args.command}: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
