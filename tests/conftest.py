"""Fixtures shared by the tests of the ``.npz`` record files (test_dataset.py, test_prediction.py),
and the session's shared folder, compilation cache and DEM runs (at the end).

Both record files are read by ``sgn_jax.records.base.read_npz_record``, so the files that fail
before any validation (missing, not a zip, corrupt, bad meta entry) and the messages they must
give are
described once here; each test module runs them against its own loader and error class.
"""

import contextlib
import json
import os
import re
import shutil
import tempfile
import zipfile

# The suite never reads or writes the user cache (sgn_jax.records.cache): every test starts cold and
# sees the same thing on any machine. Tests of the cache point SGN_JAX_CACHE_DIR at tmp_path.
os.environ["SGN_JAX_NO_CACHE"] = "1"

import numpy as np
import pytest

# One test session shares one scratch folder: JAX's persistent compilation cache
# (``jax/``), so that a program compiled by one test, one xdist worker or one subprocess
# (the docs examples, the two-device checks) is loaded, not compiled again, by the next; and
# the DEM runs the session fixtures below make once (settled packings). The folder is new for
# every session and removed at its end, so every session starts cold and sees the same thing
# on any machine; the user cache stays untouched. A cached executable is the compiled program
# itself: the numbers are the same as without it.
SESSION_DIR_ENV = "SGN_JAX_TEST_SESSION_DIR"


# The longest test files first: with ``-n 2 --dist loadfile`` each xdist worker takes
# the next whole file when it runs out, so longest-first leaves only short files for the end and
# the two workers finish within seconds of each other (in collection order a 30-50 s file could
# start last on one worker while the other sat idle). Approximate seconds of one worker
# (`pytest --durations=0`; benchmarks/compile_probe.py shows where they go); the order is only
# a scheduling hint: a wrong or stale entry costs time, never a result. Files not listed follow in
# collection order. The ones that make the session's DEM runs (conftest's fixtures below) are
# spread so that the two workers do not wait on the same one at the start.
LONGEST_FILES_FIRST = (
    "test_rollout.py",          # ~92 s; standard_dem_file
    "test_contact.py",          # ~55 s
    "test_design.py",           # ~52 s; short_packings
    "test_dem_jar.py",          # ~51 s
    "test_train.py",            # ~50 s
    "test_sdf_grid.py",         # ~45 s
    "test_sharding.py",         # ~36 s (the two-device process)
    "test_sweep.py",            # ~28 s; contact_short_packings
    "test_dem_driver.py",       # ~26 s
    "test_surrogate_collisions.py",  # ~35 s; contact_short_packings
    "test_dem_collisions.py",   # ~25 s
    "test_motion.py",           # ~20 s
    "test_extension_contact_law.py",  # ~18 s
    "test_contact_train.py",    # ~17 s
    "test_demo.py",             # ~17 s
    "test_cache.py",            # ~15 s
    "test_geometry.py",         # ~14 s
)


def pytest_collection_modifyitems(config, items):
    rank = {name: i for i, name in enumerate(LONGEST_FILES_FIRST)}
    # A stable sort: the tests of a file keep their order.
    items.sort(key=lambda item: rank.get(item.path.name, len(rank)))


def pytest_configure(config):
    # xdist's loadfile scheduler by default sorts files by their NUMBER of tests; keep ours.
    if hasattr(config.option, "loadscopereorder"):
        config.option.loadscopereorder = False
    if hasattr(config, "workerinput") or os.environ.get(SESSION_DIR_ENV):
        return  # an xdist worker (or a nested session): the controller's folder is inherited
    directory = tempfile.mkdtemp(prefix="sgn_jax_tests_")
    config._sgn_jax_session_dir = directory
    # Set before any test module imports JAX; the workers and every subprocess inherit them.
    os.environ[SESSION_DIR_ENV] = directory
    os.environ["JAX_COMPILATION_CACHE_DIR"] = os.path.join(directory, "jax")
    os.environ["JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS"] = "0.5"
    os.environ["JAX_PERSISTENT_CACHE_MIN_ENTRY_SIZE_BYTES"] = "0"


def pytest_unconfigure(config):
    directory = getattr(config, "_sgn_jax_session_dir", None)
    if directory:
        shutil.rmtree(directory, ignore_errors=True)


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


# ---------------------------------------------------------------------------------------------
# DEM runs that several test files need, made once per session.


@contextlib.contextmanager
def _session_lock(name: str):
    """An exclusive lock on ``name`` in the session folder: the other xdist worker waits here
    while one makes a shared file, then finds it made."""
    path = os.path.join(os.environ[SESSION_DIR_ENV], name)
    with open(path, "w") as fh:
        try:
            import fcntl
        except ImportError:  # not POSIX: both workers may make it; the writes are atomic
            yield
            return
        fcntl.flock(fh, fcntl.LOCK_EX)
        try:
            yield
        finally:
            fcntl.flock(fh, fcntl.LOCK_UN)


@contextlib.contextmanager
def session_settle_cache():
    """The package's settled-packing cache (sgn_jax.records.cache) in the session folder, for the
    calls inside: a packing settled by one test file (or worker) is read by the next. A cached
    packing is bit-identical to one settled anew (tests/test_cache.py)."""
    saved = {k: os.environ.get(k) for k in ("SGN_JAX_NO_CACHE", "SGN_JAX_CACHE_DIR")}
    os.environ["SGN_JAX_NO_CACHE"] = "0"
    os.environ["SGN_JAX_CACHE_DIR"] = os.environ[SESSION_DIR_ENV]
    try:
        yield
    finally:
        for key, value in saved.items():
            if value is None:
                os.environ.pop(key, None)
            else:
                os.environ[key] = value


@pytest.fixture
def session_cache():
    """The package's cache (settled packings, compiled programs) in the session folder for the
    test's duration (:func:`session_settle_cache`): e.g. a CLI command given the seeds of
    ``short_packings`` reads those packings instead of settling them again."""
    with session_settle_cache():
        yield os.environ[SESSION_DIR_ENV]


@pytest.fixture(scope="session")
def short_packings():
    """``(cfg, packings)``: the standard case with 0.02 s of settling (the docs examples'
    sizes) and its packings of seeds 0 and 1 (sgn_jax.api.make_packings), made once per worker
    and settled once per session. Tests must not change them."""
    import sgn_jax.api as sj
    from sgn_jax.config import replace_section

    cfg = replace_section(sj.load_config("emax_300rpm"), "dem", settle_time=0.02)
    with session_settle_cache():
        packings = sj.make_packings(cfg, seeds=[0, 1])
    return cfg, packings


@pytest.fixture(scope="session")
def contact_short_packings(short_packings):
    """``(model, cfg, packings)``: the shipped contact model and ``short_packings``' case and
    seeds at the model's own step (``sgn_jax.api.at_surrogate_step``: it runs at 2e-4 s), the
    packings settled as those (the same settled states, from the session's cache)."""
    import sgn_jax.api as sj

    model = sj.load_surrogate("contact")
    cfg = sj.at_surrogate_step(short_packings[0], model)
    with session_settle_cache():
        packings = sj.make_packings(cfg, seeds=list(short_packings[1].seeds))
    return model, cfg, packings


@pytest.fixture(scope="session")
def standard_dem_file():
    """The path of a DEM dataset file of the standard case, seed 0: 0.05 s of settling, then
    0.101 s of motion (1011 samples). Written once per session into the session folder; read
    it with ``load_trajectory`` (tests/test_rollout.py, tests/test_graph_consistency.py)."""
    from sgn_jax.config import builtin_config_path, load_config, replace_section
    from sgn_jax.pipelines.dem_run import run_dem
    from sgn_jax.records.trajectory import save_trajectory

    path = os.path.join(os.environ[SESSION_DIR_ENV], "standard_settle0.05_motion0.101.npz")
    with _session_lock("standard_dem.lock"):
        if not os.path.isfile(path):
            cfg = load_config(builtin_config_path("emax_300rpm"))
            cfg = replace_section(cfg, "dem", settle_time=0.05)
            run = run_dem(cfg, duration=0.101, progress=False)
            save_trajectory(path, run.arrays, run.meta)
    return path


@pytest.fixture(scope="session")
def two_device_results():
    """The default run's two-device checks (tests/two_device_checks.py: ``ensemble`` and
    ``step``, both for tests/test_sharding.py), run once per session in one process with two
    host devices (one JAX start and import instead of two); the results by check
    name, kept in the session folder (under a lock, should another worker ever ask too)."""
    from two_device_checks import run_in_two_device_process

    path = os.path.join(os.environ[SESSION_DIR_ENV], "two_device_results.json")
    with _session_lock("two_devices.lock"):
        if not os.path.isfile(path):
            results = run_in_two_device_process(["step", "ensemble"])
            with open(path + ".tmp", "w") as fh:
                json.dump(results, fh)
            os.replace(path + ".tmp", path)
    with open(path) as fh:
        return json.load(fh)
