"""Ball pairs counted on saved frames (pure numpy), and the error the metrics raise.

:func:`pairs_within` is the graph builder's ball-ball edge rule (centre distance <= 2 R + skin)
applied to positions; :func:`deepest_pair_overlap` is the deepest ball-ball overlap. Both are
used by :mod:`sgn_jax.analysis.metrics` and :func:`pairs_within` also by the perfect surrogate
(:func:`sgn_jax.records.prediction.prediction_from_trajectory`); they live here so that ``metrics``
imports ``prediction`` (to load prediction files) and neither imports the other back.
:class:`MetricsError`, which they raise, is defined here for the same reason; import it, and
these functions, from :mod:`sgn_jax.analysis.metrics`.
"""

from __future__ import annotations

import numpy as np

from sgn_jax.errors import SGNJaxError

_PAIR_CHUNK = 4096  # samples per chunk in pairs_within (N^2 distances each)


class MetricsError(SGNJaxError, ValueError):
    """The prediction and reference cannot be compared; the message says why and what to do."""


def pairs_within(pos: np.ndarray, cutoff: float) -> np.ndarray:
    """Ball pairs i < j with centre distance <= ``cutoff`` (m), per frame: (T, N, 3) -> (T,).

    With ``cutoff = 2 R + pp_skin`` this is the graph builder's ball-ball edge rule (directed
    edges = 2 x pairs).
    """
    pos = np.asarray(pos, dtype=np.float64)
    if pos.ndim != 3 or pos.shape[-1] != 3:
        raise MetricsError(f"pairs_within needs (T, N, 3) positions, got {pos.shape}")
    n_balls = pos.shape[1]
    upper = np.triu(np.ones((n_balls, n_balls), dtype=bool), k=1)
    counts = np.zeros(pos.shape[0], dtype=np.int64)
    for start in range(0, pos.shape[0], _PAIR_CHUNK):
        chunk = pos[start:start + _PAIR_CHUNK]
        d2 = np.sum((chunk[:, :, None, :] - chunk[:, None, :, :]) ** 2, axis=-1)
        counts[start:start + chunk.shape[0]] = np.sum((d2 <= cutoff * cutoff) & upper,
                                                      axis=(1, 2))
    return counts


def deepest_pair_overlap(pos: np.ndarray, radius: float) -> np.ndarray:
    """Deepest ball-ball overlap per frame: max over pairs i < j of 2 R - |x_i - x_j| (m).

    Args:
        pos: (T, N, 3) ball centres (m); radius: ball radius R (m).
    Returns:
        (T,) float64; negative where no pair touches (then minus the narrowest gap), NaN for
        fewer than two balls.
    """
    pos = np.asarray(pos, dtype=np.float64)
    if pos.ndim != 3 or pos.shape[-1] != 3:
        raise MetricsError(f"deepest_pair_overlap needs (T, N, 3) positions, got {pos.shape}")
    n_balls = pos.shape[1]
    if n_balls < 2:
        return np.full(pos.shape[0], np.nan)
    i, j = np.triu_indices(n_balls, k=1)
    deepest = np.empty(pos.shape[0])
    for start in range(0, pos.shape[0], _PAIR_CHUNK):
        chunk = pos[start:start + _PAIR_CHUNK]
        distance = np.linalg.norm(chunk[:, i, :] - chunk[:, j, :], axis=-1)
        deepest[start:start + chunk.shape[0]] = 2.0 * radius - distance.min(axis=1)
    return deepest



__all__ = ["MetricsError", "deepest_pair_overlap", "pairs_within"]
