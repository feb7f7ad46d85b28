"""Tests of sgn_jax.analysis.plots: every figure is written as a real, non-trivial PNG, atomically,
and bad input is refused with a clear message."""

import numpy as np
import pytest
from matplotlib.image import imread

from sgn_jax.analysis.plots import (
    plot_cumulative_energy,
    plot_ensemble,
    plot_position_mse,
    plot_trajectory_xz,
)
from sgn_jax.config import builtin_config_path, load_config

PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"


def assert_png(path, min_size=10_000):
    data = path.read_bytes()
    assert data[:8] == PNG_SIGNATURE
    assert len(data) > min_size
    image = imread(path)
    # something was drawn: not a single flat colour
    assert image[..., :3].std() > 0.05
    assert not [p for p in path.parent.iterdir() if p.name.endswith(".tmp")]


def test_position_mse_plot(tmp_path):
    t = np.linspace(0.0, 1.0, 200)
    mse = 1e-4 * (1 - np.exp(-5 * t))  # 0 at t = 0: not drawable on a log axis, skipped
    mse[50:60] = np.nan  # frames without a reference
    path = plot_position_mse(t, mse, tmp_path / "mse.png", plateau=1e-4)
    assert path == tmp_path / "mse.png"
    assert_png(path)
    # nothing positive to draw still gives a figure (with a note), not an error
    assert_png(plot_position_mse(t, np.zeros_like(t), tmp_path / "zero.png"))


def test_cumulative_energy_plot_with_reference_ending_early(tmp_path):
    t = np.linspace(1e-4, 2.0, 500)
    e_ref = 0.3 * t + 0.01 * np.sin(20 * t)
    e_pred = 1.05 * e_ref
    e_ref[300:] = np.nan  # the DEM stops, the prediction runs on (paper Fig. 8)
    assert_png(plot_cumulative_energy(t, e_pred, e_ref, tmp_path / "energy.png"))


def test_ensemble_plot(tmp_path):
    rows = [{"power_pred_W": p, "power_ref_W": r, "pp_contacts_pred_mean": c,
             "pp_pairs_within_skin_ref_mean": d, "n_balls": 24}
            for p, r, c, d in [(0.2, 0.25, 30.0, 28.0), (0.6, 0.5, 4.0, 5.0),
                               (0.3, None, 25.0, None)]]
    summary = {
        "runs": rows,
        "power": {"pred_W": {"mean": 0.367, "std": 0.21}, "ref_W": {"mean": 0.375, "std": 0.18},
                  "relative_error_of_means": 0.02},
        "states": {"classify_by": "contacts", "threshold": 0.75},
    }
    assert_png(plot_ensemble(summary, tmp_path / "ensemble.png"))
    summary["states"] = {"classify_by": "power", "threshold": 0.4}
    assert_png(plot_ensemble(summary, tmp_path / "ensemble_power.png"))
    with pytest.raises(ValueError, match="non-empty 'runs'"):
        plot_ensemble({"runs": []}, tmp_path / "empty.png")


def test_trajectory_xz_plot(tmp_path):
    rng = np.random.default_rng(0)
    pos = rng.uniform(-0.02, 0.02, (24, 3))
    ref = pos + rng.normal(0, 0.002, pos.shape)
    jar = load_config(builtin_config_path("emax_300rpm")).jar
    assert_png(plot_trajectory_xz(pos, tmp_path / "xz.png", ref_pos=ref,
                                  offset=np.array([0.017, 0.0, 0.0]), jar=jar))
    assert_png(plot_trajectory_xz(pos, tmp_path / "xz_plain.png"))
    # the legend names what is drawn: model balls, DEM balls, the lines joining them, the jar
    from unittest import mock

    from matplotlib.figure import Figure

    with mock.patch.object(Figure, "legend", autospec=True,
                           side_effect=Figure.legend) as legend:
        plot_trajectory_xz(pos, tmp_path / "xz_legend.png", ref_pos=ref, jar=jar)
    labels = [h.get_label() for h in legend.call_args.kwargs["handles"]]
    assert labels == ["model ball (24)", "DEM ball, same time",
                      "same ball, model to DEM (length: its position error)",
                      "jar cross-section (at its offset)"]
    assert "matched by index" in legend.call_args.kwargs["title"]
    with pytest.raises(ValueError, match=r"pos must be \(N, 3\)"):
        plot_trajectory_xz(pos[None], tmp_path / "bad.png")
    with pytest.raises(ValueError, match="ref_pos must have the shape of pos"):
        plot_trajectory_xz(pos, tmp_path / "bad.png", ref_pos=ref[:3])


def test_bad_input_is_refused(tmp_path):
    t = np.linspace(0, 1, 10)
    with pytest.raises(ValueError, match="must end in '.png'"):
        plot_position_mse(t, t, tmp_path / "mse.pdf")
    with pytest.raises(ValueError, match="same length"):
        plot_position_mse(t, t[:5], tmp_path / "mse.png")
    with pytest.raises(ValueError, match="same length"):
        plot_cumulative_energy(t, t, t[:3], tmp_path / "e.png")
    with pytest.raises(ValueError, match="must be 1-D"):
        plot_cumulative_energy(t[None], t, t, tmp_path / "e.png")
    assert list(tmp_path.iterdir()) == []
