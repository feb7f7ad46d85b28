"""More DEM packings of the held-out charges and surrogates' evaluations on them, on many cores,
inside a fixed wall-time budget (run by experiments/charges/device_heldout.sh, which documents
the call and sets the environment).

    python experiments/charges/device_heldout.py --models runs/contact_charge/touch [NAME=PATH ...] \
        [--seeds 104 105 106 107] [--names heldout_00 ...] [--duration 2.5] [--budget 470] \
        [--jobs 16] [--cores 0-15] [--work /tmp/device_heldout] [--out $OUT]

One process per job on its own core (``sched_setaffinity``), ``--jobs`` at a time:

1. DEM: experiments/charges/make_data.py for each (charge, seed), the longest charges first
   (:data:`COST`), each followed by experiments/tools/trim_records.py on its record (the first
   ``--trim-window + 2`` samples at ``--trim-dt``). A job that would clearly not end before the
   DEM's deadline (``budget - eval_reserve - pack_reserve`` after the start) is not started, and
   one still running then is killed: its record is left out.
2. Evaluation: experiments/charges/evaluate.py of each model on each new record, as soon as its
   DEM job is over (before the DEM jobs that wait; one record per process, so that the last
   charge's records are evaluated side by side: ~20 s of compile and ~20-40 s a full record of
   2.5 s on one core), killed at ``budget - pack_reserve``.
3. Packing, at the end or on SIGTERM/SIGINT: ``OUT/eval_<model>.json`` per model (the rows of
   every charge, ``runs`` keyed ``<charge>_seed_<K>``, with the summaries and the bars as
   evaluate.py writes them; usable as ``evaluate.py --dem-reference``),
   ``OUT/records_trimmed.tar.gz`` (``NAME/seed_K.npz``, the trimmed records),
   ``OUT/logs.tar.gz`` (every job's log, the per-charge evaluations, the bars tables, the job
   table) and ``OUT/device_heldout.log`` (this driver's log): 3 files and one per model (at
   most 5 models, so that at most 8 files come back).
"""

from __future__ import annotations

import argparse
import io
import json
import os
import shlex
import signal
import subprocess
import sys
import tarfile
import time
import tomllib
from pathlib import Path

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent.parent

# DEM wall time of one 2.5 s record of each held-out charge on one core of the development
# machine (s): the order of the jobs and the estimate of whether one still ends in time.
COST = {"heldout_00": 282.0, "heldout_01": 117.0, "heldout_02": 100.0, "heldout_03": 58.0,
        "heldout_04": 195.0, "heldout_05": 36.0}
STARTUP_S = 30.0   # a DEM process's import and compile, on top of COST
MAX_MODELS = 5     # 8 files come back: the log, 2 tars and one JSON per model
RETURN_FILE_LIMIT = 16 * 2**20


class Stop(Exception):
    """SIGTERM or SIGINT: kill the jobs and pack what is there."""


def _stop(signum, frame):
    raise Stop(signal.Signals(signum).name)


def parse_cores(spec: str | None) -> list[int]:
    """'0-3,8' -> [0, 1, 2, 3, 8]; None: the cores this process may run on."""
    if not spec:
        return sorted(os.sched_getaffinity(0))
    cores = []
    for part in spec.split(","):
        lo, _, hi = part.partition("-")
        cores += list(range(int(lo), int(hi or lo) + 1))
    return cores


def model_name(spec: str) -> tuple[str, str]:
    """'NAME=PATH' or PATH -> (name, path); a PATH's name is its run folder's (the folder
    above ``checkpoints`` for a checkpoint directory)."""
    if "=" in spec:
        name, path = spec.split("=", 1)
        return name, path
    parts = Path(spec).parts
    if "checkpoints" in parts:
        parts = parts[:parts.index("checkpoints")]
    return (parts[-1] if parts else "model"), spec


class Job:
    def __init__(self, kind: str, name: str, key: str, cmd: list[str], log: Path, cost: float):
        self.kind, self.name, self.key, self.cmd, self.log, self.cost = kind, name, key, cmd, log, cost
        self.proc: subprocess.Popen | None = None
        self.core = -1
        self.start = self.end = 0.0
        self.status = "pending"   # running, done, failed, killed, skipped

    def row(self, t0: float) -> dict:
        return {"kind": self.kind, "job": self.key, "status": self.status, "core": self.core,
                "start_s": round(self.start - t0, 1) if self.start else None,
                "wall_s": round(self.end - self.start, 1) if self.end else None}


class Driver:
    def __init__(self, args: argparse.Namespace):
        self.args = args
        self.t0 = float(os.environ.get("DH_T0") or time.time())
        self.deadline = self.t0 + args.budget
        self.eval_deadline = self.deadline - args.pack_reserve
        self.dem_deadline = self.eval_deadline - args.eval_reserve
        self.work = Path(args.work)
        self.data, self.trim = self.work / "data", self.work / "trim"
        self.logs, self.evals = self.work / "logs", self.work / "eval"
        for d in (self.data, self.trim, self.logs, self.evals):
            d.mkdir(parents=True, exist_ok=True)
        self.out = Path(args.out)
        self.out.mkdir(parents=True, exist_ok=True)
        self.log_file = open(self.out / "device_heldout.log", "a", buffering=1)
        self.cores = parse_cores(args.cores)
        self.slots = args.jobs or len(self.cores)
        self.models = dict(model_name(m) for m in args.models)
        design = tomllib.loads((HERE / "design.toml").read_text())["heldout"]
        self.names = args.names or sorted(design)
        self.jobs: list[Job] = []
        self.eval_queued: set[str] = set()
        self.ratios: list[float] = []   # device DEM wall / (COST + STARTUP_S) of each job
        py = sys.executable
        scale = args.duration / 2.5
        for name in sorted(self.names, key=lambda n: -COST.get(n, 300.0)):
            for seed in args.seeds:
                dem = [py, str(HERE / "make_data.py"), "--split", "heldout", "--seeds", str(seed),
                       "--names", name, "--duration", str(args.duration), "--out", str(self.data)]
                trim = [py, str(ROOT / "experiments/tools/trim_records.py"), str(self.data),
                        str(self.trim), "--names", name, "--seeds", str(seed), "--window",
                        str(args.trim_window), "--dt", str(args.trim_dt)]
                cmd = ["sh", "-c", shlex.join(dem) + " && " + shlex.join(trim)]
                job = Job("dem", name, f"{name}_seed_{seed}", cmd,
                          self.logs / f"dem_{name}_seed_{seed}.log",
                          COST.get(name, 300.0) * scale + STARTUP_S)
                self.jobs.append(job)

    def say(self, msg: str) -> None:
        line = f"[{time.time() - self.t0:6.1f} s] {msg}"
        print(line, flush=True)
        self.log_file.write(line + "\n")

    def running(self) -> list[Job]:
        return [j for j in self.jobs if j.status == "running"]

    def launch(self, job: Job) -> None:
        used = {j.core for j in self.running()}
        free = [c for c in self.cores if c not in used] or self.cores
        job.core = free[0]
        core = job.core
        job.start = time.time()
        job.proc = subprocess.Popen(job.cmd, stdout=open(job.log, "w"), stderr=subprocess.STDOUT,
                                    cwd=ROOT, start_new_session=True,
                                    preexec_fn=lambda: os.sched_setaffinity(0, {core}))
        job.status = "running"
        self.say(f"start {job.kind} {job.key} on core {core}")

    def kill(self, job: Job, why: str) -> None:
        try:
            os.killpg(job.proc.pid, signal.SIGKILL)
        except ProcessLookupError:
            pass
        job.proc.wait()
        job.end, job.status = time.time(), "killed"
        self.say(f"killed {job.kind} {job.key} after {job.end - job.start:.0f} s ({why})")

    def reap(self) -> None:
        for job in self.running():
            rc = job.proc.poll()
            if rc is None:
                continue
            job.end = time.time()
            job.status = "done" if rc == 0 else "failed"
            wall = job.end - job.start
            tail = job.log.read_text(errors="replace").strip().splitlines()[-1:] or [""]
            if job.kind == "dem" and rc == 0:
                self.ratios.append(wall / job.cost)
            self.say(f"{job.status} {job.kind} {job.key} rc {rc} in {wall:.0f} s: {tail[0][:300]}")

    @property
    def ratio(self) -> float:
        """The slowest DEM job's wall time over its estimate (1 before any has ended)."""
        return max(self.ratios, default=1.0)

    def queue_evals(self) -> None:
        """One evaluation per model of each record whose DEM job is over, as soon as it is
        (a charge's first record needs no other charge, nor its other seeds)."""
        for dem in self.jobs:
            if dem.kind != "dem" or dem.key in self.eval_queued or dem.status in (
                    "pending", "running"):
                continue
            self.eval_queued.add(dem.key)
            seed = dem.key.rsplit("_", 1)[1]
            if not (self.data / dem.name / f"seed_{seed}.npz").exists():
                continue
            for model, path in self.models.items():
                cmd = [sys.executable, str(HERE / "evaluate.py"), "--model", path, "--data",
                       str(self.data), "--names", dem.name, "--seeds", seed, "--out",
                       str(self.evals / model), "--name", dem.key]
                job = Job("eval", dem.name, f"{model}_{dem.key}", cmd,
                          self.logs / f"eval_{model}_{dem.key}.log", 0.0)
                self.jobs.insert(0, job)   # before the DEM jobs that wait

    def schedule(self, now: float) -> None:
        for job in self.jobs:
            if len(self.running()) >= self.slots:
                return
            if job.status != "pending":
                continue
            if job.kind == "dem" and now + 0.8 * job.cost * self.ratio > self.dem_deadline:
                job.status = "skipped"
                self.say(f"skip dem {job.key}: about {job.cost * self.ratio:.0f} s, "
                         f"{self.dem_deadline - now:.0f} s to the DEM deadline")
                continue
            if job.kind == "eval" and now > self.eval_deadline - 20:
                job.status = "skipped"
                self.say(f"skip eval {job.key}: too late")
                continue
            self.launch(job)

    def run(self) -> None:
        self.say(f"{len(self.jobs)} DEM jobs, models {self.models}, {self.slots} at a time on "
                 f"cores {self.cores}; DEM deadline {self.dem_deadline - self.t0:.0f} s, "
                 f"evaluations {self.eval_deadline - self.t0:.0f} s, end {self.args.budget:.0f} s")
        while True:
            now = time.time()
            self.reap()
            for job in self.running():
                limit = self.dem_deadline if job.kind == "dem" else self.eval_deadline
                if now > limit:
                    self.kill(job, "deadline")
            self.queue_evals()
            self.schedule(now)
            if not any(j.status in ("pending", "running") for j in self.jobs):
                break
            time.sleep(0.5)

    def stop_all(self, why: str) -> None:
        for job in self.running():
            self.kill(job, why)
        for job in self.jobs:
            if job.status == "pending":
                job.status = "skipped"

    def trim_missing(self) -> None:
        """Trim the records whose DEM job ended before its trim (killed in between), while
        there is time."""
        for rec in sorted(self.data.glob("*/seed_*.npz")):
            if (self.trim / rec.relative_to(self.data)).exists():
                continue
            left = self.deadline - 5 - time.time()
            if left < 10:
                self.say(f"no time to trim {rec}")
                continue
            cmd = [sys.executable, str(ROOT / "experiments/tools/trim_records.py"),
                   str(self.data), str(self.trim), "--names", rec.parent.name, "--seeds",
                   rec.stem.split("_")[1], "--window", str(self.args.trim_window), "--dt",
                   str(self.args.trim_dt)]
            res = subprocess.run(cmd, capture_output=True, text=True, timeout=left, cwd=ROOT)
            self.say(f"trimmed {rec}: rc {res.returncode} {(res.stdout + res.stderr)[-300:]}")

    def pack(self) -> None:
        t_pack = time.time()
        bars = io.StringIO()
        try:
            self.trim_missing()
        except Exception as exc:
            self.say(f"trimming failed: {type(exc).__name__}: {exc}")
        try:
            import sgn_jax.experiment_tools as tools
            design = tomllib.loads((HERE / "design.toml").read_text())["heldout"]
            for model, path in list(self.models.items())[:MAX_MODELS]:
                runs = {}
                for part in sorted((self.evals / model).glob("*.json")):
                    runs.update(json.loads(part.read_text())["runs"])
                summaries = []
                for name in self.names:   # as evaluate.py summarizes a charge
                    rows = [runs[k] for k in sorted(runs) if k.startswith(f"{name}_seed_")]
                    if rows:
                        summary = tools.summarize_runs(name, rows)
                        summary["n_balls"] = rows[0]["n_balls"]
                        summary["label"] = design[name]["label"]
                        summaries.append(summary)
                data = {"runs": runs, "summaries": summaries, "model": path,
                        "seeds": self.args.seeds, "duration_s": self.args.duration}
                target = self.out / f"eval_{model}.json"
                target.write_text(json.dumps(data, indent=1))
                self.say(f"{target.name}: {len(runs)} runs, {len(summaries)} charges")
                if summaries:
                    res = subprocess.run([sys.executable, str(HERE / "evaluate.py"), "--bars",
                                          str(target)], capture_output=True, text=True,
                                         timeout=max(5.0, self.deadline - time.time()), cwd=ROOT)
                    bars.write(res.stdout + res.stderr[-500:] + "\n")
        except Exception as exc:   # the records and logs still come back
            self.say(f"merging the evaluations failed: {type(exc).__name__}: {exc}")
        self.say("bars:\n" + bars.getvalue())
        table = [j.row(self.t0) for j in self.jobs]
        (self.logs / "jobs.json").write_text(json.dumps(table, indent=1))
        counts = {}
        for j in self.jobs:
            counts[f"{j.kind} {j.status}"] = counts.get(f"{j.kind} {j.status}", 0) + 1
        self.say(f"jobs: {counts}; DEM wall / estimate (slowest): {self.ratio:.2f}")
        target = self.out / "records_trimmed.tar.gz"
        with tarfile.open(target, "w:gz") as tar:
            for rec in sorted(self.trim.glob("*/seed_*.npz")):
                tar.add(rec, arcname=str(rec.relative_to(self.trim)))
        size = target.stat().st_size
        self.say(f"{target.name}: {len(list(self.trim.glob('*/seed_*.npz')))} records, "
                 f"{size / 2**20:.2f} MiB")
        if size > RETURN_FILE_LIMIT:
            self.say("records_trimmed.tar.gz is over 16 MiB and would not come back: removed")
            target.unlink()
        with tarfile.open(self.out / "logs.tar.gz", "w:gz") as tar:
            tar.add(self.logs, arcname="logs")
            tar.add(self.evals, arcname="eval")
        self.say(f"packed in {time.time() - t_pack:.1f} s; total {time.time() - self.t0:.0f} s")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--models", nargs="+", required=True, metavar="[NAME=]PATH")
    ap.add_argument("--seeds", type=int, nargs="+", default=[104, 105, 106, 107])
    ap.add_argument("--names", nargs="*", default=None)
    ap.add_argument("--duration", type=float, default=2.5)
    ap.add_argument("--budget", type=float, default=470.0,
                    help="s from DH_T0 (the shell script's start) to the end of the packing")
    ap.add_argument("--eval-reserve", type=float, default=60.0)
    ap.add_argument("--pack-reserve", type=float, default=20.0)
    ap.add_argument("--jobs", type=int, default=0, help="processes at a time (0: one per core)")
    ap.add_argument("--cores", default=None, help="e.g. 0-15 (default: this process's cores)")
    ap.add_argument("--trim-window", type=int, default=16)
    ap.add_argument("--trim-dt", type=float, default=2e-4)
    ap.add_argument("--work", default="/tmp/device_heldout")
    ap.add_argument("--out", default=os.environ.get("OUT") or "runs/device_heldout")
    args = ap.parse_args()
    if len(args.models) > MAX_MODELS:
        ap.error(f"at most {MAX_MODELS} models (8 files come back)")
    driver = Driver(args)
    signal.signal(signal.SIGTERM, _stop)
    signal.signal(signal.SIGINT, _stop)
    try:
        driver.run()
    except Stop as exc:
        driver.say(f"stopped by {exc}")
        driver.stop_all(str(exc))
    finally:
        signal.signal(signal.SIGTERM, signal.SIG_IGN)
        signal.signal(signal.SIGINT, signal.SIG_IGN)
        driver.stop_all("the end")
        driver.pack()


if __name__ == "__main__":
    main()
