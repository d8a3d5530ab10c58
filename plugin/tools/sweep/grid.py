"""`layerbvh sweep`: a grid of scenes × configurations run as Dask tasks, each point in a fresh process, resumable by a content key, gathered into one table."""
from __future__ import annotations

import contextlib
import glob
import hashlib
import json
import logging
import os
import re
import shlex
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import time
from dataclasses import asdict, dataclass, field
from datetime import datetime, timezone
from importlib import metadata
from pathlib import Path
from types import SimpleNamespace
from typing import Callable

import mitsuba as mi
import psutil
from tqdm import tqdm

import layerbvh
from layerbvh_mitsuba import atomic
from layerbvh_mitsuba.ab.render import UserError
from layerbvh_mitsuba.ab.stock_cache import SceneFilesError, reference_key
from layerbvh_mitsuba.runtime import record
from layerbvh_mitsuba.runtime.settings import EMBREE, Traversal, check_settings
from layerbvh_mitsuba.tools.bench.locality import (
    DEFAULT_CAP,
    DEFAULT_KINDS,
    DEFAULT_PRESETS,
    DEFAULT_SPP,
    request_from_args,
)
from layerbvh_mitsuba.tools.converge import ConvergeError, parse_configs
from layerbvh_mitsuba.tools.sweep import table as sweep_table
from layerbvh_mitsuba.tools.sweep.slurm import WALLTIME_MARGIN_S, SlurmSettings, check, make_cluster, time_left_in_job
from layerbvh_mitsuba.tools.sweep.table import short_name

EXCLUSIVE = "exclusive"  # Dask worker resource held by timed points: one per machine, so they never overlap
LOOPBACK = "127.0.0.1"  # the local cluster listens here only
SWEEP_FORMAT = 1  # part of every key: bump when a point's stored result changes shape
POLL_S = 0.2  # how often a running point's time and memory are checked
DEFAULT_TIMEOUT_S = 3600.0
MEMORY_SHARE = 0.8  # default memory limit: this share of the host's RAM, split over the points it runs at once
WAIT_WORKERS_S = 120.0  # a sweep with points left and no worker connected for this long stops
CONNECT_TIMEOUT_S = 30.0
KILL_WAIT_S = 10.0
LOG_TAIL_BYTES = 256 << 10  # a point's log.txt comes back with at most this much of its end
FILES_LIMIT_BYTES = 512 << 20  # a point's output files travel back up to this total; larger ones are left out
STATUS_OK = "ok"  # the job ran and gave its figures; anything else (error, killed, crashed) runs again next time
POINTS_DIR = "points"
RESULT_FILE = "result.json"
RUNS_FILE = "runs.json"


# -- points -----------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Point:
    """One (scene, configuration) of the grid: what its process runs and the key its result is stored under."""

    job: str
    scene: str  # absolute path, the same on every worker (shared filesystem)
    name: str  # the scene as shown in the table
    settings: dict  # the job's options for this point (JSON types); part of the key
    key: str = ""

    @property
    def label(self) -> str:
        return JOBS[self.job].label(self.settings)

    @property
    def dirname(self) -> str:
        """Folder of its stored result: readable, and a function of the key's inputs only."""
        slug = re.sub(r"[^A-Za-z0-9_.=+-]+", "_", f"{short_name(self.name)}-{self.label}").strip("_")
        return f"{slug}-{self.key[:12]}"


@dataclass(frozen=True)
class Job:
    """What a point of this job runs (sweep.point.RUNNERS), how it is labelled and whether it is timed."""

    name: str
    timed: bool  # timed points take the EXCLUSIVE resource: one at a time per machine
    label: Callable[[dict], str]  # settings -> the config column


JOBS = {
    "compare": Job("compare", False,
                   lambda s: s["traversal"] if s["traversal"] == EMBREE else
                   f"{s['traversal']} K={s.get('branching', 2)} h={s['treelet_height']}"),
    "converge": Job("converge", True, lambda s: s["config"]),
    "bench": Job("bench", True, lambda s: f"{s['rays']} rays K={','.join(map(str, s.get('branchings', [2])))} "
                                          f"h={','.join(map(str, s['heights']))}"),
    "third_party": Job("third_party", False, lambda s: s["traversal"]),
    "locality": Job("locality", False, lambda s: f"{s['rays']} rays K={s.get('branching', 2)} h={s['treelet_height']}"),
}
CLI_JOBS = ("compare", "converge", "bench", "locality")  # third_party is driven by scripts/third_party.py
GENERATED_RAYS = ("coherent", "incoherent")  # bench rays generated over the scene's triangles (meshes.py)


def code_digest() -> str:
    """SHA-256 of the engine's and the plugin's Python sources: a result computed by other code is not reused."""
    h = hashlib.sha256()
    for package, base in (("layerbvh", Path(layerbvh.__file__).parent), ("layerbvh_mitsuba", Path(__file__).parents[2])):
        for path in sorted(base.rglob("*.py")):
            h.update(f"{package}/{path.relative_to(base).as_posix()}".encode() + b"\0")
            h.update(hashlib.sha256(path.read_bytes()).digest())
    return h.hexdigest()[:16]


def versions() -> dict:

    return {"layerbvh": layerbvh.__version__, "code": code_digest(),
            **{pkg: metadata.version(pkg) for pkg in ("mitsuba", "drjit")}}


def point_key(job: str, scene: Path, settings: dict, vers: dict) -> str:
    """`stock_cache.reference_key` (the scene and every file it references) over the job, its settings and
    the versions. A scene whose references cannot be read still gets a key (from its own bytes): its
    point runs and reports the problem."""
    what = {"sweep": SWEEP_FORMAT, "job": job, "settings": settings, "versions": vers}
    try:
        return reference_key(scene, what)
    except SceneFilesError:
        h = hashlib.sha256(scene.read_bytes())
        h.update(json.dumps(what, sort_keys=True).encode())
        return h.hexdigest()


def make_points(job: str, scenes: list[tuple[str, str]], grid: list[dict]) -> list[Point]:
    """Every (scene, settings) pair, keyed; a pair that repeats another's key is kept once."""
    vers = versions()
    out, seen = [], set()
    for path, name in scenes:
        for settings in grid:
            key = point_key(job, Path(path), settings, vers)
            if key not in seen:
                seen.add(key)
                out.append(Point(job, str(Path(path).resolve()), name, settings, key))
    return out


# -- the stored results -----------------------------------------------------------------------------


def load_result(out: Path, point: Point) -> dict | None:
    path = out / POINTS_DIR / point.dirname / RESULT_FILE
    try:
        res = json.loads(path.read_text())
    except (OSError, ValueError):
        return None
    return res if res.get("key") == point.key else None


def store_result(out: Path, point: Point, run: dict) -> dict:
    """The point's files and result.json under points/<dirname>, replacing any earlier attempt as one rename."""
    files = run.pop("files", {})
    res = {"key": point.key, "job": point.job, "scene": point.name, "config": point.label, "settings": point.settings,
           **run, "files": sorted(files)}
    base = out / POINTS_DIR
    base.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(dir=base, prefix=f".tmp-{point.key[:12]}-"))
    try:
        for rel, data in files.items():
            (tmp / rel).parent.mkdir(parents=True, exist_ok=True)
            (tmp / rel).write_bytes(data)
        (tmp / RESULT_FILE).write_text(json.dumps(res, indent=1))
        os.chmod(tmp, 0o755)  # mkdtemp makes it 0700
        final = base / point.dirname
        old = None
        if final.exists():
            old = base / f".old-{point.dirname}-{os.getpid()}"
            os.rename(final, old)
        os.rename(tmp, final)
        if old is not None:
            shutil.rmtree(old, ignore_errors=True)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return res


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
    scheduler = {"cls": Scheduler, "options": {"host": LOOPBACK, "port": 0, "dashboard": False,
                                               "dashboard_address": None}}
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
def dask_client(workers: int | None, scheduler: str | None, slurm: SlurmSettings | None = None, out: Path | None = None):
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


# -- the command ------------------------------------------------------------------------------------


def _int_list(text: str, option: str) -> list[int]:
    try:
        vals = [int(x) for x in text.split(",") if x.strip()]
    except ValueError:
        raise UserError(f"{option} must be a comma list of integers, got {text!r}") from None
    if not vals:
        raise UserError(f"{option} is empty")
    return vals


def _names(text: str) -> list[str]:
    return [x.strip() for x in text.split(",") if x.strip()]


def add_parser(sub) -> None:
    """The `sweep` sub-command of `layerbvh` (cli.py)."""
    s = sub.add_parser("sweep", help="a grid of scenes x configurations on Dask (local processes or a cluster), "
                                     "resumable, one results table")
    s.add_argument("scenes", nargs="+", metavar="SCENE_OR_GLOB", help="Mitsuba 3 XML scenes (globs are expanded)")
    s.add_argument("--job", required=True, choices=CLI_JOBS,
                   help="compare: stock vs layerbvh A/B per traversal and treelet height; converge: error against "
                        "time per configuration (timed); bench: traversal throughput on the scene's triangles (timed); "
                        "locality: memory transactions and cache hits of the scene's recorded rays per mode (a model, "
                        "untimed)")
    s.add_argument("--out", required=True, help="sweep folder: results.csv/.json, summary.md, index.html, points/")
    where = s.add_mutually_exclusive_group()
    where.add_argument("--workers", type=int, help="worker processes of a local Dask cluster (default: cores)")
    where.add_argument("--scheduler", help="an existing Dask scheduler: ADDRESS (tcp://host:port) or its scheduler file")
    where.add_argument("--cluster", choices=("slurm",), help="slurm: the workers as SLURM jobs (dask-jobqueue; the "
                                                            "--slurm-* options), started and ended by the sweep")
    s.add_argument("--slurm-partition", help="slurm: partition (sbatch -p; default: the cluster's default)")
    s.add_argument("--slurm-account", help="slurm: account to charge (sbatch -A)")
    s.add_argument("--slurm-cores", type=int, default=1, help="slurm: cores per job; untimed points run one per core "
                                                              "(default %(default)s)")
    s.add_argument("--slurm-memory", type=float, default=4.0, metavar="GIB", help="slurm: memory per job in GiB "
                                                                                  "(default %(default)g)")
    s.add_argument("--slurm-walltime", default="01:00:00", help="slurm: time limit per job, [D-]HH:MM:SS (default "
                                                                "%(default)s); a point that would outlast its job "
                                                                "fails with a line naming it")
    s.add_argument("--slurm-jobs", type=int, default=1, help="slurm: jobs (workers) to run at once (default "
                                                            "%(default)s; with --slurm-adapt-min, the most)")
    s.add_argument("--slurm-adapt-min", type=int, help="slurm: scale adaptively between this many jobs and "
                                                       "--slurm-jobs (jobs end when idle)")
    s.add_argument("--slurm-extra", action="append", default=[], metavar="DIRECTIVE",
                   help="slurm: one more #SBATCH directive, e.g. --slurm-extra=--constraint=avx512 (repeatable)")
    s.add_argument("--spp", help="compare: spp, comma list (default: the scene's); bench: spp of the ray recording "
                                 "(default 4)")
    s.add_argument("--res", type=int, nargs=2, metavar=("W", "H"),
                   help="film resolution (default: the scene's; bench recordings 512 512)")
    s.add_argument("--seed", type=int, default=None, help="compare, bench: seed (default 0)")
    s.add_argument("--traversal", help="compare: comma list of auto, per_ray, layer_sorted, layer_unsorted, embree "
                                       "(default auto)")
    s.add_argument("--treelet-heights", help=f"compare, bench: comma list (default "
                                             f"{layerbvh.DEFAULT_TREELET_HEIGHT}; bench 4,8,12)")
    s.add_argument("--branchings", help=f"compare, bench, locality: children per BVH node, comma list of 2, 4, 8 (default "
                                        f"{layerbvh.DEFAULT_BRANCHING})")
    s.add_argument("--configs", help="converge: comma list, one point each: stock, embree, auto, per_ray, "
                                     "layer_sorted:H, layer_unsorted:H (default stock,per_ray,layer_sorted)")
    s.add_argument("--budget", type=float, help="converge: seconds of rendering per configuration (required)")
    s.add_argument("--ref-spp", type=int, help="converge: spp of the stock reference (default 4096)")
    s.add_argument("--max-spp", type=int, help="converge: stop doubling here (default ref spp / 16)")
    s.add_argument("--rays", help=f"bench: comma list of ray sets, one point each: {', '.join(GENERATED_RAYS)} "
                                  f"(generated over the scene's triangles) or recorded kinds (camera, "
                                  f"first_bounce_diffuse, diffuse, glossy, specular, shadow) (default "
                                  f"{','.join(GENERATED_RAYS)})")
    s.add_argument("--ray-count", type=int, help="bench: rays per set (default 1,000,000); locality: rays recorded "
                                                 "per kind at most (default 1,000,000)")
    s.add_argument("--preset", help="locality: comma list of hardware presets (default gtx965m,h200,cpu)")
    s.add_argument("--warp", help="locality: comma list of warp widths (default: each preset's own)")
    s.add_argument("--sample", type=int, help="locality: replay at most N rays per kind (default: all)")
    s.add_argument("--segment", help="locality: comma list of transaction sizes in bytes (default: each preset's own)")
    s.add_argument("--runs", type=int, help="bench: timed runs per configuration (default 5)")
    s.add_argument("--variant", default="llvm_ad_rgb", help="Mitsuba variant (llvm_ad_rgb, cuda_ad_rgb)")
    s.add_argument("--timeout", type=float, default=DEFAULT_TIMEOUT_S,
                   help="seconds per point; a point past it is killed and recorded (default %(default)g)")
    s.add_argument("--memory-limit", type=float, metavar="GIB",
                   help=f"resident memory per point in GiB; a point above it is killed and recorded (default "
                        f"{MEMORY_SHARE:g} x the host's RAM, divided among the local workers for untimed jobs)")
    s.add_argument("--rerun", action="store_true", help="run every point again, ignoring stored results")
    s.add_argument("--no-progress", action="store_true")


JOB_OPTIONS = {  # which options each job takes (an option given to another job is an error)
    "compare": {"spp", "res", "seed", "traversal", "treelet_heights", "branchings"},
    "converge": {"res", "configs", "budget", "ref_spp", "max_spp"},
    "bench": {"spp", "res", "seed", "treelet_heights", "branchings", "rays", "ray_count", "runs"},
    "locality": {"spp", "res", "seed", "treelet_heights", "branchings", "rays", "ray_count", "preset", "warp", "sample",
                 "segment"},
}
ALL_JOB_OPTIONS = set().union(*JOB_OPTIONS.values())


def expand_scenes(patterns: list[str]) -> list[tuple[str, str]]:
    """(path, name) of every scene: a path is taken as given, a glob is expanded (sorted)."""
    out = []
    for pat in patterns:
        if any(c in pat for c in "*?["):
            hits = sorted(h for h in glob.glob(pat, recursive=True) if Path(h).is_file())
            if not hits:
                raise UserError(f"no scene file matches {pat}")
        elif Path(pat).is_file():
            hits = [pat]
        else:
            raise UserError(f"scene file not found: {pat}")
        out += [(h, h) for h in hits if (h, h) not in out]
    return out


def grid(args) -> list[dict]:
    """The settings of every configuration the options ask for (one point per scene each)."""

    for opt in sorted(ALL_JOB_OPTIONS - JOB_OPTIONS[args.job]):
        if getattr(args, opt) is not None:
            raise UserError(f"--{opt.replace('_', '-')} does not apply to --job {args.job}")
    if args.variant not in mi.variants():
        raise UserError(f"--variant: Mitsuba variant {args.variant!r} is not available (choose one of "
                        f"{', '.join(mi.variants())})")
    if args.res is not None and min(args.res) < 1:
        raise UserError(f"--res must be positive, got {args.res[0]} {args.res[1]}")
    res = list(args.res) if args.res else None
    seed = 0 if args.seed is None else args.seed
    branchings = _int_list(args.branchings, "--branchings") if args.branchings else [layerbvh.DEFAULT_BRANCHING]
    for k in branchings:
        try:
            layerbvh.check_param("branching", k)
        except ValueError as e:
            raise UserError(f"--branchings: {e}") from None
    if args.job == "compare":
        spps = _int_list(args.spp, "--spp") if args.spp else [None]
        if any(s is not None and s < 1 for s in spps):
            raise UserError(f"--spp must be >= 1, got {args.spp}")
        traversals = _names(args.traversal or layerbvh.AUTO)
        heights = _int_list(args.treelet_heights, "--treelet-heights") if args.treelet_heights else \
            [layerbvh.DEFAULT_TREELET_HEIGHT]
        for t in traversals:
            for h in heights:
                try:
                    Traversal.parse(t)
                    check_settings(max_depth=-1, rr_depth=5, treelet_height=h, leaf_size=layerbvh.DEFAULT_LEAF_SIZE,
                                   batch_rays=1)
                except ValueError as e:
                    name, _, rule = str(e).partition(" ")
                    opt = "--treelet-heights" if name == "treelet_height" else f"--{name.replace('_', '-')}"
                    raise UserError(f"{opt} {rule}") from None
        return [{"traversal": t, "treelet_height": layerbvh.DEFAULT_TREELET_HEIGHT if t == EMBREE else h,
                 "branching": layerbvh.DEFAULT_BRANCHING if t == EMBREE else k,
                 "spp": spp, "res": res, "seed": seed, "variant": args.variant}
                for spp in spps for t in traversals for k in ([None] if t == EMBREE else branchings)
                for h in ([None] if t == EMBREE else heights)]
    if args.job == "converge":
        if args.budget is None:
            raise UserError("--job converge needs --budget SECONDS")
        if args.budget <= 0:
            raise UserError(f"--budget must be > 0 seconds, got {args.budget}")
        try:
            configs = parse_configs(args.configs or "stock,per_ray,layer_sorted")
        except ConvergeError as e:
            raise UserError(str(e)) from None
        return [{"config": c.name, "budget": args.budget, "ref_spp": args.ref_spp or 4096, "max_spp": args.max_spp,
                 "res": res, "variant": args.variant} for c in configs]
    if args.job == "locality":
        return _locality_grid(args, res, seed, branchings)
    kinds = _names(args.rays or ",".join(GENERATED_RAYS))
    for k in kinds:
        if k not in GENERATED_RAYS + record.KINDS:
            raise UserError(f"--rays: unknown ray set {k!r}; use {', '.join(GENERATED_RAYS + record.KINDS)}")
    heights = _int_list(args.treelet_heights or "4,8,12", "--treelet-heights")
    for h in heights:
        try:
            layerbvh.check_param("treelet_height", h)
        except ValueError as e:
            raise UserError(f"--treelet-heights: {e}") from None
    spp = _int_list(args.spp, "--spp") if args.spp else [4]
    if len(spp) != 1 or spp[0] < 1:
        raise UserError(f"--spp for --job bench is one value >= 1 (the recording's), got {args.spp}")
    for opt, val in (("--ray-count", args.ray_count), ("--runs", args.runs)):
        if val is not None and val < 1:
            raise UserError(f"{opt} must be >= 1, got {val}")
    # res and spp make the recording; generated ray sets do not depend on them (nor does their key)
    return [{"rays": k, "heights": heights, "branchings": branchings, "ray_count": args.ray_count or 1_000_000,
             "runs": args.runs or 5,
             "res": None if k in GENERATED_RAYS else res or [512, 512], "spp": None if k in GENERATED_RAYS else spp[0],
             "seed": seed, "variant": args.variant} for k in kinds]


def _locality_grid(args, res, seed: int, branchings: list[int]) -> list[dict]:
    """One point per recorded kind, treelet height and branching; each replays every mode x preset x warp."""


    opts = SimpleNamespace(scene="", res=res, spp=int(args.spp) if args.spp and args.spp.isdigit() else None,
                           seed=seed, rays=args.rays or ",".join(DEFAULT_KINDS), warp=args.warp,
                           preset=args.preset or ",".join(DEFAULT_PRESETS),
                           treelet_heights=args.treelet_heights or str(layerbvh.DEFAULT_TREELET_HEIGHT),
                           modes=",".join(layerbvh.MODES), leaf_size=None, sample=args.sample,
                           cap=args.ray_count or DEFAULT_CAP, no_check=False, segment=args.segment)
    if args.spp and not args.spp.isdigit():
        raise UserError(f"--spp for --job locality is one value >= 1 (the recording's), got {args.spp}")
    try:
        req = request_from_args(opts)
    except ValueError as e:
        raise UserError(str(e)) from None
    return [{"rays": k, "treelet_height": h, "presets": list(req.presets), "warps": list(req.warps or []) or None,
             "res": res, "spp": req.spp or DEFAULT_SPP, "seed": seed, "sample": req.sample, "ray_count": req.cap,
             "segments": list(req.segments) if req.segments else None, "variant": args.variant, "branching": b}
            for k in req.kinds for h in req.treelet_heights for b in branchings]


def run_command(args) -> int:
    """`layerbvh sweep ...` (cli.py dispatches here)."""
    if args.workers is not None and args.workers < 1:
        raise UserError(f"--workers must be >= 1, got {args.workers}")
    if args.timeout <= 0:
        raise UserError(f"--timeout must be > 0 seconds, got {args.timeout:g}")
    if args.memory_limit is not None and args.memory_limit <= 0:
        raise UserError(f"--memory-limit must be > 0 GiB, got {args.memory_limit:g}")
    settings = grid(args)
    points = make_points(args.job, expand_scenes(args.scenes), settings)
    slurm = None
    if args.cluster == "slurm":
        slurm = check(SlurmSettings(partition=args.slurm_partition, account=args.slurm_account, cores=args.slurm_cores,
                                    memory_gib=args.slurm_memory, walltime=args.slurm_walltime, jobs=args.slurm_jobs,
                                    adapt_min=args.slurm_adapt_min, extra=tuple(args.slurm_extra)))
    workers = None if args.scheduler or slurm else (args.workers or os.cpu_count() or 1)
    slots = 1 if JOBS[args.job].timed else (slurm.cores if slurm else (workers or 1))
    memory = args.memory_limit or (slurm.memory_gib * MEMORY_SHARE if slurm else None)  # a job's memory, shared
    limits = Limits(timeout_s=args.timeout, memory_bytes=int(memory * (1 << 30) / (slots if slurm and not
                    args.memory_limit else 1)) if memory else None, slots=slots)
    command = shlex.join(["layerbvh", *sys.argv[1:]]) if Path(sys.argv[0]).name == "layerbvh" else \
        shlex.join(getattr(sys, "orig_argv", sys.argv))
    res = run_sweep(points, args.out, workers=workers, scheduler=args.scheduler, limits=limits, rerun=args.rerun,
                    progress=not args.no_progress, command=command, slurm=slurm)
    done = sum(1 for r in res.results if r is not None)
    bad = len(res.failed)
    print(f"{len(points)} points: {len(points) - bad} ok, {bad} failed or not run; ran {len(res.ran)}, reused "
          f"{done - len(res.ran)}; {res.wall_s:.1f} s")
    print(str(res.out / "index.html"))
    if res.interrupted:
        print(f"layerbvh: interrupted; {done} of {len(points)} points stored, tables written", file=sys.stderr)
        return 130
    if bad:  # scripts and CI must notice; the table is written all the same
        print(f"layerbvh: {bad} of {len(points)} points failed (see {res.out / 'summary.md'})", file=sys.stderr)
        return 1
    return 0
