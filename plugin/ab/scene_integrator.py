"""Which integrator a scene asks for, and the settings both sides of a comparison render with: the loaded scene's
integrator by Mitsuba's API where it says enough, the scene file (following <include>) where it does not."""
from __future__ import annotations

import re
import xml.etree.ElementTree as ET
from dataclasses import dataclass
from pathlib import Path

from layerbvh_mitsuba.runtime.registry import STANDS_IN_FOR, sampling
from layerbvh_mitsuba.ab.render import UserError, signed_depth


# Integrator objects by the names they give themselves, and their plugin names (for messages and
# reports). class_name() and to_string's prefix differ for some (volpath is VolumetricPathIntegrator
# and prints VolumetricSimplePathIntegrator[...]; volpathmis VolpathMisIntegratorImpl and
# VolumetricMisPathIntegrator[...]); a wrapper prints the integrators it holds by the latter.
INTEGRATOR_PLUGINS = {
    "PathIntegrator": "path",
    "VolumetricPathIntegrator": "volpath", "VolumetricSimplePathIntegrator": "volpath",
    "VolpathMisIntegratorImpl": "volpathmis", "VolumetricMisPathIntegrator": "volpathmis",
    "DirectIntegrator": "direct", "AOVIntegrator": "aov", "MomentIntegrator": "moment",
    "ParticleTracerIntegrator": "ptracer", "DepthIntegrator": "depth", "StokesIntegrator": "stokes",
    "PRBIntegrator": "prb", "BasicPRBIntegrator": "prb_basic", "PRBVolpathIntegrator": "prbvolpath",
    "PathProjectiveIntegrator": "prb_projective",
    "LayerBVHIntegrator": "layerbvh",
}
WRAPPERS = ("aov", "moment", "stokes")  # integrators that run others and add channels
ESTIMATORS = tuple(STANDS_IN_FOR)  # Mitsuba's integrators ours mirror: path, direct, volpath, ..., prb
# Those a wrapper may hold (a wrapper calls a sampling integrator's `sample`; ptracer and prb have other ones).
WRAPPED_ESTIMATORS = tuple(e for e in ESTIMATORS if sampling(e))


def _plugin(cls: str) -> str:
    return INTEGRATOR_PLUGINS.get(cls, cls.removesuffix("Integrator").lower())


def _items(text: str) -> list[str]:
    """The top-level items of the first `integrators = [...]` list in a wrapper's to_string."""
    start = text.find("integrators = [")
    if start < 0:
        return []
    items, depth, item = [], 0, ""
    for ch in text[start + len("integrators = ["):]:
        if ch == "[":
            depth += 1
        elif ch == "]":
            if depth == 0:
                break
            depth -= 1
        if ch == "," and depth == 0:
            items.append(item)
            item = ""
        else:
            item += ch
    return [i.strip() for i in items + [item] if i.strip()]


def _described(name: str, text: str) -> str:
    if name not in WRAPPERS:
        return name
    inner = [_described(_plugin(i.split("[", 1)[0].strip()), i) for i in _items(text)]
    return f"{name}({', '.join(inner)})" if inner else name


def integrator_name(integ) -> str:
    """The plugin name of a Mitsuba integrator object (`path`, `volpath`, `prb`, ...); a wrapper
    is named with what it wraps: `moment(volpath)`, `aov(direct)`, `moment(path, volpath)`.
    Why to_string: Mitsuba 3.9.1's Python API gives a loaded integrator's class name, but not the
    integrators a wrapper (aov, moment) holds nor their integer settings (mi.traverse lists
    differentiable parameters only), and the scene file may not say (an <include>, a default);
    to_string is the one place the loaded object states them. The scene file is read as well
    (scene_wrapper), for what to_string leaves out."""
    cls = integ.class_name()
    if cls not in INTEGRATOR_PLUGINS:  # Python integrators (prb, ...) report their base class
        cls = str(integ).split("[", 1)[0].strip() or cls
    return _described(_plugin(cls), str(integ))


def inner_integrator_text(integ) -> str:
    """The to_string of the first integrator a wrapper runs (of the integrator itself if it
    wraps none): where its max_depth and rr_depth are read."""
    items = _items(str(integ)) if _plugin(integ.class_name()) in WRAPPERS else []
    return items[0] if items else str(integ)


def _int_setting(text: str, key: str) -> int | None:
    m = re.search(rf"\b{key}\s*=\s*(-?\d+)", text)
    return signed_depth(int(m.group(1))) if m else None


@dataclass(frozen=True)
class Wrapper:
    """An `aov`, `moment` or `stokes` integrator around one of ESTIMATORS (possibly through another
    such wrapper), as the scene's XML states it: it adds channels (AOVs, second moments, the Stokes
    vector's four components) to the estimator's result and changes nothing else. `wrap(inner)` is
    the same wrapper around another integrator (a dict or a loaded object): stock's estimator, or
    ours standing in for it."""

    type: str                        # "aov" | "moment" | "stokes"
    props: tuple = ()                # its own properties as (name, value) pairs (aov: aovs)
    inner: "Wrapper | None" = None   # a wrapper it wraps, else it wraps the estimator itself
    leaf: str = "path"               # the estimator inside: one of ESTIMATORS

    def wrap(self, inner) -> dict:
        return {"type": self.type, **dict(self.props), "inner": inner if self.inner is None else self.inner.wrap(inner)}

    @property
    def name(self) -> str:
        return f"{self.type}({self.leaf if self.inner is None else self.inner.name})"

    @property
    def loaded_name(self) -> str:
        """What `integrator_name` makes of the loaded wrapper: `stokes` prints nothing of what it
        holds (its to_string is the class name and an address)."""
        if self.type == "stokes":
            return "stokes"
        return f"{self.type}({self.leaf if self.inner is None else self.inner.loaded_name})"


def substituted(value: str | None, defaults: dict) -> str | None:
    """A scene file's attribute with its `$name` parameters replaced by their values (`defaults`)."""
    return None if value is None else re.sub(r"\$(\w+)", lambda m: str(defaults.get(m.group(1), m.group(0))), value)


def _xml_values(el, defaults: dict) -> dict:
    """An <integrator> element's boolean and integer properties, by name, as written ("true",
    "4"): what a loaded integrator does not state (a boolean's value; ptracer's samples_per_pass)."""
    return {c.get("name"): substituted(c.get("value"), defaults) for c in el if c.tag in ("boolean", "integer")}


def _xml_wrapper(el, defaults: dict) -> tuple[Wrapper | None, dict]:
    """(the wrapper, the inner estimator's XML boolean properties) of an <integrator> element, or
    (None, {}) when it is not aov/moment/stokes around exactly one of ESTIMATORS with properties we know."""
    kind = substituted(el.get("type"), defaults)
    if kind not in WRAPPERS:
        return None, {}
    props, inner = [], []
    for child in el:
        if child.tag == "integrator":
            inner.append(child)
        elif kind == "aov" and child.tag == "string" and child.get("name") == "aovs":
            props.append(("aovs", substituted(child.get("value"), defaults)))
        elif child.tag != "default":
            return None, {}
    if len(inner) != 1:
        return None, {}
    leaf = substituted(inner[0].get("type"), defaults)
    if leaf in WRAPPED_ESTIMATORS:
        return Wrapper(kind, tuple(props), leaf=leaf), _xml_values(inner[0], defaults)
    nested, path = _xml_wrapper(inner[0], defaults)
    return (None, {}) if nested is None else (Wrapper(kind, tuple(props), nested, leaf=nested.leaf), path)


def referenced_file(name: str, including: Path, scene_dir: Path) -> Path | None:
    """Where Mitsuba finds a relative file name written in `including` (the scene file or a file
    it <include>s): next to that file, else in the scene file's folder, which Mitsuba's file
    resolver holds (Mitsuba's own test scenes include `include/preamble.xml` from a file in
    include/); None if neither holds it."""
    return next((c for c in ((including.parent / name).resolve(), (scene_dir / name).resolve()) if c.is_file()), None)


def _scene_integrator(path: Path, defaults: dict, seen: set, scene_dir: Path | None = None):
    """The first <integrator> of a scene file in document order, <include>d files read where they
    stand (as Mitsuba merges them); None if there is none or a file cannot be read."""
    path = path.resolve()
    if path in seen:
        return None
    seen.add(path)
    scene_dir = scene_dir or path.parent
    try:
        root = ET.parse(path).getroot()
    except (OSError, ET.ParseError):
        return None
    for d in root.iter("default"):
        defaults.setdefault(d.get("name"), d.get("value"))
    for el in root:
        if el.tag == "integrator":
            return el
        if el.tag == "include" and el.get("filename"):
            included = referenced_file(substituted(el.get("filename"), defaults), path, scene_dir)
            found = None if included is None else _scene_integrator(included, defaults, seen, scene_dir)
            if found is not None:
                return found
    return None


def scene_wrapper(scene_path, params: dict | None = None) -> tuple[Wrapper | None, dict]:
    """The wrapper around one of ESTIMATORS that the scene file's <integrator> states, read from
    its XML (an `aov` wrapper's channel list is in its properties, not in the loaded object;
    <include>d files are followed), and the inner estimator's boolean properties; (None, the
    estimator's boolean properties) for an estimator without a wrapper (volpathmis's
    use_spectral_mis is not in the loaded object); (None, {}) for anything else. (Integer
    properties come with the booleans: _xml_values.)"""
    defaults = {k: str(v).lower() if isinstance(v, bool) else str(v) for k, v in (params or {}).items()}
    el = _scene_integrator(Path(scene_path), defaults, set())
    if el is not None and substituted(el.get("type"), defaults) in ESTIMATORS:
        return None, _xml_values(el, defaults)
    return (None, {}) if el is None else _xml_wrapper(el, defaults)


@dataclass
class PathSettings:
    """The settings both sides of a comparison render with, and where they come from.

    `estimator`: the scene's estimator, `path`, `direct`, `volpath` or `volpathmis` (ours stands in
    for it: runtime.registry.STANDS_IN_FOR). `props`: its settings (path, volpath: max_depth,
    rr_depth, hide_emitters; volpathmis: those and use_spectral_mis; direct: emitter_samples,
    bsdf_samples, hide_emitters; only those the scene sets). `scene_integrator`: the scene's
    integrator (`integrator_name`). `wrapper`: the scene's `aov`/`moment` around its estimator, kept
    on both sides (stock's estimator inside on one, ours on the other). `as_path`: the scene's
    integrator is neither path nor such a wrapper and the user asked to compare it as path
    (`--as-path`); `note` says what was taken from it."""

    props: dict
    scene_integrator: str
    as_path: bool = False
    note: str = ""
    wrapper: Wrapper | None = None
    estimator: str = "path"

    def stock_inner(self) -> dict:
        """Stock's estimator (inside the wrapper, where there is one)."""
        return {"type": self.estimator, **self.props}

    @property
    def ours_type(self) -> str:
        """The plugin of ours that stands in for the scene's estimator."""
        return STANDS_IN_FOR[self.estimator]

    def integrator(self, inner):
        """What a side renders: `inner` (stock's estimator or ours, a dict or a loaded object), in
        the scene's wrapper where it has one."""
        return inner if self.wrapper is None else self.wrapper.wrap(inner)

    @property
    def compared_as(self) -> str:
        if self.wrapper:
            return self.wrapper.name
        return self.estimator + (" (--as-path)" if self.as_path else "")


SUPPORTED = f"{', '.join(ESTIMATORS)}, and aov, moment or stokes around the sampling ones"


def path_settings(mi, scene, as_path: bool = False, scene_path=None, params: dict | None = None,
                  integrator=None) -> PathSettings:
    """The scene's own estimator and its settings, read from its integrator object: `path`
    (max_depth, rr_depth, hide_emitters) or `direct` (emitter_samples, bsdf_samples,
    hide_emitters), and an `aov`/`moment` wrapper around either (read from `scene_path`'s XML with
    its `params`), kept as `wrapper`. Any other integrator is refused (UserError) unless
    `as_path`: then it is compared as path, its settings read where it has them (a wrapper's inner
    integrator, volpath's depths). `integrator`: a loaded integrator read instead of the scene's
    (the scene file is then not read either)."""
    integ = scene.integrator() if integrator is None else integrator
    if integ is None:
        return PathSettings({}, "path")
    name = integrator_name(integ)
    read = scene_path is not None and integrator is None
    wrapper, inner_xml = scene_wrapper(scene_path, params) if read else (None, {})
    if wrapper is not None and wrapper.loaded_name != name:
        wrapper = None  # the XML's first <integrator> is not the one loaded (an include): not read
    own = name in ESTIMATORS
    if not own and wrapper is None and not as_path:
        raise UserError(f"the scene's integrator is {name}: layerbvh renders {SUPPORTED}, so both sides would "
                        f"render something else than the scene asks; pass --as-path to compare them rendered with "
                        f"path")
    estimator = name if own else wrapper.leaf if wrapper is not None else "path"
    inner = inner_integrator_text(integ)
    keys = ("emitter_samples", "bsdf_samples") if estimator == "direct" else ("max_depth", "rr_depth")
    props = {k: v for k in keys if (v := _int_setting(inner, k)) is not None}
    for k in keys:  # (prbvolpath's to_string leaves rr_depth out)
        if k not in props and k in inner_xml:
            props[k] = signed_depth(int(inner_xml[k]))
    if (own or name == "volpath") and hasattr(integ, "hide_emitters"):
        props["hide_emitters"] = bool(integ.hide_emitters)
    elif "hide_emitters" in inner_xml:  # (an adjoint integrator, or inside a wrapper: only the XML has it)
        props["hide_emitters"] = inner_xml["hide_emitters"].lower() == "true"
    if estimator == "ptracer" and "samples_per_pass" in inner_xml:  # (its passes draw their own samples)
        props["samples_per_pass"] = int(inner_xml["samples_per_pass"])
        if props["samples_per_pass"] < 1:  # (stock's render divides by it: SIGFPE, issue 56)
            raise UserError(f"the scene's ptracer has samples_per_pass {props['samples_per_pass']}; it must be >= 1 "
                            f"(or left out: all samples in one pass)")
    if estimator == "volpathmis" and "use_spectral_mis" in inner_xml:  # (only the XML has it)
        props["use_spectral_mis"] = inner_xml["use_spectral_mis"].lower() == "true"
    note = ""
    if not own and wrapper is None:
        shown = ", ".join(f"{k}={v}" for k, v in props.items()) or "path's defaults"
        note = f"the scene's integrator is {name}; both sides rendered with path ({shown})"
    return PathSettings(props, name if wrapper is None else wrapper.name, as_path=not own and wrapper is None,
                        note=note, wrapper=wrapper, estimator=estimator)


def path_props(mi, scene) -> dict:
    """The scene's path settings, comparing any integrator as path (tools that say so themselves)."""
    return path_settings(mi, scene, as_path=True).props
