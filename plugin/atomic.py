"""Output files that appear whole or not at all: write to a temporary sibling, then rename."""
from __future__ import annotations

import contextlib
import fcntl
import os
import shutil
import tempfile
from pathlib import Path


def _readable(path) -> None:
    # mkstemp makes 0600; an output should be as readable as any file the user creates.
    if Path(path).is_file():
        os.chmod(path, 0o666 & ~_umask())


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


def section_markers(section: str) -> tuple[str, str]:
    """The comments a generated section of a markdown file sits between."""
    return f"<!-- {section}:start -->", f"<!-- {section}:end -->"


def marked_lines(section: str, body: str) -> list[str]:
    """`body` between `section`'s markers, as lines of a document (a blank one after), so the
    section can later be regenerated alone with splice_section."""
    start, end = section_markers(section)
    return [start, body, end, ""]


def read_section(path, section: str) -> str | None:
    """The text between `section`'s markers in `path`, stripped (None: no file or no markers)."""
    path = Path(path)
    start, end = section_markers(section)
    text = path.read_text() if path.exists() else ""
    if start not in text or end not in text:
        return None
    return text[text.index(start) + len(start):text.index(end)].strip()


def splice_section(path, section: str, body: str) -> None:
    """Replace the text between `section`'s markers (section_markers) in `path`."""
    path = Path(path)
    start, end = section_markers(section)
    old = path.read_text()
    if start not in old or end not in old:
        raise ValueError(f"{path}: markers {start} / {end} not found")
    new = old[:old.index(start) + len(start)] + "\n" + body.strip() + "\n" + old[old.index(end):]
    write_text(path, new)


# -- output folders ---------------------------------------------------------------------------------


@contextlib.contextmanager
def atomic_folder(out, marker: str):
    """Yield a temporary sibling folder to write a whole output folder into; on success it
    replaces `out` in one step, so `out` always holds the files of one run.

    `marker` names the file that identifies such a folder (e.g. report.json): an existing `out`
    without it is somebody else's and is never replaced (check_output_folder refuses it before
    any work). Two runs publishing into the same `out` take turns (an exclusive lock on the
    parent folder), each replacing the folder whole."""
    out = Path(out).absolute()
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(dir=out.parent, prefix=f".{out.name}.tmp-"))
    try:
        yield tmp
        _readable(tmp)
        os.chmod(tmp, 0o777 & ~_umask())  # mkdtemp makes it 0700
        fd = os.open(out.parent, os.O_RDONLY)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX)
            if out.exists() and not (out / marker).exists() and any(out.iterdir()):
                raise FileExistsError(f"{out} holds files that are not a layerbvh output (no {marker}); "
                                      f"nothing was replaced")
            old = None
            if out.exists():
                old = Path(tempfile.mkdtemp(dir=out.parent, prefix=f".{out.name}.old-"))
                os.rename(out, old / out.name)
            os.rename(tmp, out)
            if old is not None:
                shutil.rmtree(old, ignore_errors=True)
        finally:
            os.close(fd)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise


def check_output_folder(out, marker: str | tuple[str, ...]) -> str | None:
    """Why `out` cannot take an output folder (one line), or None: it is a file, a folder of
    somebody else's files (none of the `marker` files a layerbvh output holds), or its parent
    cannot be created or written."""
    out = Path(out)
    markers = (marker,) if isinstance(marker, str) else marker
    if out.exists() and not out.is_dir():
        return f"{out} exists and is not a folder"
    if out.is_dir() and any(out.iterdir()) and not any((out / m).exists() for m in markers):
        return f"{out} exists and holds files that are not a layerbvh output (no {markers[0]}): choose another folder"
    return _check_writable(out.absolute().parent)


def check_output_file(out) -> str | None:
    """Why the file `out` cannot be written (one line), or None."""
    out = Path(out)
    if out.is_dir():
        return f"{out} is a folder"
    return _check_writable(out.absolute().parent)


def _check_writable(folder: Path) -> str | None:
    try:
        folder.mkdir(parents=True, exist_ok=True)
        fd, probe = tempfile.mkstemp(dir=folder, prefix=".layerbvh-write-test-")
        os.close(fd)
        os.unlink(probe)
    except OSError as e:
        return f"cannot write into {folder}: {e.strerror or e}"
    return None


def _umask() -> int:
    umask = os.umask(0)
    os.umask(umask)
    return umask
