"""The pieces that the experiment scripts share (``experiments/tools/run_experiments.py``,
``experiments/tools/generate_data.py``, ``experiments/tools/evaluate_contact.py``,
``experiments/reproduce/envelope_heldout/evaluate_model.py``): how to start the ``sgn-jax`` CLI
in a subprocess
and on which cores, how to read the JSON summary line it prints, and the planning and summary
steps of a model's evaluation on an ensemble (rollout length, ``[rollout]`` overrides, the
per-case result). Exposed through :mod:`sgn_jax.experiment_tools`.
"""

from __future__ import annotations

import dataclasses
import json
import math
import os
import shutil
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from sgn_jax.analysis.metrics import headline
from sgn_jax.config import RolloutConfig, load_config, replace_section, save_config
from sgn_jax.errors import SGNJaxError
from sgn_jax.records.prediction import PredictionError, load_prediction


class ExperimentError(SGNJaxError, ValueError):
    """A bad argument or missing input; the message says what and how to fix it."""


# --------------------------------------------------------------------------------------------
# Subprocesses of the CLI


def sgn_jax_command() -> list[str]:
    """How to call the CLI: this interpreter's ``sgn-jax`` script, else ``python -m``."""
    script = Path(sys.executable).with_name("sgn-jax")
    if script.is_file():
        return [str(script)]
    found = shutil.which("sgn-jax")
    return [found] if found else [sys.executable, "-m", "sgn_jax.cli"]


def usable_cores() -> list[int]:
    try:
        return sorted(os.sched_getaffinity(0))
    except AttributeError:  # not Linux
        return list(range(os.cpu_count() or 1))


def last_json_line(path: Path, offset: int = 0, key: str = "total_dissipation_J"
                   ) -> dict[str, Any] | None:
    """The last JSON object with ``key`` in the log ``path`` after byte ``offset`` (the summary
    line a ``sgn-jax`` command prints: ``dem`` has total_dissipation_J, ``rollout`` ms_per_step)."""
    with open(path, "rb") as fh:
        fh.seek(offset)
        text = fh.read().decode("utf-8", "replace")
    for line in reversed(text.splitlines()):
        line = line.strip()
        if line.startswith("{"):
            try:
                data = json.loads(line)
            except ValueError:
                continue
            if isinstance(data, dict) and key in data:
                return data
    return None


# --------------------------------------------------------------------------------------------
# A model's evaluation on an ensemble


def rollout_duration(reference: Path, window: int, dt: float, save_every: int) -> float:
    """Seconds of rollout that the DEM file ``reference`` covers from its first full window.

    The rollout starts at sample ``window`` (time ``t[window]``) and runs whole multiples of
    ``save_every`` steps of ``dt`` up to the reference's last sample.
    """
    with np.load(reference, allow_pickle=False) as data:
        t = np.asarray(data["t"])
    span = float(t[-1] - t[window])
    block = save_every * dt
    blocks = math.floor(span / block + 1e-6)
    if blocks < 1:
        raise ExperimentError(f"{reference}: covers only {span:.4g} s after its first window; "
                              f"a rollout needs at least {block:.4g} s")
    return round(blocks * block, 9)


def prediction_ok(path: Path) -> bool:
    """Whether ``path`` is a prediction file that loads (a finished rollout)."""
    if not path.is_file():
        return False
    try:
        load_prediction(path)
    except (PredictionError, OSError, ValueError):
        return False
    return True


def parse_rollout_settings(items: Sequence[str]) -> dict[str, Any]:
    """``["pp_separation=false", "pp_max_overlap=1e-4"]`` -> typed [rollout] field values."""
    fields = {f.name: f for f in dataclasses.fields(RolloutConfig)}
    out: dict[str, Any] = {}
    for item in items:
        key, sep, text = item.partition("=")
        key = key.strip()
        if not sep or key not in fields:
            raise ExperimentError(f"--rollout {item!r}: expected KEY=VALUE with KEY one of "
                                  f"{sorted(fields)}")
        kind = type(getattr(RolloutConfig(), key))
        text = text.strip()
        if kind is bool:
            if text.lower() not in ("true", "false"):
                raise ExperimentError(f"--rollout {item!r}: {key} takes true or false")
            out[key] = text.lower() == "true"
        else:
            try:
                out[key] = kind(text)
            except ValueError as exc:
                raise ExperimentError(f"--rollout {item!r}: {key} takes a {kind.__name__}") \
                    from exc
    return out


def case_config(case: Any, settings: dict[str, Any], out: Path) -> Path:
    """The config a case's rollouts use: the case's own, or a copy with ``settings`` applied
    to its [rollout] section, written to ``OUT/configs/{case}.toml``."""
    if not settings:
        return case.config_path
    cfg = replace_section(load_config(case.config_path), "rollout", **settings)
    path = out / "configs" / f"{case.name}.toml"
    save_config(cfg, path)
    return path


def _stats(values: Sequence[float | None]) -> dict[str, Any]:
    vals = [float(v) for v in values if v is not None and np.isfinite(v)]
    if not vals:
        return {"n": 0, "mean": None, "min": None, "max": None}
    return {"n": len(vals), "mean": float(np.mean(vals)), "median": float(np.median(vals)),
            "min": float(np.min(vals)), "max": float(np.max(vals))}


def case_result(case: Any, seeds: Sequence[int], out: Path) -> dict[str, Any]:
    """The summary of one case from its rollout JSON lines and its evaluation files."""
    eval_dir = out / "eval" / case.name
    ensemble = json.loads((eval_dir / "ensemble.json").read_text())
    runs = []
    for i, seed in enumerate(seeds):
        metrics = json.loads((eval_dir / f"run_{i:02d}" / "metrics.json").read_text())
        roll_json = out / "rollouts" / f"{case.name}_seed{seed}.json"
        roll = json.loads(roll_json.read_text()) if roll_json.is_file() else {}
        runs.append({"seed": seed, **headline(metrics), "ms_per_step": roll.get("ms_per_step"),
                     "metrics": str(eval_dir / f"run_{i:02d}" / "metrics.json")})
    return {
        "case": case.name,
        "description": case.description,
        "config": str(case.config_path),
        "seeds": list(seeds),
        "runs": runs,
        "mse_plateau_m2": _stats([r["mse_plateau_m2"] for r in runs]),
        "energy_relative_error_final": _stats([r["energy_relative_error_final"] for r in runs]),
        "abs_energy_relative_error_final": _stats(
            [abs(r["energy_relative_error_final"]) for r in runs
             if r["energy_relative_error_final"] is not None]),
        "pearson_r": _stats([r["pearson_r"] for r in runs]),
        "balls_outside_total": int(sum(r["balls_outside_total"] or 0 for r in runs)),
        "overflow_total": int(sum(r["overflow_total"] or 0 for r in runs)),
        "ms_per_step": _stats([r["ms_per_step"] for r in runs]),
        "ensemble": ensemble,
        "ensemble_file": str(eval_dir / "ensemble.json"),
    }


__all__ = [
    "ExperimentError",
    "case_config",
    "case_result",
    "last_json_line",
    "parse_rollout_settings",
    "prediction_ok",
    "rollout_duration",
    "sgn_jax_command",
    "usable_cores",
]
