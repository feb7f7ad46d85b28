"""The regime of a ball-mill run: "bed" or "agitated", with every rule and threshold.

The two states are those of docs/conventions.md section 7.

One place for the science of the two states: the thresholds (with units and where they come
from) and the classifiers. :mod:`sgn_jax.analysis.metrics` applies them to a prediction and its DEM
reference (``sgn-jax evaluate``); ``experiments/tools/generate_data.py`` labels each DEM file of
an ensemble with :func:`regime_of` and :func:`regime_windows`; the speed threshold comes from
both indicators measured over the 1-s windows of a DEM ensemble (:data:`AGITATED_SPEED_M_S`).

Two families of rules:

- **The evaluation rule** (:func:`classify_state`, applied to predictions and references alike).
  By default (``classify_by="speed"``) a run is "agitated" when the mean ball speed in the jar
  frame, from finite differences of the saved frames (``pos - offset``, 1 ms apart at the
  default ``save_every``; :func:`sgn_jax.analysis.metrics.jar_frame_speed`), is >=
  :data:`AGITATED_SPEED_M_S`, else "bed". It reads positions only, so it does not depend on the
  surrogate's energy head (which the power comparison judges). Two other rules are available:
  ``"contacts"`` (mean ball pairs within the edge skin per ball >= :data:`BED_PAIRS_PER_BALL`
  is a "bed") does not separate the DEM states and a surrogate whose balls overlap inflates it;
  ``"power"`` (agitated when the mean dissipation power >= an explicit threshold in W) judges
  the energy head by its own output.
- **The DEM's ground truth** (:func:`regime_of`): the mean number of ball-ball contacts per ball
  from the DEM's own contact list, "bed" when >= :data:`REGIME_PP_CONTACTS_PER_BALL`. Only the
  DEM has a contact list, so this rule labels DEM data (ensemble manifests) and calibrates the
  speed threshold; :func:`regime_windows` applies it per :data:`REGIME_WINDOW_S` window, since a
  run can switch state.

Pure Python and numpy; no file I/O.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

from sgn_jax.pairs import MetricsError

AGITATED_SPEED_M_S = 0.16
"""Default state threshold of :func:`classify_state`: mean ball speed in the jar frame (m/s);
agitated if >=. Provenance: calibrated on the 12-packing DEM ensemble of the standard case
(seeds 0-11; :func:`regime_windows` against :func:`sgn_jax.analysis.metrics.jar_frame_speed`):
over 1-s windows the bed (>= 14 DEM ball-ball contacts) moves at 0.059-0.123 m/s in the jar
frame and the agitated state (fewer contacts) at 0.191-0.366 m/s; 0.16 m/s is near the middle of
the gap (0.157). Whole 10-s runs: bed 0.063-0.118 m/s, agitated 0.222-0.332 m/s."""

BED_PAIRS_PER_BALL = 0.75
"""``classify_by="contacts"`` threshold: mean ball pairs within ``2 R + [graph] pp_skin`` per
ball (dimensionless; bed if >=). Provenance: the original evaluation rule. It does not separate
the DEM states of the standard case (1.45-1.59 pairs per ball for the agitated seed 0,
1.66-1.76 for the bed seeds 1 and 3, all "bed"); kept for comparison and recorded in the
ensemble manifests (``regime_evaluate_rule``)."""

CLASSIFIERS = ("speed", "contacts", "power")
"""The state rules of :func:`classify_state` (``--classify-by`` of ``sgn-jax evaluate``)."""

REGIME_PP_CONTACTS_PER_BALL = 14.0 / 24.0
"""The DEM's bed/agitated threshold on its mean ball-ball contacts per ball (dimensionless,
bed if >=): 14 contacts for 24 balls. Provenance: on the standard case the agitated seed 0 has
9-11 contacts (0.30 W) in every second of its 10 s, the bed seeds 1-3 have 17-21
(0.09-0.14 W) (docs/dem.md, and 1-s reruns of seeds 1 and 3); 14 lies between."""

REGIME_WINDOW_S = 1.0
"""Length (s of motion) of the windows of :func:`regime_windows`: the 1-s windows over which
the calibration above was measured."""


def classify_state(value: float, threshold: float, classify_by: str = "speed") -> str:
    """The state of a run (docs/conventions.md section 7): "bed" or "agitated".

    ``classify_by="speed"``: ``value`` = mean ball speed in the jar frame (m/s); agitated when
    >= threshold. ``classify_by="contacts"``: ``value`` = mean pairs within the skin per ball;
    bed when >= threshold. ``classify_by="power"``: ``value`` = mean dissipation power (W);
    agitated when >= threshold (the agitated state dissipates 2-3x more). NaN -> "unknown".
    """
    if classify_by not in CLASSIFIERS:
        raise MetricsError(f"classify_by must be one of {CLASSIFIERS}, got {classify_by!r}")
    if value is None or not math.isfinite(value):
        return "unknown"
    if classify_by == "contacts":
        return "bed" if value >= threshold else "agitated"
    return "agitated" if value >= threshold else "bed"


def default_threshold(classify_by: str) -> float:
    """The default threshold of a state rule; "power" has none (it depends on the case)."""
    if classify_by == "speed":
        return AGITATED_SPEED_M_S
    if classify_by == "contacts":
        return BED_PAIRS_PER_BALL
    if classify_by == "power":
        raise MetricsError("classify_by='power' needs an explicit threshold in W (e.g. the "
                           "midpoint between the bed and agitated dissipation powers)")
    raise MetricsError(f"classify_by must be one of {CLASSIFIERS}, got {classify_by!r}")


def regime_of(pp_contacts_per_ball: float) -> str:
    """The DEM's state from its mean ball-ball contacts per ball: "bed" when >=
    :data:`REGIME_PP_CONTACTS_PER_BALL`, else "agitated"."""
    return "bed" if pp_contacts_per_ball >= REGIME_PP_CONTACTS_PER_BALL else "agitated"


def regime_windows(contacts: Sequence[float] | np.ndarray, n_balls: int, duration: float,
                   window_s: float | None = None) -> tuple[list[str], float]:
    """:func:`regime_of` per window of a DEM run.

    Args:
        contacts: (T,) ball-ball contact count per sample, sample 0 at the start of motion
            (it is left out when there are more samples).
        n_balls: the number of balls.
        duration: seconds of motion the samples cover.
        window_s: window length in s (default :data:`REGIME_WINDOW_S`, read at call time);
            the run is split into ``max(1, round(duration / window_s))`` equal windows.
    Returns:
        (one state per window, the windows' length in s).
    """
    window_s = REGIME_WINDOW_S if window_s is None else float(window_s)
    contacts = np.asarray(contacts)
    n_windows = max(1, int(round(duration / window_s)))
    parts = np.array_split(contacts[1:] if contacts.size > 1 else contacts, n_windows)
    return [regime_of(float(np.mean(part)) / n_balls) for part in parts], duration / n_windows


__all__ = [
    "AGITATED_SPEED_M_S",
    "BED_PAIRS_PER_BALL",
    "CLASSIFIERS",
    "REGIME_PP_CONTACTS_PER_BALL",
    "REGIME_WINDOW_S",
    "classify_state",
    "default_threshold",
    "regime_of",
    "regime_windows",
]
