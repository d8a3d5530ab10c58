"""A sweep's points (job, scene, settings) and their content keys, and the results stored under them: what a resumed
sweep finds done."""
from __future__ import annotations

import hashlib
import json
import os
import re
import shutil
import tempfile
from dataclasses import dataclass
from importlib import metadata
from pathlib import Path
from typing import Callable


import layerbvh
from layerbvh_mitsuba.ab.stock_cache import SceneFilesError, reference_key
from layerbvh_mitsuba.runtime.settings import EMBREE
from layerbvh_mitsuba.tools.sweep.table import short_name


SWEEP_FORMAT = 1  # part of every key: bump when a point's stored result changes shape

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
    packages = (("layerbvh", Path(layerbvh.__file__).parent), ("layerbvh_mitsuba", Path(__file__).parents[2]))
    for package, base in packages:
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
