"""The schema of report.json (what `layerbvh compare` and the pytest plugin write): every field a user's script may
read, its type and meaning, checked against real reports by the tests and rendered as the documentation's reference
page."""
from __future__ import annotations

from layerbvh_mitsuba.ab.metrics import AGREES, DIFFERS, SAME_PATHS, SAME_SEED_DIFFERS

# JSON Schema (draft 2020-12), the subset `validate` checks: type, required, properties, items,
# enum. Objects stay open (additionalProperties): a report may carry more than is listed here,
# never less, and never a listed field with another type.
NUM = {"type": "number"}
SECONDS = {"type": "number", "description": "seconds (wall clock)"}


def _obj(desc: str, props: dict, required=()) -> dict:
    return {"type": "object", "description": desc, "properties": props, "required": list(required)}


TIMES = _obj("a render's times", {"render_s": {**SECONDS, "description": "the render, compiling included"},
                                  "compile_s": {**SECONDS, "description": "of it, Dr.Jit compiling kernels"},
                                  "wall_s": SECONDS}, ("render_s", "compile_s"))

VERDICT = _obj("the verdict (plugin/ab/verdict.py; docs/verdict.md says what each label promises)", {
    "label": {"type": "string", "enum": [SAME_PATHS, AGREES, DIFFERS, SAME_SEED_DIFFERS],
              "description": f"{SAME_PATHS}, {AGREES} or {DIFFERS} (or {SAME_SEED_DIFFERS}: step 1 alone, "
                             "where no scene was at hand to render step 2 from)"},
    "passed": {"type": "boolean", "description": "same paths or agrees"},
    "summary": {"type": "string", "description": "the verdict line the command prints"},
    "mde": {"type": ["object", "null"], "description": "the minimum detectable effect: the relative bias of the "
                                                       "image mean (and of a tile's) caught with 95% probability; "
                                                       "null where no test of equal means ran"},
    "criterion": {"type": "string", "description": "the two steps' rule, in words, with its thresholds"},
    "same_seed": _obj("step 1, the same-seed criterion",
                      {"passed": {"type": "boolean"},
                       "frac_within": {**NUM, "description": "share of pixels within the tolerance"}},
                      ("passed", "frac_within")),
    "hypotheses": {"type": ["object", "null"], "description": "the family of tests of equal means (per level: "
                                                              "count, alpha each, rejections) and its summary"},
    "statistical": {"type": ["object", "null"], "description": "the independent-seed renders where step 1 failed "
                                                               "(film, spp, seconds, failing pixels); null where "
                                                               "the paired tests decided or step 1 passed"},
}, ("label", "passed", "summary", "mde", "criterion", "same_seed"))

METRICS = _obj("ours against stock, per image (the same-seed images)", {
    "rmse": {**NUM, "description": "root mean square error over pixels and channels"},
    "rel_mse": {**NUM, "description": "mean squared error relative to stock's squared values"},
    "flip_mean": {**NUM, "description": "mean ꟻLIP error (0: identical)"},
    "delta_e2000_mean": {**NUM, "description": "mean CIEDE2000 colour difference"},
    "delta_e2000_p95": {**NUM, "description": "its 95th percentile"},
    "max_abs": {**NUM, "description": "largest absolute pixel difference"},
    "frac_pixels_over_1e-3": {**NUM, "description": "share of pixels differing by more than 1e-3"},
    "pixels": {"type": "integer"},
}, ("rmse", "rel_mse", "flip_mean", "delta_e2000_mean", "delta_e2000_p95", "max_abs", "frac_pixels_over_1e-3"))

OURS = _obj("ours' render", {**TIMES["properties"],
                             "build_s": {**SECONDS, "description": "building the Layer BVH"},
                             "loop": {"type": "string", "description": "megakernel | wavefront"},
                             "trace_s": {"type": ["number", "null"]},
                             "traversal": {"type": "string", "description": "the --traversal asked for"},
                             "treelet_height": {"type": "integer"},
                             "branching": {"type": "integer", "description": "children per node: 2, 4 or 8"}},
            ("render_s", "compile_s", "build_s", "loop", "traversal", "treelet_height", "branching"))

SCHEMA = {
    "$schema": "https://json-schema.org/draft/2020-12/schema",
    "title": "report.json",
    **_obj("One comparison of ours against stock Mitsuba: what ran, how long it took, how far the images are "
           "apart and the verdict.", {
               "scene": {"type": "string", "description": "the scene file as given"},
               "spp": {"type": "integer", "description": "samples per pixel, each side"},
               "resolution": {"type": "array", "items": {"type": "integer"}, "description": "film [width, height]"},
               "seed": {"type": "integer", "description": "the seed both sides rendered with"},
               "variant": {"type": "string", "description": "the Mitsuba variant, e.g. llvm_ad_rgb"},
               "integrator": {"type": "object", "description": "the integrator's properties, as both sides got them"},
               "scene_integrator": {"type": "string", "description": "the scene's integrator type"},
               "compared_as": {"type": "string", "description": "the estimator both sides ran (a wrapper's inner one "
                                                                "where the scene wraps it)"},
               "params": {"type": "object", "description": "the scene's $parameters given on the command line"},
               "stock": {**TIMES, "description": "stock Mitsuba's render (cached: true where its image came from "
                                                 "the stock cache)"},
               "ours": OURS,
               "auto_choices": {"type": "object",
                                "description": "traversal auto: the mode chosen per kind of ray batch"},
               "features": {"type": "object", "description": "what of the scene the render used and left out"},
               "traversal": {"type": "object", "description": "the statistics pass: rays, wavefront steps, nodes, "
                                                              "leaves and triangles visited, time split, the BVH"},
               "statistics_pass": {"type": "object",
                                   "description": "its spp and times (a separate render with counters)"},
               "embree_control": {**TIMES, "description": "our loop with Mitsuba's own ray queries (Embree): the "
                                                          "control that isolates the traversal"},
               "split": {"type": "object", "description": "ours' time over stock's, split into traversal and loop"},
               "nonfinite_pixels": {"type": "object",
                                    "description": "NaN/Inf pixels per side (set to 0 for the metrics)"},
               "gradient": {"type": "object", "description": "compare --grad: the derivatives' verdict (forward and "
                                                             "backward, same seed, then paired over render pairs)"},
               "referee": {"type": "object", "description": "extreme scales: the scene rescaled to unit size on "
                                                            "stock's side, and which side matches it"},
               "metrics": METRICS,
               "verdict": VERDICT,
           }, ("scene", "spp", "resolution", "seed", "variant", "integrator", "compared_as", "stock", "ours",
               "metrics", "verdict")),
}

_TYPES = {"object": dict, "array": list, "string": str, "boolean": bool, "null": type(None)}


def _is(value, t: str) -> bool:
    if t == "integer":
        return isinstance(value, int) and not isinstance(value, bool)
    if t == "number":
        return isinstance(value, (int, float)) and not isinstance(value, bool)
    return isinstance(value, _TYPES[t])


def validate(value, schema: dict = SCHEMA, where: str = "report") -> list[str]:
    """'where: what is wrong' for every place `value` breaks `schema` (empty: it holds)."""
    types = schema.get("type")
    if types is not None:
        types = [types] if isinstance(types, str) else types
        if not any(_is(value, t) for t in types):
            return [f"{where}: {type(value).__name__}, not {' or '.join(types)}"]
    bad = []
    if "enum" in schema and value not in schema["enum"]:
        bad.append(f"{where}: {value!r} is none of {schema['enum']}")
    if isinstance(value, dict):
        bad += [f"{where}.{k}: missing" for k in schema.get("required", ()) if k not in value]
        for k, sub in schema.get("properties", {}).items():
            if k in value:
                bad += validate(value[k], sub, f"{where}.{k}")
    if isinstance(value, list) and "items" in schema:
        for i, x in enumerate(value):
            bad += validate(x, schema["items"], f"{where}[{i}]")
    return bad


def markdown() -> str:
    """The reference page: every listed field with its type, whether it is always there, and its meaning."""
    out = ["# report.json", "", SCHEMA["description"] + " Generated from `plugin/ab/report_schema.py`, which the "
           "tests check real reports against; a report may hold more fields than are listed, never fewer of the "
           "required ones.", "", "| field | type | always | meaning |", "|---|---|---|---|"]

    def rows(schema: dict, prefix: str) -> None:
        req = set(schema.get("required", ()))
        for k, sub in schema.get("properties", {}).items():
            t = sub.get("type", "")
            t = " or ".join(t) if isinstance(t, list) else t
            if "items" in sub:
                t += f" of {sub['items']['type']}"
            desc = sub.get("description", "").replace("|", "\\|")
            out.append(f"| `{prefix}{k}` | {t} | {'yes' if k in req else ''} | {desc} |")
            if "properties" in sub:
                rows(sub, f"{prefix}{k}.")
    rows(SCHEMA, "")
    return "\n".join(out) + "\n"
