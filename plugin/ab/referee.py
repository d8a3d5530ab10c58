"""The extreme-scale referee (issue 56 item 2): a scene far from unit size rendered by stock once more, rescaled to
unit size by a power of two, and which side's image matches it."""
from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np

from layerbvh_mitsuba.ab import metrics
from layerbvh_mitsuba.ab.render import load_scene
from layerbvh_mitsuba.runtime import extreme_scale

# A scene whose bounding box is larger than this, or smaller than its inverse (or than
# extreme_scale.TINY_EXTENT), gets the referee:
# float32 keeps 7 digits, and Mitsuba's epsilons (RayEpsilon ~9e-5, absolute below 1) and squared
# norms (overflowing past ~1.8e19) are tuned for scenes near unit size.
FAR_FROM_UNIT = 1e6
# Which side matches the referee: its image mean within this of the referee's (the 1%).
TOLERANCE = 0.01


class RefereeRefused(Exception):
    """What the referee cannot rescale without changing the image (named in its one line)."""


@dataclass
class Referee:
    """Stock's render of the scene rescaled by `factor` (a power of two) against both sides'."""

    extent: float          # the scene's bounding-box diagonal
    factor: float          # what every length was multiplied by
    stock_rel: float       # stock's image mean / the referee's - 1
    ours_rel: float
    stock_within: float    # share of pixels within the same-seed tolerance of the referee
    ours_within: float
    matches: str           # "both", "ours", "stock" or "neither" (which_matches)

    def as_dict(self) -> dict:
        return asdict(self)

    def line(self) -> str:
        side = {"both": "both sides match it", "neither": "neither side matches it"}.get(
            self.matches, f"{self.matches} matches it")
        return (f"unit-scale referee (the scene x {self.factor:g}, rendered by stock): {side} "
                f"(stock {self.stock_rel:+.2%}, ours {self.ours_rel:+.2%} in the image mean; "
                f"{self.stock_within:.1%} / {self.ours_within:.1%} of pixels within the same-seed tolerance)")


def which_matches(stock_rel: float, ours_rel: float, stock_finite: bool = True, ours_finite: bool = True,
                  tolerance: float = TOLERANCE) -> str:
    """Which side's image mean is within `tolerance` of the referee's: "both", "ours", "stock", "neither"."""
    ok_ours = ours_finite and abs(ours_rel) <= tolerance
    ok_stock = stock_finite and abs(stock_rel) <= tolerance
    return "both" if ok_ours and ok_stock else "ours" if ok_ours else "stock" if ok_stock else "neither"


def extent(scene) -> float:
    """The diagonal of `scene`'s bounding box (0 for an empty or infinite one)."""
    box = extreme_scale.scene_box(scene)
    return 0.0 if box is None else box[1]


def needed(scene) -> bool:
    """Whether `scene` is far from unit size: beyond FAR_FROM_UNIT, or so small that our renders take
    the unit-size scene's ray offsets, not stock's (runtime/extreme_scale.TINY_EXTENT)."""
    e = extent(scene)
    return e > 0 and (e > FAR_FROM_UNIT or e < max(1 / FAR_FROM_UNIT, extreme_scale.TINY_EXTENT))


def unit_factor(e: float) -> float:
    """The power of two that brings extent `e` nearest to 1 (exact: every coordinate keeps its bits)."""
    return 1.0 / extreme_scale.unit_of(e)


def _scaled(mi, t, k: float):
    """Transform `t` followed by a uniform scale by `k` (every length of what it places x k)."""
    return type(t)(mi.ScalarTransform4f().scale(k)) @ t


def _moved(mi, t, k: float):
    """Transform `t` with its translation x `k` (a camera's or a light's: its own axes kept)."""
    m = np.array(t.matrix, np.float64).reshape(4, 4, -1)[..., 0]
    m[:3, 3] *= k
    return type(t)(mi.ScalarTransform4f(m))


def rescaled(mi, scene_path: str, res, params: dict, k: float):
    """A fresh copy of the scene with every length x `k`: mesh vertices, the placements of
    shapes and instances, the camera's position and clip planes, point and spot lights (their
    intensity x k^2, so the irradiance they give is kept). Raises RefereeRefused naming what
    cannot be rescaled with its image kept (media: their densities are per unit length)."""
    scene = load_scene(mi, scene_path, res, **params)
    p = mi.traverse(scene)
    own = {s.ptr for s in scene.shapes()}
    by_node: dict = {}
    for key in p.keys():
        by_node.setdefault(p.properties[key][2].ptr, []).append(key)
    for keys in by_node.values():
        node = p.properties[keys[0]][2]
        kind, name = type(node).__name__, node.class_name()
        prefix = {key.rsplit(".", 1)[0] for key in keys}
        field = {key.rsplit(".", 1)[-1]: key for key in keys if key.rsplit(".", 1)[0] in prefix}
        if "Medium" in kind or "Volume" in kind:
            raise RefereeRefused(f"{keys[0]}: {name} is a medium, whose densities are per unit length")
        if kind in ("ProjectiveCamera", "Sensor"):
            if name != "PerspectiveCamera":
                raise RefereeRefused(f"the sensor is {name}: only a perspective camera is rescaled")
            for clip in ("near_clip", "far_clip"):
                p[field[clip]] = p[field[clip]] * k
            p[field["to_world"]] = _moved(mi, p[field["to_world"]], k)
        elif name in ("PointLight", "SpotLight"):
            if "position" in field:
                p[field["position"]] = p[field["position"]] * k
            if "to_world" in field:
                p[field["to_world"]] = _moved(mi, p[field["to_world"]], k)
            p[field["value"]] = p[field["value"]] * (k * k)  # intensity.value
        elif "vertex_positions" in field:
            if node.ptr in own:  # (a shapegroup's mesh: its instances are scaled instead)
                p[field["vertex_positions"]] = p[field["vertex_positions"]] * k
        elif "to_world" in field and (kind in ("Mesh", "Shape") or name == "Instance") and \
                (node.ptr in own or name == "Instance"):
            p[field["to_world"]] = _scaled(mi, p[field["to_world"]], k)
    p.update()
    return scene


def judge(mi, scene_path, res, params: dict, scene, integrator, spp: int, seed: int,
          stock_img: np.ndarray, ours_img: np.ndarray) -> Referee:
    """Render the referee with `integrator` (stock's) at the comparison's spp and seed, and judge
    both sides' images against it."""
    e = extent(scene)
    k = unit_factor(e)
    unit_scene = rescaled(mi, str(scene_path), res, params, k)
    img = np.array(mi.render(unit_scene, integrator=integrator, spp=spp, seed=seed), np.float64)
    img = img[..., :stock_img.shape[-1]]
    ref_mean = float(np.nanmean(img))
    rel = {}
    within = {}
    for side, x in (("stock", stock_img), ("ours", ours_img)):
        rel[side] = float(np.mean(x)) / ref_mean - 1.0 if ref_mean else float("inf")
        within[side] = metrics.same_seed_verdict(img.astype(np.float32), x)["values"]["frac_within"]
    return Referee(extent=e, factor=k, stock_rel=rel["stock"], ours_rel=rel["ours"], stock_within=within["stock"],
                   ours_within=within["ours"], matches=which_matches(rel["stock"], rel["ours"]))
