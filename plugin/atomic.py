"""Output files that appear whole or not at all: write to a temporary sibling, then rename."""
from __future__ import annotations

import contextlib
import os
import tempfile
from pathlib import Path


def _readable(path: str) -> None:
    # mkstemp makes 0600; an output should be as readable as any file the user creates.
    umask = os.umask(0)
    os.umask(umask)
    os.chmod(path, 0o666 & ~umask)


@contextlib.contextmanager
def atomic_path(out):
    """Yield a temporary path next to `out`; on success it replaces `out`, on error it is removed."""
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=out.parent, prefix=f".{out.name}.", suffix=".tmp" + out.suffix)
    os.close(fd)
    try:
        yield tmp
        _readable(tmp)
        os.replace(tmp, out)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def write_text(out, text: str) -> None:
    with atomic_path(out) as tmp:
        Path(tmp).write_text(text)


def write_bytes(out, data: bytes) -> None:
    with atomic_path(out) as tmp:
        Path(tmp).write_bytes(data)


def splice_section(path, section: str, body: str) -> None:
    """Replace the text between `<!-- section:start -->` and `<!-- section:end -->` in `path`."""
    path = Path(path)
    start, end = f"<!-- {section}:start -->", f"<!-- {section}:end -->"
    old = path.read_text()
    if start not in old or end not in old:
        raise ValueError(f"{path}: markers {start} / {end} not found")
    new = old[:old.index(start) + len(start)] + "\n" + body.strip() + "\n" + old[old.index(end):]
    write_text(path, new)
