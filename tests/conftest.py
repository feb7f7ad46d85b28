"""Fixtures shared by the tests of the ``.npz`` record files (test_dataset.py, test_prediction.py).

Both files are read by ``sgn_jax.records.base.read_npz_record``, so the files that fail before any
validation (missing, not a zip, corrupt, bad meta entry) and the messages they must give are
described once here; each test module runs them against its own loader and error class.
"""

import json
import os
import re
import zipfile

# The suite never reads or writes the user cache (sgn_jax.records.cache): every test starts cold and
# sees the same thing on any machine. Tests of the cache point SGN_JAX_CACHE_DIR at tmp_path.
os.environ["SGN_JAX_NO_CACHE"] = "1"

import numpy as np
import pytest


def _write_raw(path, arrays, meta):
    entries = dict(arrays)
    if meta is not None:
        entries["meta"] = np.array(meta if isinstance(meta, str) else json.dumps(meta))
    np.savez(path, **entries)
    return path


@pytest.fixture
def write_raw_npz():
    """``write(path, arrays, meta) -> path``: an npz written without validation, to make bad
    files. ``meta`` None leaves out the 'meta' entry; a str is stored as is (bad JSON), anything
    else JSON-encoded."""
    return _write_raw


def _flip_bytes_in_member(data: bytes, good, member: str) -> bytes:
    """``data`` (the bytes of ``good``) with 8 bytes flipped inside the stored ``member``: the
    zip directory stays intact, the member's CRC does not."""
    with zipfile.ZipFile(good) as zf:
        info = zf.getinfo(member)
    start = info.header_offset + 30 + len(info.filename) + len(info.extra) + 200
    flipped = bytearray(data)
    flipped[start:start + 8] = bytes(b ^ 0xFF for b in flipped[start:start + 8])
    return bytes(flipped)


def _unreadable_file(case, good, arrays):
    """The file of ``case``, made next to ``good`` (a valid saved record with a 'pos' member)."""
    folder, data = good.parent, good.read_bytes()
    path = folder / f"{case}.npz"
    if case == "missing":
        return path
    if case == "directory":
        return folder
    if case == "not_zip":
        path.write_text("this is not an archive\n")
    elif case == "single_npy":
        with open(path, "wb") as fh:
            np.save(fh, np.zeros(3))
    elif case == "truncated":
        path.write_bytes(data[: len(data) // 2])
    elif case == "tail_cut":  # the zip directory at the end is gone
        path.write_bytes(data[:-200])
    elif case == "crc":
        path.write_bytes(_flip_bytes_in_member(data, good, "pos.npy"))
    elif case == "no_meta":
        _write_raw(path, arrays, None)
    elif case == "meta_not_json":
        _write_raw(path, arrays, "{config: oops")
    elif case == "meta_not_string":
        np.savez(path, **dict(arrays, meta=np.zeros(3)))
    return path


# case -> regex of the message after "<kind> file '<path>'"; {produce} is the kind's tool.
_UNREADABLE = {
    "missing": r" not found; check the path, or .*{produce}",
    "directory": r" is not a file",
    "not_zip": r" is not an \.npz archive or is corrupt",
    "single_npy": r" is a single \.npy array, not an \.npz archive",
    "truncated": r" is (not an \.npz archive or is|a) corrupt",
    "tail_cut": r" is (not an \.npz archive or is|a) corrupt",
    "crc": r" is a corrupt or truncated \.npz archive",
    "no_meta": r" has no 'meta' entry \(the JSON metadata\)",
    "meta_not_json": r": 'meta' is not valid JSON",
    "meta_not_string": r": 'meta' must be a JSON string \(0-d unicode array\)",
}


@pytest.fixture(params=sorted(_UNREADABLE))
def load_refuses_unreadable(request, tmp_path):
    """``check(save, load, error, arrays, meta, kind=..., produce=...)``: saves a good record
    with ``save``, breaks a copy of it one way, and asserts ``load`` raises ``error`` naming the
    file ("<kind> file '<path>'") and saying what is wrong. A test using this fixture runs once
    per case: missing, directory, not_zip, single_npy (an .npy under .npz), truncated (first
    half), tail_cut (last 200 bytes gone), crc (bytes flipped inside the 'pos' member), no_meta,
    meta_not_json, meta_not_string (a numeric 'meta' entry)."""
    case = request.param

    def check(save, load, error, arrays, meta, *, kind, produce):
        good = tmp_path / "good.npz"
        save(good, arrays, meta)
        path = _unreadable_file(case, good, arrays)
        message = (re.escape(f"{kind} file {str(path)!r}")
                   + _UNREADABLE[case].format(produce=re.escape(produce)))
        with pytest.raises(error, match=message):
            load(path)

    return check


@pytest.fixture
def round_trip(tmp_path):
    """``run(save, load, arrays, meta, **save_kwargs) -> record``: save to a fresh folder, load
    back, and assert what every record file guarantees: no temporary file left behind, the
    same array names, every array bit-identical (dtype, shape, bytes) and read-only, the same
    meta, ``path`` set, arrays by item and attribute, a clear AttributeError for a missing
    one, arrays listed by ``dir``, ``dt`` and ``n_balls`` from meta and 'pos'."""

    def run(save, load, arrays, meta, **save_kwargs):
        folder = tmp_path / "round_trip"
        path = folder / "record.npz"
        save(path, arrays, meta, **save_kwargs)
        assert [p.name for p in folder.iterdir()] == ["record.npz"]  # no temp file left behind
        record = load(path)
        assert record.path == str(path) and record.meta == meta
        assert set(record.arrays) == set(arrays)
        for name, value in arrays.items():
            value, loaded = np.asarray(value), record.arrays[name]
            assert loaded.dtype == value.dtype and loaded.shape == value.shape, name
            assert loaded.tobytes() == value.tobytes(), name
            assert record[name] is loaded and not loaded.flags.writeable, name
        assert record.pos is record.arrays["pos"]
        with pytest.raises(ValueError):
            record.pos[0, 0, 0] = 1.0  # read-only
        with pytest.raises(AttributeError, match=f"^{type(record).__name__} has no attribute or "
                                                 "array 'velocity'; arrays: "):
            _ = record.velocity
        assert set(arrays) <= set(dir(record))
        assert record.dt == meta["dt"] and record.n_balls == np.shape(arrays["pos"])[1]
        return record

    return run
