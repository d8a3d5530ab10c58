"""Where the repository's own files are (scenes, meshes, README, generated reports), for the development tools."""
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
SCENES = ROOT / "scenes"
