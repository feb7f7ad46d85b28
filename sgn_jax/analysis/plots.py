"""Figures in the paper's style (section 3, Figs. 7 and 8), written as PNG.

Uses matplotlib's object API with the Agg canvas (``matplotlib.figure.Figure``, no pyplot), so
nothing global is touched and no display is needed. Every function writes its file atomically
and returns the path.

- :func:`plot_position_mse`: MSE_t over time on a log axis (Fig. 7).
- :func:`plot_cumulative_energy`: predicted vs DEM cumulative dissipation, with the relative
  error in a second panel (Fig. 8); the prediction may run on past the reference.
- :func:`plot_ensemble`: per-run dissipation power, predicted vs DEM, and power vs contact
  count (the two docs/conventions.md section 7 states).
- :func:`plot_trajectory_xz`: a top view (x-z) of the balls at one frame, with the jar outline
  and a legend (model balls, DEM balls, the line joining the same ball of both, the jar).
- :func:`plot_run`: all single-run figures from a ``sgn_jax.analysis.metrics.Comparison``.
- :func:`plot_case_curves`: all runs of an ensemble case in one figure (energy and MSE_t).
- :func:`new_figure`, :func:`save_figure`: the figure and the file writer every plot here uses,
  for scripts that draw their own figures.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure
from matplotlib.patches import Circle

from sgn_jax.analysis.metrics import align, position_mse, relative_error
from sgn_jax.records.io_utils import atomic_write
from sgn_jax.records.prediction import load_prediction
from sgn_jax.records.trajectory import load_trajectory

_DPI = 150
_PRED_COLOR = "tab:blue"
_REF_COLOR = "black"


def new_figure(width: float, height: float, **kwargs: Any) -> Figure:
    """A matplotlib ``Figure`` of ``width`` x ``height`` inches on the Agg canvas (no pyplot,
    no display); ``kwargs`` go to ``Figure`` (e.g. ``layout="constrained"``)."""
    fig = Figure(figsize=(width, height), **kwargs)
    FigureCanvasAgg(fig)
    return fig


def save_figure(fig: Figure, path: str | Path) -> Path:
    """Write ``fig`` to ``path`` (a ``.png``) atomically at the package's resolution; returns
    the path."""
    path = Path(path)
    if path.suffix.lower() != ".png":
        raise ValueError(f"plot path {str(path)!r} must end in '.png'")
    with atomic_write(path, "wb") as fh:
        fig.savefig(fh, format="png", dpi=_DPI)
    return path


def _as_1d(values: Any, name: str) -> np.ndarray:
    array = np.asarray(values, dtype=np.float64)
    if array.ndim != 1:
        raise ValueError(f"{name} must be 1-D, got shape {array.shape}")
    return array


def plot_position_mse(t: Any, mse: Any, path: str | Path, *, plateau: float | None = None,
                      title: str | None = None) -> Path:
    """MSE_t (m^2) against time (s) on a log y axis, as paper Fig. 7.

    Args:
        t: (P,) s; mse: (P,) m^2 (NaN or values <= 0, e.g. the exact start frame, are not
            drawn on the log axis); plateau: drawn as a dashed line if given.
    """
    t, mse = _as_1d(t, "t"), _as_1d(mse, "mse")
    if t.shape != mse.shape:
        raise ValueError(f"t and mse must have the same length, got {t.size} and {mse.size}")
    fig = new_figure(7.0, 3.6, layout="constrained")
    ax = fig.add_subplot()
    shown = np.where(np.isfinite(mse) & (mse > 0), mse, np.nan)
    ax.plot(t, shown, color=_PRED_COLOR, lw=1.0, label=r"MSE$_t$ (model vs DEM)")
    if plateau is not None and math.isfinite(plateau) and plateau > 0:
        ax.axhline(plateau, color="tab:red", ls="--", lw=1.0,
                   label=f"plateau (median, last half) = {plateau:.3g} m$^2$")
    ax.set_yscale("log")
    ax.set_xlabel("time since start of motion (s)")
    ax.set_ylabel(r"position MSE$_t$ (m$^2$)")
    ax.set_title(title or "Position error of the recursive rollout")
    ax.grid(True, which="both", alpha=0.3)
    if np.isfinite(shown).any():
        ax.legend(loc="lower right")
    else:
        ax.text(0.5, 0.5, "no positive MSE values to draw", transform=ax.transAxes,
                ha="center")
    return save_figure(fig, path)


def plot_cumulative_energy(t: Any, e_pred: Any, e_ref: Any, path: str | Path, *,
                           title: str | None = None) -> Path:
    """Cumulative dissipated energy, model vs DEM (paper Fig. 8), and the relative error.

    Args:
        t: (S,) s; e_pred: (S,) J; e_ref: (S,) J, NaN where the reference does not cover the
            prediction (the prediction is drawn on, the reference stops, as in Fig. 8).
    """
    t, e_pred, e_ref = _as_1d(t, "t"), _as_1d(e_pred, "e_pred"), _as_1d(e_ref, "e_ref")
    if not t.shape == e_pred.shape == e_ref.shape:
        raise ValueError(f"t, e_pred and e_ref must have the same length, got {t.size}, "
                         f"{e_pred.size} and {e_ref.size}")
    fig = new_figure(7.0, 5.2, layout="constrained")
    top, bottom = fig.subplots(2, 1, sharex=True, height_ratios=[2.2, 1.0])
    top.plot(t, e_ref, color=_REF_COLOR, lw=1.4, label="DEM (normal + tangential damping)")
    top.plot(t, e_pred, color=_PRED_COLOR, lw=1.2, ls="--", label="model prediction")
    covered = np.flatnonzero(np.isfinite(e_ref))
    if covered.size and covered[-1] < t.size - 1:
        top.axvline(t[covered[-1]], color="grey", ls=":", lw=1.0)
        top.text(t[covered[-1]], 0.02, " DEM reference ends", transform=top.get_xaxis_transform(),
                 color="grey", fontsize=8)
    top.set_ylabel("cumulative dissipated energy (J)")
    top.set_title(title or "Cumulative energy dissipation: model vs DEM")
    top.grid(True, alpha=0.3)
    top.legend(loc="upper left")

    rel = 100.0 * relative_error(e_pred, e_ref)
    bottom.plot(t, rel, color="tab:red", lw=1.0)
    finite = rel[np.isfinite(rel)]
    if finite.size:
        final = finite[-1]
        bottom.axhline(final, color="tab:red", ls=":", lw=0.8)
        bottom.set_title(f"relative error |E_pred - E_ref| / E_ref, final {final:.2f} %",
                         fontsize=9)
        # The first steps divide by a tiny E_ref; clip the axis to the settled part.
        settled = finite[finite.size // 10:]
        bottom.set_ylim(0.0, max(1.0, 1.2 * float(np.max(settled))))
    bottom.set_xlabel("time since start of motion (s)")
    bottom.set_ylabel("relative error (%)")
    bottom.grid(True, alpha=0.3)
    return save_figure(fig, path)


def plot_ensemble(summary: Mapping[str, Any], path: str | Path, *,
                  title: str | None = None) -> Path:
    """Per-run mean dissipation power (model vs DEM) and power vs contact count, by state.

    Args:
        summary: the dict from ``sgn_jax.analysis.metrics.ensemble_summary``.
    """
    rows = summary.get("runs")
    if not rows:
        raise ValueError("plot_ensemble needs the dict from "
                         "sgn_jax.analysis.metrics.ensemble_summary (with a non-empty 'runs' list)")

    def column(key: str) -> np.ndarray:
        return np.asarray([np.nan if r[key] is None else r[key] for r in rows], dtype=np.float64)

    p_pred, p_ref = column("power_pred_W"), column("power_ref_W")
    states = summary.get("states", {})
    by_speed = states.get("classify_by") == "speed" and all(
        "jar_speed_ref_mean_m_s" in r for r in rows)
    if by_speed:  # the state rule's own indicator on the x axis
        c_pred, c_ref = column("jar_speed_pred_mean_m_s"), column("jar_speed_ref_mean_m_s")
        ref_label, pred_label = "DEM", "model"
        x_label = "mean ball speed in the jar frame (m/s)"
    else:
        c_pred, c_ref = column("pp_contacts_pred_mean"), column("pp_pairs_within_skin_ref_mean")
        ref_label, pred_label = "DEM (pairs within skin)", "model (edges / 2)"
        x_label = "mean ball pairs within the edge skin"
    fig = new_figure(10.0, 4.2, layout="constrained")
    left, right = fig.subplots(1, 2)

    index = np.arange(len(rows))
    left.bar(index - 0.2, p_ref, width=0.4, color="grey", label="DEM")
    left.bar(index + 0.2, p_pred, width=0.4, color=_PRED_COLOR, label="model")
    for spread, color, name in ((summary["power"]["ref_W"], "black", "DEM"),
                                (summary["power"]["pred_W"], _PRED_COLOR, "model")):
        if spread["mean"] is not None:
            left.axhline(spread["mean"], color=color, ls="--", lw=1.0,
                         label=f"{name} mean {spread['mean']:.3g} +- {spread['std']:.2g} W")
            left.axhspan(spread["mean"] - spread["std"], spread["mean"] + spread["std"],
                         color=color, alpha=0.08)
    left.set_xticks(index)
    left.set_xticklabels([str(i) for i in index])
    left.set_xlabel("run")
    left.set_ylabel("mean dissipation power (W)")
    rel = summary["power"].get("relative_error_of_means")
    left.set_title("dissipation power per run" + (f" (ensemble means differ by {100 * rel:.1f} %)"
                                                   if rel is not None else ""), fontsize=10)
    left.set_ylim(0.0, 1.35 * float(np.nanmax(np.concatenate([p_ref, p_pred, [1e-30]]))))
    left.legend(loc="upper left", fontsize=8, ncols=2)
    left.grid(True, axis="y", alpha=0.3)

    right.scatter(c_ref, p_ref, marker="s", color="grey", label=ref_label)
    right.scatter(c_pred, p_pred, marker="o", color=_PRED_COLOR, label=pred_label)
    for i in index:
        if np.isfinite([c_ref[i], p_ref[i], c_pred[i], p_pred[i]]).all():
            right.plot([c_ref[i], c_pred[i]], [p_ref[i], p_pred[i]], color="grey", lw=0.5)
    if by_speed:
        right.axvline(states["threshold"], color="tab:red", ls=":", lw=1.0)
        right.set_title(f"agitated if speed >= {states['threshold']:g} m/s (dotted), else bed",
                        fontsize=10)
    elif states.get("classify_by") == "contacts":
        ball_counts = {r.get("n_balls") for r in rows}
        if len(ball_counts) == 1 and None not in ball_counts:
            # the threshold is per ball; in pairs it is threshold * N when all runs share N
            right.axvline(states["threshold"] * ball_counts.pop(), color="tab:red", ls=":",
                          lw=1.0)
        right.set_title(f"bed if pairs per ball >= {states['threshold']:g} (dotted), else "
                        "agitated", fontsize=10)
    elif states.get("classify_by") == "power":
        right.axhline(states["threshold"], color="tab:red", ls=":", lw=1.0)
        right.set_title(f"agitated if power >= {states['threshold']:g} W", fontsize=10)
    right.set_xlim(left=0.0)
    right.set_xlabel(x_label)
    right.set_ylabel("mean dissipation power (W)")
    right.legend(loc="best")
    right.grid(True, alpha=0.3)
    fig.suptitle(title or f"Ensemble of {len(rows)} runs")
    return save_figure(fig, path)


def _stadium_outline(jar: Any, offset_xz: tuple[float, float]) -> tuple[np.ndarray, np.ndarray]:
    """x, z of the Emax stadium cross-section (semicircles at x = +-L/2), shifted by offset."""
    radius, half = float(jar.radius), 0.5 * float(jar.straight_length)
    angle_right = np.linspace(-0.5 * np.pi, 0.5 * np.pi, 60)
    angle_left = angle_right + np.pi
    x = np.concatenate([half + radius * np.cos(angle_right), -half + radius * np.cos(angle_left),
                        [half]])
    z = np.concatenate([radius * np.sin(angle_right), radius * np.sin(angle_left), [-radius]])
    return x + offset_xz[0], z + offset_xz[1]


def plot_trajectory_xz(pos: Any, path: str | Path, *, ref_pos: Any = None, offset: Any = None,
                       jar: Any = None, ball_radius: float = 0.005,
                       title: str | None = None) -> Path:
    """Top view (x horizontal, z vertical) of the balls at one frame, with a legend.

    Drawn: the surrogate's balls (filled blue discs); with ``ref_pos``, the DEM's balls at the
    same time (open black circles) and a grey line from each model ball to the same ball (by
    index) of the DEM, whose length is that ball's position error; for an Emax jar its
    stadium cross-section (and post) at the jar offset. The legend under the axes says so.

    Args:
        pos: (N, 3) predicted positions (m); ref_pos: (N, 3) DEM positions at the same time,
            drawn as open circles with a line to the matching predicted ball;
        offset: (3,) jar offset (m) at that time; jar: a ``sgn_jax.config.JarConfig`` with
            kind "emax" to draw the cavity outline (and post); ball_radius: m.
    """
    from matplotlib.lines import Line2D

    pos = np.asarray(pos, dtype=np.float64)
    if pos.ndim != 2 or pos.shape[1] != 3:
        raise ValueError(f"pos must be (N, 3) positions of one frame, got {pos.shape}")
    offset_xz = (0.0, 0.0) if offset is None else (float(offset[0]), float(offset[2]))
    fig = new_figure(6.4, 4.6, layout="constrained")
    ax = fig.add_subplot()
    handles = [Line2D([], [], ls="none", marker="o", ms=9, mfc=_PRED_COLOR, mec=_PRED_COLOR,
                      alpha=0.6, label=f"model ball ({len(pos)})")]
    emax = jar is not None and getattr(jar, "kind", None) == "emax"
    if emax:
        x, z = _stadium_outline(jar, offset_xz)
        ax.plot(x, z, color="dimgrey", lw=1.5)
        if float(jar.post_radius) > 0:
            ax.add_patch(Circle(offset_xz, float(jar.post_radius), color="dimgrey", alpha=0.5))
    if ref_pos is not None:
        ref_pos = np.asarray(ref_pos, dtype=np.float64)
        if ref_pos.shape != pos.shape:
            raise ValueError(f"ref_pos must have the shape of pos {pos.shape}, got "
                             f"{ref_pos.shape}")
        for p, r in zip(pos, ref_pos, strict=True):
            ax.add_patch(Circle((r[0], r[2]), ball_radius, fill=False, ec=_REF_COLOR, lw=0.8))
            ax.plot([p[0], r[0]], [p[2], r[2]], color="grey", lw=0.5)
        handles += [
            Line2D([], [], ls="none", marker="o", ms=9, mfc="none", mec=_REF_COLOR,
                   label="DEM ball, same time"),
            Line2D([], [], color="grey", lw=0.8,
                   label="same ball, model to DEM (length: its position error)")]
    if emax:
        handles.append(Line2D([], [], color="dimgrey", lw=1.5,
                              label="jar cross-section (at its offset)"))
    for p in pos:
        ax.add_patch(Circle((p[0], p[2]), ball_radius, color=_PRED_COLOR, alpha=0.6))
    points = pos if ref_pos is None else np.concatenate([pos, ref_pos])
    extent = ball_radius * 1.5
    if emax:
        extent = max(extent, float(jar.radius) * 1.1)
        x_span = 0.5 * float(jar.straight_length) + 1.1 * float(jar.radius)
        ax.set_xlim(offset_xz[0] - x_span, offset_xz[0] + x_span)
        ax.set_ylim(offset_xz[1] - extent, offset_xz[1] + extent)
    else:
        ax.set_xlim(points[:, 0].min() - extent, points[:, 0].max() + extent)
        ax.set_ylim(points[:, 2].min() - extent, points[:, 2].max() + extent)
    ax.set_aspect("equal")
    ax.set_xlabel("x (m), lab frame")
    ax.set_ylabel("z (m), lab frame")
    legend = "filled: model" + ("; open: DEM" if ref_pos is not None else "")
    ax.set_title(title or f"Top view ({legend})", fontsize=10)
    ax.grid(True, alpha=0.3)
    caption = "balls projected along the vertical (y) onto the x-z plane"
    if ref_pos is not None:
        caption += "; model and DEM balls matched by index"
    fig.legend(handles=handles, loc="outside lower center", ncols=2, fontsize=8, frameon=False,
               title=caption, title_fontsize=8)
    return save_figure(fig, path)


def plot_run(comparison: Any, prediction: Any, reference: Any, out_dir: str | Path
             ) -> dict[str, str]:
    """Write position_mse.png, cumulative_energy.png and trajectory_xz.png (last compared
    frame) for one run into ``out_dir``; returns name -> path."""
    out_dir = Path(out_dir)
    summary = comparison.summary
    paths: dict[str, str] = {}
    position = summary.get("position")
    paths["position_mse"] = str(plot_position_mse(
        comparison.t_pos, comparison.mse, out_dir / "position_mse.png",
        plateau=None if position is None else position["mse_plateau_m2"]))
    paths["cumulative_energy"] = str(plot_cumulative_energy(
        comparison.t_step, comparison.energy_pred, comparison.energy_ref,
        out_dir / "cumulative_energy.png"))
    frames = comparison.alignment.frame_index
    frame = int(frames[-1]) if frames.size else prediction.n_frames - 1
    ref_frame = (reference.pos[int(comparison.alignment.frame_ref_index[-1])]
                 if frames.size else None)
    paths["trajectory_xz"] = str(plot_trajectory_xz(
        prediction.pos[frame], out_dir / "trajectory_xz.png", ref_pos=ref_frame,
        offset=prediction.offset[frame], jar=prediction.config.jar,
        ball_radius=float(reference.meta["ball_radius"]),
        title=f"Top view at t = {float(prediction.t_pos[frame]):.4g} s (filled: model"
              + ("; open: DEM)" if ref_frame is not None else ")")))
    return paths


def plot_sensitivity(result: Mapping[str, Any], path: str | Path) -> Path:
    """Power vs each design parameter around the design point (``sgn_jax.api.sensitivity``).

    One panel per parameter: the surrogate's ensemble-mean power at theta - h, theta, theta + h
    (error bars: standard error over the packings), and the tangent of the estimated gradient
    through the design point (shaded: +- its standard error); with the DEM's difference
    (``sensitivity(..., dem=True)``) also the DEM's ensemble-mean power at theta -+ h.
    """
    names = list(result["names"])
    fig = new_figure(4.2 * len(names), 3.6, layout="constrained")
    axes = fig.subplots(1, len(names), squeeze=False)[0]
    for ax, i_name in zip(axes, enumerate(names), strict=True):
        i, name = i_name
        x0, p0 = float(result["theta0"][i]), float(result["power_W"])
        unit = result["units"][name]
        curve = result.get("curves", {}).get(name)
        h = curve["h"] if curve else 0.1 * (abs(x0) or 1.0)
        if curve:
            ax.errorbar(curve["theta"], curve["power_W"], yerr=curve["power_se_W"], fmt="o",
                        color=_PRED_COLOR, capsize=3, label="surrogate ensemble mean (+-SE)")
        else:
            ax.errorbar([x0], [p0], yerr=[result["power_se_W"]], fmt="o", color=_PRED_COLOR,
                        capsize=3, label="surrogate ensemble mean (+-SE)")
        dem = result.get("dem", {}).get(name)
        if dem:
            ax.errorbar(dem["theta"], dem["power_W"], yerr=dem["power_se_W"], fmt="s",
                        color=_REF_COLOR, capsize=3, label=f"DEM ensemble mean (+-SE): "
                        f"{dem['central_difference']:.3g} +- {dem['central_difference_se']:.2g} "
                        f"W/{unit}")
        g, se = float(result["gradient"][name]), float(result["gradient_se"][name])
        xs = np.array([x0 - h, x0 + h])
        ax.plot(xs, p0 + g * (xs - x0), "-", color="tab:red",
                label=f"gradient {g:.3g} +- {se:.2g} W/{unit}")
        if np.isfinite(se):
            ax.fill_between(xs, p0 + (g - se) * (xs - x0), p0 + (g + se) * (xs - x0),
                            color="tab:red", alpha=0.15, linewidth=0)
        ax.axvline(x0, color="0.6", linewidth=0.8, linestyle=":")
        ax.set_xlabel(f"{name} [{unit}]")
        ax.set_ylabel("mean dissipation power [W]")
        ax.set_title(f"{name} = {x0:.4g} {unit}", fontsize=9)
        ax.legend(fontsize=7, loc="best")
    fig.suptitle(f"Design sensitivity: {len(result['seeds'])} packings, power over "
                 f"{result['burn_in_s']:g}-{result['duration_s']:g} s", fontsize=10)
    return save_figure(fig, path)


def plot_case_curves(title: str, preds: Sequence[str | Path], refs: Sequence[str | Path],
                     labels: Sequence[str], path: str | Path) -> Path:
    """All runs of a case in one figure: cumulative dissipated energy (DEM dashed, model solid)
    and the position MSE_t (paper Eq. 33), with the paper's ~2e-4 m^2 plateau for scale."""
    fig = new_figure(10.0, 7.0, layout="constrained")
    top, bottom = fig.subplots(2, 1, sharex=True)
    colors = [f"C{i % 10}" for i in range(len(preds))]
    for pred_path, ref_path, label, color in zip(preds, refs, labels, colors, strict=True):
        pred, ref = load_prediction(pred_path), load_trajectory(ref_path)
        al = align(pred, ref)
        cum = np.asarray(ref.cumulative_dissipation("normal+tangential", "pp+pw"))
        zero = cum[al.start_ref_index] if al.start_ref_index >= 0 else cum[al.step_ref_index[0]]
        t = np.asarray(pred.t_step)[al.step_index]
        top.plot(t, np.asarray(pred.energy_cum)[al.step_index], color=color, lw=1.0,
                 label=label)
        top.plot(t, cum[al.step_ref_index] - zero, color=color, lw=1.0, ls="--")
        mse = position_mse(np.asarray(pred.pos)[al.frame_index], ref.pos[al.frame_ref_index])
        bottom.plot(np.asarray(pred.t_pos)[al.frame_index], mse, color=color, lw=0.6)
    bottom.axhline(2e-4, color="k", ls=":", lw=1.0, label="paper plateau ~2e-4 m²")
    top.set_ylabel("cumulative dissipated energy (J)")
    top.set_title("model solid, DEM dashed (normal + tangential damping)", fontsize=10)
    top.legend(fontsize=7, ncols=4, loc="upper left")
    top.grid(True, alpha=0.3)
    bottom.set_yscale("log")
    bottom.set_ylabel("MSE_t (m²)")
    bottom.set_xlabel("time since the start of motion (s)")
    bottom.legend(fontsize=8, loc="lower right")
    bottom.grid(True, which="both", alpha=0.3)
    fig.suptitle(title)
    return save_figure(fig, path)


__all__ = [
    "new_figure",
    "plot_case_curves",
    "plot_cumulative_energy",
    "plot_ensemble",
    "plot_position_mse",
    "plot_run",
    "plot_sensitivity",
    "plot_trajectory_xz",
    "save_figure",
]
