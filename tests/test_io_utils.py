"""The JSON-lines log that resumable experiment scripts append to (sgn_jax.records.io_utils)."""

from __future__ import annotations

from sgn_jax.records.io_utils import append_jsonl, read_jsonl


def test_jsonl_log_round_trips_and_skips_a_line_cut_by_a_kill(tmp_path):
    path = tmp_path / "sub" / "log.jsonl"
    assert read_jsonl(path) == []
    append_jsonl(path, {"key": "a", "power_W": 0.1})
    append_jsonl(path, {"key": "b", "power_W": 0.2})
    with open(path, "a") as fh:
        fh.write('{"key": "c", "pow')          # a kill in the middle of a write
    assert read_jsonl(path) == [{"key": "a", "power_W": 0.1}, {"key": "b", "power_W": 0.2}]
