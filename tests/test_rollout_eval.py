"""sgn_jax.pipelines.rollout_eval: a DEM reference row's interval, whatever its model's step."""

import json
from pathlib import Path

import pytest

from sgn_jax.pipelines.rollout_eval import reference_span

ROOT = Path(__file__).resolve().parent.parent


def test_a_reference_row_gives_its_own_interval_to_a_model_of_another_step():
    """A row of 7,492 steps of a 2e-4 s model covers 1.4984 s: a model at 1e-4 s rolls out
    14,984 of its steps (not 7,492, half the DEM's interval), one at 2e-4 s the same 7,492."""
    row = {"steps": 7492, "dt_s": 2e-4}
    assert reference_span(row, 1e-4) == pytest.approx(1.4984, rel=1e-12)
    assert round(reference_span(row, 1e-4) / 1e-4) == 14984
    assert round(reference_span(row, 2e-4) / 2e-4) == 7492
    # 7,491 steps of 1e-4 s are not a whole number of 2e-4 s steps
    with pytest.raises(ValueError, match="not a whole number"):
        reference_span({"steps": 7491, "dt_s": 1e-4}, 2e-4)
    # a row that does not say its step is refused, not guessed
    with pytest.raises(ValueError, match="no dt_s"):
        reference_span({"steps": 7492}, 1e-4, "old.json")


def test_the_shipped_dem_references_state_the_step_of_their_rows():
    """experiments/reproduce/contact_heldout/expected/*.json, the DEM's side of
    run.sh for any model: every row says its step, and its interval is the ensemble's (1.5 s
    held-out and fresh, 2 s unseen, 10 s standard, less the first window)."""
    spans = {"heldout": 1.5, "heldout_sepon": 1.5, "fresh": 1.5, "unseen": 2.0,
             "unseen_sepon": 2.0, "standard": 10.0}
    for name, seconds in spans.items():
        path = ROOT / "experiments" / "reproduce" / "contact_heldout" / "expected" / f"{name}.json"
        for key, row in json.loads(path.read_text())["runs"].items():
            span = reference_span(row, 1e-4, f"{name}.json {key}")
            assert seconds - 0.01 < span <= seconds, (name, key, span)
