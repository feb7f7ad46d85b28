"""Figures of the collision statistics (docs/collisions.md), one per statistic, as PNG.

Each function takes one or more :class:`sgn_jax.analysis.collisions.EnsembleStatistics` (the DEM's
and the surrogate's, drawn on the same axes: DEM in black, surrogate in blue), draws the
ensemble mean with the standard error as error bars (none for an ensemble of one record) and
writes the figure atomically; energies and speeds are on log axes.

- :func:`plot_frequency`: collisions per ball per second, by pair kind (bars);
- :func:`plot_spectrum`: the dissipated-energy or stress-energy spectrum: events/s and W per bin;
- :func:`plot_power_share`: the share of the power from events at or above each energy;
- :func:`plot_impact_speeds`: the impact-speed distribution;
- :func:`plot_dissipation_split`: the normal/tangential split by pair kind (stacked bars);
- :func:`plot_collision_figures`: all of them into one folder.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from sgn_jax.analysis.collisions import KINDS, EnsembleStatistics
from sgn_jax.analysis.plots import new_figure, save_figure

_STYLE = {"dem": {"color": "black", "marker": "s", "label": "DEM"},
          "surrogate": {"color": "tab:blue", "marker": "o", "label": "surrogate"}}


def _ensembles(ensembles: EnsembleStatistics | Sequence[EnsembleStatistics]
               ) -> list[EnsembleStatistics]:
    if isinstance(ensembles, EnsembleStatistics):
        return [ensembles]
    ensembles = list(ensembles)
    if not ensembles or not all(isinstance(e, EnsembleStatistics) for e in ensembles):
        raise ValueError("the collision plots need one or more EnsembleStatistics "
                         "(sgn_jax.analysis.collisions.ensemble_statistics)")
    return ensembles


def _label(ensemble: EnsembleStatistics) -> str:
    return f"{_STYLE[ensemble.source]['label']} ({ensemble.n_records} records)"


def _errors(se: Any) -> Any:
    """Error bars from an SE: None where there is no scatter to draw (one record)."""
    se = np.asarray(se, dtype=np.float64)
    return None if not np.isfinite(se).any() else np.where(np.isfinite(se), se, 0.0)


def _log_errors(mean: np.ndarray, se: Any) -> Any:
    """Error bars on a log axis: the lower bar stops at 10 % of the value (a bar that reaches
    zero has no end on a log axis)."""
    errors = _errors(se)
    if errors is None:
        return None
    return np.stack([np.minimum(errors, 0.9 * mean), errors])


def _centres(edges: np.ndarray) -> np.ndarray:
    """Geometric centres of log bins."""
    return np.sqrt(edges[:-1] * edges[1:])


def plot_frequency(ensembles: EnsembleStatistics | Sequence[EnsembleStatistics],
                   path: str | Path) -> Path:
    """Collisions per ball per second (1/s) for each pair kind, one bar per source, +- SE."""
    ensembles = _ensembles(ensembles)
    fig = new_figure(6.0, 3.8, layout="constrained")
    ax = fig.add_subplot()
    index = np.arange(len(KINDS))
    width = 0.8 / len(ensembles)
    for i, e in enumerate(ensembles):
        values = [e.mean[f"frequency_per_ball_hz[{k}]"] for k in KINDS]
        errors = _errors([e.se[f"frequency_per_ball_hz[{k}]"] for k in KINDS])
        ax.bar(index + (i - (len(ensembles) - 1) / 2) * width, values, width=width,
               yerr=errors, capsize=3, color=_STYLE[e.source]["color"],
               alpha=0.75, label=_label(e))
    ax.set_xticks(index)
    ax.set_xticklabels(KINDS)
    ax.set_ylabel("collisions per ball per second (1/s)")
    ax.set_title("collision frequency by pair kind", fontsize=10)
    ax.legend(fontsize=8)
    ax.grid(True, axis="y", alpha=0.3)
    return save_figure(fig, path)


def plot_spectrum(ensembles: EnsembleStatistics | Sequence[EnsembleStatistics],
                  path: str | Path, *, quantity: str = "dissipation") -> Path:
    """The spectrum of the dissipated energy (``quantity="dissipation"``) or of the stress
    energy (``"stress"``) per collision, on log-log axes: events per second in each bin (left)
    and the power the bin's events dissipated (right, W), +- SE."""
    if quantity not in ("dissipation", "stress"):
        raise ValueError(f"quantity={quantity!r}: use 'dissipation' or 'stress'")
    ensembles = _ensembles(ensembles)
    fig = new_figure(10.0, 4.0, layout="constrained")
    left, right = fig.subplots(1, 2)
    name = ("dissipated energy per collision (J)" if quantity == "dissipation"
            else "stress energy 0.5 m* v_n^2 per collision (J)")
    for ax, key, ylabel, log_y in (
            (left, f"{quantity}_rate_hz", "collisions per second per bin", True),
            (right, f"{quantity}_power_W", "power dissipated per bin (W)", False)):
        for e in ensembles:
            mean = np.asarray(e.mean[key], dtype=np.float64)
            shown = mean > 0  # a log axis has no place for an empty bin
            style = _STYLE[e.source]
            errors = _log_errors(mean, e.se[key]) if log_y else _errors(e.se[key])
            if errors is not None:
                errors = errors[..., shown]
            ax.errorbar(_centres(e.edges)[shown], mean[shown], yerr=errors,
                        color=style["color"], marker=style["marker"], ms=4, lw=1.0,
                        capsize=2, label=_label(e))
        ax.set_xscale("log")
        if log_y:
            ax.set_yscale("log")
        else:  # linear: on equal log bins the area under the points is where the power lies
            ax.set_ylim(bottom=0.0)
        ax.set_xlim(ensembles[0].edges[0], ensembles[0].edges[-1])
        ax.set_xlabel(name)
        ax.set_ylabel(ylabel)
        ax.grid(True, which="both", alpha=0.3)
        ax.legend(fontsize=8)
    fig.suptitle(("dissipated-energy" if quantity == "dissipation" else "stress-energy")
                 + " spectrum", fontsize=11)
    return save_figure(fig, path)


def plot_power_share(ensembles: EnsembleStatistics | Sequence[EnsembleStatistics],
                     path: str | Path) -> Path:
    """The share of the dissipated power delivered by events at or above each energy (log x),
    +- SE, with the chosen threshold and the power above it."""
    ensembles = _ensembles(ensembles)
    fig = new_figure(6.5, 4.0, layout="constrained")
    ax = fig.add_subplot()
    for e in ensembles:
        style = _STYLE[e.source]
        mean = np.asarray(e.mean["share_above_curve"], dtype=np.float64)
        errors = _errors(e.se["share_above_curve"])
        ax.errorbar(e.edges, mean, yerr=errors, color=style["color"], marker=style["marker"],
                    ms=3, lw=1.0, capsize=2,
                    label=f"{_label(e)}: {e.mean['power_above_W']:.3g} W above")
    threshold, by = ensembles[0].threshold, ensembles[0].threshold_by
    ax.axvline(threshold, color="tab:red", ls=":", lw=1.0, label=f"threshold {threshold:g} J")
    ax.set_xscale("log")
    ax.set_ylim(-0.02, 1.02)
    ax.set_xlabel(f"{'dissipated' if by == 'dissipated' else 'stress'} energy threshold (J)")
    ax.set_ylabel("share of the power at or above it")
    ax.set_title("cumulative power above an energy threshold", fontsize=10)
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=8)
    return save_figure(fig, path)


def plot_impact_speeds(ensembles: EnsembleStatistics | Sequence[EnsembleStatistics],
                       path: str | Path) -> Path:
    """The normal impact speed at first touch: events per second in each speed bin (log-log),
    +- SE, with each source's median (dashed)."""
    ensembles = _ensembles(ensembles)
    fig = new_figure(6.5, 4.0, layout="constrained")
    ax = fig.add_subplot()
    for e in ensembles:
        style = _STYLE[e.source]
        mean = np.asarray(e.mean["impact_speed_rate_hz"], dtype=np.float64)
        shown = mean > 0
        errors = _log_errors(mean, e.se["impact_speed_rate_hz"])
        ax.errorbar(_centres(e.speed_edges)[shown], mean[shown],
                    yerr=None if errors is None else errors[..., shown], color=style["color"],
                    marker=style["marker"], ms=4, lw=1.0, capsize=2, label=_label(e))
        median = e.mean["impact_speed_median_m_s[all]"]
        if np.isfinite(median):
            ax.axvline(median, color=style["color"], ls="--", lw=0.8,
                       label=f"{style['label']} median {median:.3g} m/s")
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlabel("normal impact speed at first touch (m/s)")
    ax.set_ylabel("collisions per second per bin")
    ax.set_title("impact-speed distribution", fontsize=10)
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=8)
    return save_figure(fig, path)


def plot_dissipation_split(ensembles: EnsembleStatistics | Sequence[EnsembleStatistics],
                           path: str | Path) -> Path:
    """The share of the dissipated energy in normal damping (impact) and in the tangential
    kinds (shear), per pair kind and source, as stacked bars with the normal share's SE."""
    ensembles = _ensembles(ensembles)
    fig = new_figure(7.0, 3.8, layout="constrained")
    ax = fig.add_subplot()
    labels, position = [], 0
    for kind in KINDS:
        for e in ensembles:
            normal = e.mean[f"normal_share[{kind}]"]
            tangential = e.mean[f"tangential_share[{kind}]"]
            error = _errors([e.se[f"normal_share[{kind}]"]])
            color = _STYLE[e.source]["color"]
            ax.bar(position, normal, color=color, alpha=0.8, yerr=error, capsize=3,
                   label="normal (impact)" if position == 0 else None)
            ax.bar(position, tangential, bottom=normal, color=color, alpha=0.3,
                   hatch="//", label="tangential (shear)" if position == 0 else None)
            labels.append(f"{kind}\n{_STYLE[e.source]['label']}")
            position += 1
    ax.set_xticks(np.arange(position))
    ax.set_xticklabels(labels, fontsize=8)
    ax.set_ylim(0.0, 1.05)
    ax.set_ylabel("share of the dissipated energy")
    ax.set_title("normal / tangential split", fontsize=10)
    ax.legend(fontsize=8, loc="lower right")
    ax.grid(True, axis="y", alpha=0.3)
    return save_figure(fig, path)


FIGURES = ("frequency", "dissipation_spectrum", "stress_spectrum", "power_above",
           "impact_speed", "split")
"""The figures :func:`plot_collision_figures` writes, as ``<name>.png``."""


def plot_collision_figures(ensembles: EnsembleStatistics | Sequence[EnsembleStatistics],
                           out_dir: str | Path) -> dict[str, Path]:
    """Every figure of :data:`FIGURES` into ``out_dir``; returns {name: path}."""
    out_dir = Path(out_dir)
    return {
        "frequency": plot_frequency(ensembles, out_dir / "frequency.png"),
        "dissipation_spectrum": plot_spectrum(ensembles, out_dir / "dissipation_spectrum.png",
                                              quantity="dissipation"),
        "stress_spectrum": plot_spectrum(ensembles, out_dir / "stress_spectrum.png",
                                         quantity="stress"),
        "power_above": plot_power_share(ensembles, out_dir / "power_above.png"),
        "impact_speed": plot_impact_speeds(ensembles, out_dir / "impact_speed.png"),
        "split": plot_dissipation_split(ensembles, out_dir / "split.png"),
    }


__all__ = [
    "FIGURES",
    "plot_collision_figures",
    "plot_dissipation_split",
    "plot_frequency",
    "plot_impact_speeds",
    "plot_power_share",
    "plot_spectrum",
]
