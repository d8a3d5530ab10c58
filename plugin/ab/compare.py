"""One A/B comparison: stock Mitsuba (Embree) against ours on one scene, in the scene's own integrator where ours
mirrors it (path, direct, aov/moment around them), at the same seed, then the two-step verdict. The command line, the
sweep, the third-party table, the pytest helpers and the stability suite all run this."""
from __future__ import annotations

import time
from dataclasses import dataclass, field
from functools import cached_property
from pathlib import Path
from typing import Callable, Mapping

import mitsuba
import numpy as np

import layerbvh
from layerbvh_mitsuba.ab import hypotheses, metrics, referee
from layerbvh_mitsuba.ab.gradient import GradientComparison, check_gradient, compare_gradients
from layerbvh_mitsuba.ab.page import split_share
from layerbvh_mitsuba.ab.referee import Referee
from layerbvh_mitsuba.ab.render import TimedRender, load_integrator, load_scene, scene_spp, timed_render
from layerbvh_mitsuba.ab.memory import check_memory
from layerbvh_mitsuba.ab.scene_integrator import PathSettings, path_settings
from layerbvh_mitsuba.ab.stock_cache import cached_stock
from layerbvh_mitsuba.ab.verdict import Verdict, judge, load_modified, same_seed_only
from layerbvh_mitsuba.runtime.settings import EMBREE, Traversal
from layerbvh_mitsuba.runtime.stats import RenderStats

STATS_SPP = 4  # spp of the separate counted pass (statistics, heat maps: work per ray needs few samples)
STOCK, OURS = "stock", "ours"


@dataclass(frozen=True)
class CompareSettings:
    """What one comparison renders. Ours gets the scene's own estimator settings (both sides do),
    then our integrator's properties below, then `ours_props` on top."""

    scene: str | Path
    spp: int | None = None                # None: the scene's sampler's
    res: tuple[int, int] | None = None    # film (W, H); None: the scene's
    seed: int = 0
    traversal: Traversal = Traversal(layerbvh.AUTO)
    treelet_height: int = layerbvh.DEFAULT_TREELET_HEIGHT
    branching: int = layerbvh.DEFAULT_BRANCHING
    leaf_size: int | None = None          # None: the branching's default
    as_path: bool = False                 # compare a scene whose integrator is not path, as path
    path_overrides: Mapping = field(default_factory=dict)  # path settings set over the scene's (both sides)
    params: Mapping = field(default_factory=dict)      # the scene's $parameters
    ours_props: Mapping = field(default_factory=dict)  # more layerbvh properties (max_depth, batch_rays, ...)
    ours_modify: Callable | None = None   # ours' copy of the scene changed by ours_modify(mi.traverse(copy))
    control: bool = False                 # also time our loop with Embree's queries: traversal vs loop
    statistics_pass: bool = False         # a counted pass: traversal statistics and heat maps
    statistical_step: bool = True         # where same-seed paths diverge, the independent-seed test
    grad: str | None = None               # also compare derivatives w.r.t. this mi.traverse key (ab/gradient.py)
    integrator: Mapping | None = None     # both sides render this ({"type": "ptracer", ...}), not the scene's
    stock_cache: Path | None = None       # keep stock's image there (stock_cache.cached_stock)
    progress: bool = False


class ComparisonFailed(Exception):
    """A side could not be loaded, set up or rendered: `side` (STOCK or OURS), `stage` ("load",
    "setup", "render") and the error itself (`error`, also the __cause__)."""

    def __init__(self, side: str, stage: str, error: BaseException):
        super().__init__(f"{side} {stage}: {error}")
        self.side, self.stage, self.error = side, stage, error


@dataclass
class SideTime:
    """Where one side's render time went (ab.render.TimedRender less its image)."""

    render_s: float           # the render itself: wall time less compilation and calibration
    compile_s: float = 0.0
    wall_s: float = 0.0
    calibration_s: float = 0.0
    cached: bool = False      # stock's image came from the cache (no time spent)

    @classmethod
    def of(cls, r: TimedRender) -> "SideTime":
        return cls(r.seconds, r.compile_s, r.wall_s, r.calibration_s)

    def as_dict(self) -> dict:
        return {"render_s": self.render_s, "compile_s": self.compile_s, "wall_s": self.wall_s}


@dataclass
class Comparison:
    """What a comparison found. Images are (H, W, C) float32; NaN/Inf pixels (counted in
    `nonfinite`, stock then ours) are 0 in them, so metrics and the verdict stay finite."""

    settings: CompareSettings
    spp: int
    resolution: tuple[int, int]     # (W, H)
    variant: str
    path: PathSettings              # the path settings both sides rendered with
    ours_props: dict                # the layerbvh integrator's properties
    stock: np.ndarray = field(repr=False)
    ours: np.ndarray = field(repr=False)
    nonfinite: tuple[int, int]
    stock_time: SideTime
    ours_time: SideTime
    stats: RenderStats              # ours' timed render
    verdict: Verdict
    control_time: SideTime | None = None
    counted: RenderStats | None = None   # the statistics pass
    counted_time: SideTime | None = None
    heatmaps: dict = field(default_factory=dict, repr=False)
    gradient: GradientComparison | None = None          # with settings.grad
    referee: Referee | str | None = None  # a scene far from unit size: the unit-scale referee, or why not (referee.py)
    scene: object = field(default=None, repr=False)       # the loaded scene (stock's copy)
    integrator: object = field(default=None, repr=False)  # ours, as it rendered (its tracer holds the BVH)

    @property
    def passed(self) -> bool:
        return self.verdict.passed

    @cached_property
    def measured(self) -> tuple[dict, np.ndarray]:
        """(metrics.compare_images of ours against stock, the ꟻLIP map): measured once, when first
        asked for (the report and the tables do; the same-seed helpers never pay for ꟻLIP)."""
        return metrics.compare_images_with_flip_map(self.stock, self.ours)

    @property
    def metrics(self) -> dict:
        return self.measured[0]

    def split(self) -> dict | None:
        """Our time split by the control: loop (ours with Embree less stock) and traversal (ours
        less ours with Embree)."""
        if self.control_time is None:
            return None
        st, ctl, ou = self.stock_time.render_s, self.control_time.render_s, self.ours_time.render_s
        return {"loop_s": ctl - st, "traversal_s": ou - ctl, "ours_over_stock": ou / st if st else None}

    def info(self) -> dict:
        """report.json's description of the run (report.write_report's `info`)."""
        s = self.settings
        info = {
            "scene": str(s.scene), "spp": self.spp, "resolution": list(self.resolution), "seed": s.seed,
            "variant": self.variant, "integrator": self.path.props, "scene_integrator": self.path.scene_integrator,
            "compared_as": self.path.compared_as,
            **({"compared_as_note": self.path.note} if self.path.note else {}),
            **({"params": dict(s.params)} if s.params else {}),
            "stock": {**self.stock_time.as_dict(), **({"cached": True} if self.stock_time.cached else {})},
            "ours": {**self.ours_time.as_dict(), "calibration_s": self.ours_time.calibration_s,
                     "build_s": self.stats.build_s,
                     "kernel_load_s": self.stats.bvh.kernel_load_s if self.stats.bvh else 0.0,
                     "loop": self.stats.loop, "trace_s": self.stats.trace_s, "shading_s": self.stats.shading_s,
                     "traversal": s.traversal.name, "treelet_height": s.treelet_height, "branching": s.branching,
                     **({"ours_props": dict(s.ours_props)} if s.ours_props else {})},
            "auto_choices": self.stats.auto_choices,
            "features": self.stats.features.as_dict(),
        }
        if any(self.nonfinite):
            info["nonfinite_pixels"] = {"stock": self.nonfinite[0], "ours": self.nonfinite[1],
                                        "note": "NaN/Inf pixels set to 0 for the metrics and the verdict"}
        if self.counted is not None:
            info["traversal"] = self.counted.traversal_dict()
            info["statistics_pass"] = {"spp": min(self.spp, STATS_SPP), "render_s": self.counted_time.render_s,
                                       "compile_s": self.counted_time.compile_s}
        if self.control_time is not None:
            info["embree_control"] = self.control_time.as_dict()
            info["split"] = self.split()
        if self.gradient is not None:
            info["gradient"] = self.gradient.as_dict()
        if isinstance(self.referee, Referee):
            info["referee"] = {**self.referee.as_dict(), "line": self.referee.line()}
        elif self.referee is not None:
            info["referee"] = {"refused": self.referee}
        return info

    def summary(self) -> str:
        """One line: the times, the split and the error metrics (what `layerbvh compare` prints)."""
        st, ou, m = self.stock_time.render_s, self.ours_time.render_s, self.metrics
        ratio = f" ({ou / st:.1f}x)" if st else ""
        split = ""
        if self.control_time is not None:
            sp = self.split()
            split = (f"; our loop with Embree {self.control_time.render_s:.2f} s: traversal "
                     f"{split_share(sp['traversal_s'])}, loop {split_share(sp['loop_s'])}")
        return (f"stock {st:.2f} s, layerbvh {ou:.2f} s{ratio}{split} (not counted: build {self.stats.build_s:.2f} s, "
                f"compile {self.ours_time.compile_s:.2f} s, calibration {self.ours_time.calibration_s:.2f} s); "
                f"rmse {m['rmse']:.3g}, FLIP {m['flip_mean']:.3g}, pixels > 1e-3: "
                f"{100 * m['frac_pixels_over_1e-3']:.3f}%"
                + ("" if self.gradient is None else f"; {self.gradient.summary()}"))


def ours_props(s: CompareSettings, path: PathSettings, traversal: Traversal | None = None, stats: bool = False) -> dict:
    """Our integrator's properties (the one standing in for the scene's estimator) for these
    settings and the scene's."""
    return {"type": path.ours_type, "traversal": (traversal or s.traversal).name, "treelet_height": s.treelet_height,
            "branching": s.branching, "stats": stats, **path.props,
            **({} if s.leaf_size is None else {"leaf_size": s.leaf_size}), **s.ours_props}


def _finite(img: np.ndarray) -> tuple[np.ndarray, int]:
    bad = ~np.isfinite(img)
    return (np.where(bad, 0.0, img).astype(np.float32), int(bad.any(-1).sum())) if bad.any() else (img, 0)


def check_memory_for(scene, spp: int, integ) -> None:
    """Refuse (UserError, one line) a render of `integ` that would not fit in memory, before it
    starts; builds the BVH (and refuses unsupported shapes) first."""
    size = scene.sensors()[0].film().crop_size()
    tracer = integ.tracer(scene)
    work = 0
    if tracer is not None:
        st = tracer.bvh.stats
        rays = min(int(size[0]) * int(size[1]) * spp, tracer.bvh.batch_rays)
        work = st.total_bytes + rays * ((st.branching - 1) * st.depth * 8 + 150)  # entry stacks + ray state
    check_memory(int(size[0]), int(size[1]), spp, "megakernel" if integ.megakernel() else "wavefront", work)


def _stage(side: str, stage: str, fn: Callable):
    """fn(), its failure a ComparisonFailed naming the side and stage (Ctrl-C passes through)."""
    try:
        return fn()
    except KeyboardInterrupt:
        raise
    except Exception as e:
        raise ComparisonFailed(side, stage, e) from e


def _cached_stock(mi, s: CompareSettings, scene, scene_path: Path, path: PathSettings, spp: int):
    """Stock's image from `s.stock_cache` (rendered and kept there when missing) and its time
    (0 when it came from the cache)."""
    size = [int(x) for x in scene.sensors()[0].film().crop_size()]
    key = {"resolution": size, "integrator": path.props, "variant": mi.variant(), "params": dict(s.params),
           "versions": {"mitsuba": mitsuba.__version__, "layerbvh": layerbvh.__version__},
           **({"stock": path.integrator(path.stock_inner())} if path.wrapper or path.estimator != "path" else {})}
    t0 = time.perf_counter()
    img, info = cached_stock(mi, scene, scene_path, key, spp, s.seed, s.stock_cache, "stock", s.progress)
    cached = bool(info.get("cached"))
    return img, SideTime(0.0 if cached else time.perf_counter() - t0, cached=cached)


def wrapped(mi, path: PathSettings, integ):
    """`integ` (a loaded integrator) in the scene's aov/moment wrapper, where it has one."""
    return integ if path.wrapper is None else load_integrator(mi, path.integrator(integ))


def compare(mi, s: CompareSettings, scene=None) -> Comparison:
    """Stock's estimator and ours (path_settings: the scene's path or direct, in its wrapper) on
    `s.scene` at the same seed (and, with
    `s.control`, our loop with Embree's queries between them), timed without kernel compilation
    and auto's calibration; then the verdict (verdict.judge: same seed, and where same-seed paths
    diverged, independent seeds), the image metrics and, with `s.statistics_pass`, a counted pass
    for traversal statistics and heat maps. A side that fails raises ComparisonFailed; a refused
    setting (a non-path scene without `as_path`) raises ab.render.UserError. `scene`: the scene
    already loaded from `s.scene` at `s.res` with `s.params`, where the caller has it."""
    scene_path = Path(s.scene)
    res = tuple(s.res) if s.res is not None else None
    if scene is None:
        scene = _stage(STOCK, "load", lambda: load_scene(mi, str(scene_path), res, **s.params))
    spp = s.spp or scene_spp(scene)
    chosen = None if s.integrator is None else _stage(STOCK, "setup", lambda: load_integrator(mi, s.integrator))
    path = path_settings(mi, scene, s.as_path, scene_path, s.params, chosen)
    if s.path_overrides:
        path.props.update(s.path_overrides)
    if s.grad is not None:  # (refused before anything renders)
        check_gradient(mi, path.estimator, scene, s.grad)
    ours_all = ours_props(s, path)
    ours_scene = scene
    if s.ours_modify is not None:
        ours_scene = _stage(OURS, "load", lambda: load_modified(mi, scene_path, res, s.params, s.ours_modify))

    def setup():
        integ = load_integrator(mi, ours_all)
        check_memory_for(ours_scene, spp, integ)  # builds the BVH (and refuses unsupported shapes) first
        return integ
    ours = _stage(OURS, "setup", setup)
    # In a scene's aov/moment wrapper, our integrator is the wrapper's inner one: its statistics,
    # BVH and calibration are read from it (`ours`), the wrapper renders (`ours_render`).
    ours_render = _stage(OURS, "setup", lambda: wrapped(mi, path, ours))

    # Timed renders without work counters: what a user's render costs.
    if s.stock_cache is not None:
        stock_img, stock_time = _stage(STOCK, "render", lambda: _cached_stock(mi, s, scene, scene_path, path, spp))
    else:
        stock_int = _stage(STOCK, "setup", lambda: load_integrator(mi, path.integrator(path.stock_inner())))
        r = _stage(STOCK, "render", lambda: timed_render(mi, scene, stock_int, spp, s.seed, "stock path", s.progress))
        stock_img, stock_time = r.image, SideTime.of(r)
    control_time = None
    if s.control and not s.traversal.control:
        ctl = _stage(OURS, "setup", lambda: wrapped(mi, path, load_integrator(
            mi, ours_props(s, path, Traversal.parse(EMBREE)))))
        control_time = SideTime.of(_stage(OURS, "render", lambda: timed_render(
            mi, ours_scene, ctl, spp, s.seed, "layerbvh loop + Embree", s.progress)))
    r = _stage(OURS, "render", lambda: timed_render(mi, ours_scene, ours_render, spp, s.seed, "layerbvh", s.progress,
                                                    calibrated=ours))
    ours_img, ours_time, stats = r.image, SideTime.of(r), ours.last_stats

    counted = counted_time = None
    heatmaps = {}
    if s.statistics_pass:  # counters cost time: a pass of their own, reported apart
        cint = _stage(OURS, "setup", lambda: load_integrator(mi, ours_props(s, path, stats=True)))
        cr = _stage(OURS, "render", lambda: timed_render(mi, ours_scene, wrapped(mi, path, cint), min(spp, STATS_SPP),
                                                         s.seed, "statistics pass", s.progress, calibrated=cint))
        counted, counted_time, heatmaps = cint.last_stats, SideTime.of(cr), cint.heatmaps(ours_scene)

    film = (stock_img.shape[1], stock_img.shape[0])  # (W, H)
    stokes = path.wrapper is not None and path.wrapper.type == "stokes"
    if stokes:  # the polarization is what a stokes render is for: its five RGB images side by side, all judged
        stock_img, ours_img = _stage(OURS, "render", lambda: (metrics.stokes_panels(stock_img),
                                                              metrics.stokes_panels(ours_img)))
    elif path.wrapper is not None:  # the wrapper's own channels (AOVs, moments) are its business: RGB is compared
        stock_img, ours_img = stock_img[..., :3], ours_img[..., :3]
    if stock_img.shape != ours_img.shape:
        raise ComparisonFailed(OURS, "render", ValueError(
            f"image shapes {list(stock_img.shape)} (stock) and {list(ours_img.shape)} (ours) differ"))
    stock_img, bad_stock = _finite(stock_img)
    ours_img, bad_ours = _finite(ours_img)
    if s.statistical_step:
        verdict = judge(mi, scene_path, stock_img, ours_img, spp, path.stock_inner(), ours_all, dict(s.params),
                        s.ours_modify, film, path.integrator if stokes else None, hypotheses.reach(scene), s.seed)
    else:
        verdict = same_seed_only(stock_img, ours_img)
    w, h = film
    gradient = None
    if s.grad is not None:
        gradient = _stage(OURS, "render", lambda: compare_gradients(
            mi, path.estimator, scene_path, scene, ours_scene, (w, h), spp, s.seed, path.stock_inner(), ours_all,
            s.grad, dict(s.params), s.ours_modify, s.statistical_step))
    ref = None
    if referee.needed(scene) and path.wrapper is None:  # (a wrapper's channels are not radiance)
        try:
            ref = _stage(STOCK, "render", lambda: referee.judge(
                mi, scene_path, res, dict(s.params), scene, load_integrator(mi, path.integrator(path.stock_inner())),
                spp, s.seed, stock_img, ours_img))
        except ComparisonFailed as e:
            if not isinstance(e.error, referee.RefereeRefused):
                raise
            ref = f"no unit-scale referee: {e.error}"
    return Comparison(settings=s, spp=spp, resolution=(w, h), variant=mi.variant(), path=path, ours_props=ours_all,
                      stock=stock_img, ours=ours_img, nonfinite=(bad_stock, bad_ours), stock_time=stock_time,
                      ours_time=ours_time, stats=stats, verdict=verdict,
                      control_time=control_time, counted=counted, counted_time=counted_time, heatmaps=heatmaps,
                      gradient=gradient, scene=scene, integrator=ours, referee=ref)
