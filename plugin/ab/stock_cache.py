"""Stock images kept by scene content and settings: a SHA-256 over the scene's XML, every file it references and the
render settings names each one (converge's references, the pytest plugin's stock side, recorded rays)."""
from __future__ import annotations

import hashlib
import json
import sys
import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np

from layerbvh_mitsuba import atomic
from layerbvh_mitsuba.ab.render import load_integrator, read_exr, render_passes, write_exr
from layerbvh_mitsuba.ab.scene_integrator import referenced_file, substituted


class SceneFilesError(ValueError):
    """A scene's files cannot be read for its key (bad XML, a referenced file missing), or its
    stock render cannot be cached."""


def scene_files(scene: Path, _seen=None, _base: Path | None = None, _defaults: dict | None = None) -> list[Path]:
    """The XML file and every file it references (meshes, textures, included XML, recursively),
    found where Mitsuba finds them (`render.referenced_file`), with $parameters keeping the values
    the including file gave them."""
    seen = _seen if _seen is not None else set()
    scene = scene.resolve()
    if scene in seen:
        return []
    seen.add(scene)
    base = _base or scene.parent
    try:
        root = ET.parse(scene).getroot()
    except ET.ParseError as e:
        raise SceneFilesError(f"scene {scene}: not valid XML ({e})") from None
    defaults = {**{d.get("name"): d.get("value") for d in root.iter("default")}, **(_defaults or {})}
    files = [scene]
    for el in root.iter():
        ref = el.get("filename") if el.tag == "include" else (
            el.get("value") if el.get("name") == "filename" else None)
        if ref is None:
            continue
        name = substituted(ref, defaults)
        path = referenced_file(name, scene, base)
        if path is None:
            raise SceneFilesError(f"scene {scene.name}: referenced file not found: {ref}")
        files += scene_files(path, seen, base, defaults) if path.suffix == ".xml" else [path]
    return files


def reference_key(scene: Path, settings: dict) -> str:
    """SHA-256 over the bytes of the scene and all its files plus the render settings: any edit
    to a mesh, a texture or the XML gives a new key, so a stale reference is never reused."""
    h = hashlib.sha256()
    for path in scene_files(scene):
        h.update(path.name.encode() + b"\0")
        h.update(hashlib.sha256(path.read_bytes()).digest())
    h.update(json.dumps(settings, sort_keys=True).encode())
    return h.hexdigest()


def cached_stock(mi, scene, scene_path: Path, settings: dict, spp: int, seed: int, cache: Path, label: str,
                 progress: bool) -> tuple[np.ndarray, dict]:
    """A stock render (settings["stock"], an integrator dict, else `path` with
    settings["integrator"]; `spp`, `seed`): read from the cache when
    its key (`reference_key`: every file of the scene, `settings`, spp and seed) and the EXR's
    SHA-256 match, else rendered and stored (a damaged or replaced cache file is rendered again,
    with a notice)."""
    key = reference_key(scene_path, {**settings, "spp": spp, "seed": seed})
    exr, meta = cache / f"{key[:24]}.exr", cache / f"{key[:24]}.json"
    if exr.is_file() and meta.is_file():
        try:
            info = json.loads(meta.read_text())
            data = exr.read_bytes()
            if info.get("key") == key and hashlib.sha256(data).hexdigest() == info.get("exr_sha256"):
                img = read_exr(exr)[:, :, :3]
                if list(img.shape[:2]) == list(settings["resolution"][::-1]):
                    return img, {**info, "path": str(exr), "cached": True}
            problem = "does not match its checksum" if info.get("key") == key else "belongs to other settings"
        except (OSError, ValueError, RuntimeError) as e:
            problem = f"cannot be read ({str(e).strip().splitlines()[-1] if str(e).strip() else type(e).__name__})"
        print(f"layerbvh: cached reference {exr} {problem}; rendering it again", file=sys.stderr)
    stock = load_integrator(mi, settings.get("stock") or {"type": "path", **settings["integrator"]})
    img, secs = render_passes(mi, scene, stock, spp, seed, label, progress)
    if not np.isfinite(img).all():
        raise SceneFilesError("the stock render has NaN/Inf pixels; nothing cached")
    write_exr(exr, img)
    info = {"key": key, "settings": settings, "spp": spp, "seed": seed, "render_s": secs, "scene": str(scene_path),
            "exr_sha256": hashlib.sha256(exr.read_bytes()).hexdigest()}
    atomic.write_text(meta, json.dumps(info, indent=1))  # written last: its presence means the EXR is whole
    return img, {**info, "path": str(exr), "cached": False}
