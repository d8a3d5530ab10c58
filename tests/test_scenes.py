"""Every XML scene in scenes/ declares the common parameters and renders with stock Mitsuba and with layerbvh alike."""
from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pytest

from layerbvh_mitsuba import testing

SCENES = sorted((Path(__file__).resolve().parents[1] / "scenes").glob("*.xml"))


def test_scene_folder_is_not_empty():
    assert len(SCENES) >= 8


@pytest.mark.parametrize("path", SCENES, ids=[p.stem for p in SCENES])
def test_scene_declares_parameters_and_matches_stock(path):
    text = path.read_text()
    for name in ("resx", "resy", "spp", "max_depth"):
        assert re.search(rf'<default\s+name="{name}"', text), f"{path.name} does not declare ${name}"
    # The default traversal, as a user renders the scene (the layer modes on these scenes:
    # tests/test_mitsuba_backend.py, tests/test_instancing.py).
    r = testing.same_seed(path, spp=4, res=(16, 16), traversal="auto")
    assert np.isfinite(r.ours).all() and np.isfinite(r.stock).all()
    assert r.mean_ref > 1e-3, f"{path.name} renders black"
    # Specular paths through many shared edges (glass meshes) may diverge on a few pixels.
    assert r.frac_within >= 0.95, f"{path.name}: {r.summary()}"
    assert abs(r.ours.mean() - r.stock.mean()) <= 0.02 * r.stock.mean(), f"{path.name}: {r.summary()}"
