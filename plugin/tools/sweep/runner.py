"""Running a sweep's points as Dask tasks (a local cluster, a scheduler file or SLURM), each point in a fresh process
under time and memory limits, its result stored as it arrives."""
from __future__ import annotations

import contextlib
import json
import logging
import os
import signal
import socket
import subprocess
import sys
import tempfile
import time
from dataclasses import asdict, dataclass, field
from datetime import datetime, timezone
from pathlib import Path

import psutil
from tqdm import tqdm

from layerbvh_mitsuba import atomic
from layerbvh_mitsuba.ab.render import UserError
from layerbvh_mitsuba.tools.sweep import table as sweep_table
from layerbvh_mitsuba.tools.sweep.slurm import WALLTIME_MARGIN_S, SlurmSettings, make_cluster, time_left_in_job
from layerbvh_mitsuba.tools.sweep.store import JOBS, Point, RESULT_FILE, RUNS_FILE, STATUS_OK, load_result, store_result


EXCLUSIVE = "exclusive"  # Dask worker resource held by timed points: one per machine, so they never overlap
LOOPBACK = "127.0.0.1"  # the local cluster listens here only
POLL_S = 0.2  # how often a running point's time and memory are checked
DEFAULT_TIMEOUT_S = 3600.0
MEMORY_SHARE = 0.8  # default memory limit: this share of the host's RAM, split over the points it runs at once
WAIT_WORKERS_S = 120.0  # a sweep with points left and no worker connected for this long stops
CONNECT_TIMEOUT_S = 30.0
KILL_WAIT_S = 10.0
LOG_TAIL_BYTES = 256 << 10  # a point's log.txt comes back with at most this much of its end
FILES_LIMIT_BYTES = 512 << 20  # a point's output files travel back up to this total; larger ones are left out


# -- one point on a worker --------------------------------------------------------------------------


@dataclass(frozen=True)
class Limits:
    """Per-point limits, enforced by the task on the child process (killed past either)."""

    timeout_s: float = DEFAULT_TIMEOUT_S
    memory_bytes: int | None = None  # None: MEMORY_SHARE of the host's RAM / slots
    slots: int = 1  # points that may run at once on one host (local cluster: its workers)

    def memory_on_host(self) -> int:
        return self.memory_bytes or int(MEMORY_SHARE * psutil.virtual_memory().total / max(1, self.slots))


def _gib(n: float) -> str:
    return f"{n / (1 << 30):.2f} GiB"


def _tail_line(text: str) -> str:
    lines = [ln.strip() for ln in text.strip().splitlines() if ln.strip()]
    return lines[-1][:300] if lines else "no output"


def run_point_task(point: dict, limits: dict) -> dict:
    """Dask task: run one point as `python -m layerbvh_mitsuba.tools.sweep.point` in a fresh process under the
    time and memory limits, and return its status, figures, host and output files (as bytes, so the
    sweep folder need exist only where the sweep was started)."""
    lim = Limits(**limits)
    host = socket.gethostname()
    start_time = time.time()
    started = datetime.fromtimestamp(start_time, timezone.utc).isoformat(timespec="seconds")
    if not Path(point["scene"]).is_file():
        return {"status": "error", "host": host, "started": started, "wall_s": 0.0, "files": {},
                "error": f"scene file not found on host {host}: {point['scene']} (workers need the scenes at the "
                         f"same path, e.g. on a shared filesystem)"}
    memory = lim.memory_on_host()
    # Inside a SLURM job (--cluster slurm) the point must end before its job does: a point cut off
    # by the walltime would take its worker with it and come back as a crash.
    timeout, too_long = lim.timeout_s, f"killed: time limit {lim.timeout_s:g} s"
    job = time_left_in_job()
    if job is not None and job[0] - WALLTIME_MARGIN_S < timeout:
        timeout = max(0.0, job[0] - WALLTIME_MARGIN_S)
        too_long = (f"killed: the SLURM job's walltime {job[1]} ended before the point finished (raise "
                    f"--slurm-walltime)")
    with tempfile.TemporaryDirectory(prefix="layerbvh-point-") as tmp:
        tmp = Path(tmp)
        (tmp / "point.json").write_text(json.dumps(point))
        out = tmp / "out"
        out.mkdir()
        log = tmp / "log.txt"
        cmd = [sys.executable, "-m", "layerbvh_mitsuba.tools.sweep.point", str(tmp / "point.json"), str(out)]
        t0 = time.perf_counter()
        peak, killed = 0, None
        with open(log, "wb") as fh:
            proc = subprocess.Popen(cmd, stdout=fh, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL,
                                    env={**os.environ, "LAYERBVH_SWEEP_PARENT": str(os.getpid())})
            try:
                ps = psutil.Process(proc.pid)
                while proc.poll() is None:
                    with contextlib.suppress(psutil.Error):
                        peak = max(peak, ps.memory_info().rss)
                    if peak > memory:
                        killed = f"killed: resident memory {_gib(peak)} above the limit {_gib(memory)}"
                    elif time.perf_counter() - t0 > timeout:
                        killed = too_long
                    if killed:
                        proc.kill()
                        break
                    with contextlib.suppress(subprocess.TimeoutExpired):
                        proc.wait(POLL_S)
            finally:
                if proc.poll() is None:
                    proc.kill()
                with contextlib.suppress(subprocess.TimeoutExpired):
                    proc.wait(KILL_WAIT_S)
        wall = time.perf_counter() - t0
        text = log.read_bytes()[-LOG_TAIL_BYTES:]
        # start/end (Unix seconds) show which points overlapped on a host: timed ones never do
        res = {"host": host, "started": started, "start_time": start_time, "end_time": time.time(), "wall_s": wall,
               "peak_rss_bytes": peak}
        result_file = out / RESULT_FILE
        if killed:
            res.update(status="killed", error=killed)
        elif result_file.is_file():
            res.update(json.loads(result_file.read_text()))
            res["peak_rss_bytes"] = max(peak, res.get("peak_rss_bytes") or 0)
            result_file.unlink()
        else:
            code = proc.returncode
            how = f"signal {-code}" if code is not None and code < 0 else f"exit {code}"
            res.update(status="crashed", error=f"crashed ({how}): {_tail_line(text.decode(errors='replace'))}")
        files, size, left = {"log.txt": text}, len(text), []
        for path in sorted(p for p in out.rglob("*") if p.is_file()):
            n = path.stat().st_size
            if size + n > FILES_LIMIT_BYTES:
                left.append(path.relative_to(out).as_posix())
                continue
            files[path.relative_to(out).as_posix()] = path.read_bytes()
            size += n
        if left:
            res["files_left_out"] = left
        res["files"] = files
        return res


# -- the cluster ------------------------------------------------------------------------------------


def local_cluster(n: int):
    """N single-threaded worker processes on 127.0.0.1; the first holds the EXCLUSIVE resource, so
    timed points run one at a time while untimed ones use every worker."""
    from distributed import Nanny, Scheduler, SpecCluster  # local: Dask starts only for a sweep
    opts = {"host": LOOPBACK, "nthreads": 1, "memory_limit": 0, "dashboard": False, "silence_logs": logging.ERROR}
    workers = {f"point-worker-{i}": {"cls": Nanny, "options": {**opts, "resources": {EXCLUSIVE: 1} if i == 0 else {}}}
               for i in range(n)}
    # (dashboard_address ":0": None still binds Dask's default 8787, and a second sweep running
    # beside the first then warned on stderr that the port was taken, measured)
    scheduler = {"cls": Scheduler, "options": {"host": LOOPBACK, "port": 0, "dashboard": False,
                                               "dashboard_address": ":0"}}
    return SpecCluster(scheduler=scheduler, workers=workers, silence_logs=logging.ERROR, name="layerbvh-sweep")


@contextlib.contextmanager
def _sigint_ignored():
    """Processes started inside inherit SIGINT ignored: Ctrl-C (sent to the whole process group)
    reaches the sweep alone, which stops them in order instead of each dying with a traceback."""
    try:
        old = signal.signal(signal.SIGINT, signal.SIG_IGN)
    except ValueError:  # not the main thread: nothing to change
        yield
        return
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, old)


def scheduler_address(text: str) -> str:
    """ADDRESS, HOST:PORT or the JSON file `dask scheduler --scheduler-file` writes."""
    if Path(text).is_file():
        try:
            return json.loads(Path(text).read_text())["address"]
        except (OSError, ValueError, KeyError):
            raise UserError(f"--scheduler {text}: not a Dask scheduler file (no 'address')") from None
    return text if "://" in text else f"tcp://{text}"


@contextlib.contextmanager
def dask_client(workers: int | None, scheduler: str | None, slurm: SlurmSettings | None = None,
                out: Path | None = None):
    """A client of a new local cluster of `workers` processes, of the scheduler at `scheduler`, or of
    a new cluster of SLURM jobs (`slurm`; its job script goes to `out`)."""
    from distributed import Client  # local: Dask starts only for a sweep
    for name in ("distributed", "tornado"):
        logging.getLogger(name).setLevel(logging.ERROR)
    cluster = None
    try:
        if slurm is not None:
            cluster = make_cluster(slurm, out, EXCLUSIVE)
            client = Client(cluster)
        elif scheduler:
            address = scheduler_address(scheduler)
            try:
                client = Client(address, timeout=CONNECT_TIMEOUT_S)
            except (OSError, TimeoutError) as e:
                raise UserError(f"--scheduler {scheduler}: cannot connect to {address} ({e})") from None
        else:
            with _sigint_ignored():
                cluster = local_cluster(workers)
            client = Client(cluster)
        try:
            yield client
        finally:
            client.close()
    finally:
        if cluster is not None:
            cluster.close()


def describe_cluster(client) -> dict:
    try:
        workers = client.scheduler_info(n_workers=-1)["workers"]  # newer Dask lists 5 workers by default
    except TypeError:
        workers = client.scheduler_info()["workers"]
    return {"scheduler": client.scheduler.address, "workers": len(workers),
            "hosts": sorted({w.get("host", "?") for w in workers.values()}),
            "exclusive_workers": sum(1 for w in workers.values() if w.get("resources", {}).get(EXCLUSIVE))}


# -- the sweep --------------------------------------------------------------------------------------


@dataclass
class SweepResult:
    """What a sweep left: its points, each one's stored result (None: not run), what this run ran."""

    out: Path
    points: list
    results: list
    ran: list = field(default_factory=list)
    wall_s: float = 0.0
    cluster: dict = field(default_factory=dict)
    interrupted: bool = False

    @property
    def failed(self) -> list:
        return [p for p, r in zip(self.points, self.results) if r is None or r["status"] != STATUS_OK]


class RunLog:
    """runs.json: per invocation of the sweep, which points it reused and which it ran (and how they ended)."""

    def __init__(self, out: Path, entry: dict):
        self.path = out / RUNS_FILE
        try:
            self.doc = json.loads(self.path.read_text())
        except (OSError, ValueError):
            self.doc = {"runs": []}
        self.entry = {**entry, "ran": [], "failed": []}
        self.doc["runs"].append(self.entry)
        self.write()

    def point(self, point: Point, status: str) -> None:
        self.entry["ran"].append(point.key)
        if status != STATUS_OK:
            self.entry["failed"].append(point.key)
        self.write()

    def close(self, **fields) -> None:
        self.entry.update(fields)
        self.write()

    def write(self) -> None:
        atomic.write_text(self.path, json.dumps(self.doc, indent=1))


def run_sweep(points: list[Point], out, *, workers: int | None = None, scheduler: str | None = None,
              client=None, limits: Limits | None = None, rerun: bool = False, progress: bool = True,
              command: str = "", slurm: SlurmSettings | None = None) -> SweepResult:
    """Run every point without a stored successful result as one Dask task; store each as it finishes;
    write the tables (sweep.table). Ctrl-C stops it with the finished points stored and the tables written."""

    out = Path(out).absolute()
    t0 = time.perf_counter()
    results = [None if rerun else load_result(out, p) for p in points]
    todo = [i for i, r in enumerate(results) if r is None or r["status"] != STATUS_OK]
    res = SweepResult(out, points, results)
    if client is not None or not todo:
        connection = contextlib.nullcontext(client)
    else:
        out.mkdir(parents=True, exist_ok=True)  # the SLURM job script and logs go next to the results
        connection = dask_client(workers, scheduler, slurm, out)
    with connection as c:  # connected (and checked) before anything is written
        if c is not None:
            res.cluster = describe_cluster(c)
            _check_cluster(c, res.cluster, any(JOBS[points[i].job].timed for i in todo))
        out.mkdir(parents=True, exist_ok=True)
        log = RunLog(out, {"started": datetime.now(timezone.utc).isoformat(timespec="seconds"), "command": command,
                           "points": len(points), "reused": [points[i].key for i in range(len(points))
                                                             if i not in todo]})
        try:
            if todo:
                lim = limits or Limits(slots=workers if client is None and not scheduler and not slurm and workers
                                       else 1)
                with tqdm(total=len(points), initial=len(points) - len(todo), desc="sweep", unit="point",
                          disable=not progress, file=sys.stderr) as bar:
                    _run_tasks(c, points, todo, lim, res, log, bar)
        except KeyboardInterrupt:
            res.interrupted = True
        finally:
            res.wall_s = time.perf_counter() - t0
            log.close(finished=datetime.now(timezone.utc).isoformat(timespec="seconds"), wall_s=res.wall_s,
                      interrupted=res.interrupted, cluster=res.cluster)
            sweep_table.write_tables(res, command)
    return res


def _check_cluster(client, info: dict, timed: bool) -> None:
    if not info["workers"]:  # workers may still be joining (e.g. SLURM jobs starting)
        try:
            client.wait_for_workers(1, timeout=WAIT_WORKERS_S)
        except TimeoutError:
            raise UserError(f"no Dask worker connected to {info['scheduler']} within {WAIT_WORKERS_S:g} s") from None
        info.update(describe_cluster(client))
    if timed and not info["exclusive_workers"]:
        raise UserError(f"timed jobs (converge, bench) need a worker with the '{EXCLUSIVE}' resource and none of the "
                        f"{info['workers']} workers at {info['scheduler']} has it: start one worker per machine with "
                        f"`dask worker ADDRESS --resources {EXCLUSIVE}=1`")


def _run_tasks(client, points, todo, limits: Limits, res: SweepResult, log: RunLog, bar) -> None:
    from distributed import wait  # local: Dask starts only for a sweep
    futures = {}
    for i in todo:
        p = points[i]
        fut = client.submit(run_point_task, asdict(p), asdict(limits), key=f"point-{p.key[:24]}-{time.time_ns()}",
                            resources={EXCLUSIVE: 1} if JOBS[p.job].timed else None, pure=False, retries=0)
        futures[fut] = i
    pending, idle_since = set(futures), None
    try:
        while pending:
            try:
                done, pending = wait(pending, timeout=1.0, return_when="FIRST_COMPLETED")
            except TimeoutError:
                done = set()
            for fut in done:
                i = futures[fut]
                if fut.status == "finished":
                    run = fut.result()
                else:  # the worker died under it (KilledWorker) or the task itself raised
                    exc = fut.exception()
                    run = {"status": "crashed", "error": f"crashed: {type(exc).__name__}: {_tail_line(str(exc))}",
                           "host": None, "wall_s": None, "files": {}}
                res.results[i] = store_result(res.out, points[i], run)
                res.ran.append(points[i].key)
                log.point(points[i], run["status"])
                bar.update(1)
                if run["status"] != STATUS_OK:
                    bar.write(f"{points[i].name} [{points[i].label}]: {run['error']}", file=sys.stderr)
            if not done:
                workers = describe_cluster(client)["workers"]
                idle_since = None if workers else (idle_since or time.monotonic())
                if idle_since is not None and time.monotonic() - idle_since > WAIT_WORKERS_S:
                    bar.write(f"no Dask worker for {WAIT_WORKERS_S:g} s: stopping with {len(pending)} points not run",
                              file=sys.stderr)
                    break
    finally:
        for fut in pending:
            fut.cancel()
