"""Files and folders written safely: checked before any work, written atomically.

:func:`publish_folder` writes a folder's files into a temporary folder beside it, which then
replaces it whole, so a run that fails or is killed mid-write never leaves a folder that mixes
two runs' files; :func:`write_file_atomic` does the same for one file. :func:`check_output_folder`,
:func:`check_output_file` and :func:`check_free_space` tell before any work whether a path can be
written.
"""

from __future__ import annotations

import os
import shutil
import tempfile
import uuid
from pathlib import Path

__all__ = ["OutputError", "check_free_space", "check_output_file", "check_output_folder", "publish_folder",
           "write_file_atomic"]


class OutputError(ValueError):
    """An output path cannot be written; the message names it and says why."""


def _nearest_existing(path: Path) -> Path:
    while not path.exists() and path != path.parent:
        path = path.parent
    return path


def _probe_writable(folder: Path) -> str | None:
    """None if a file can be created (and removed) in ``folder``, else why not."""
    try:
        fd, name = tempfile.mkstemp(prefix=".jaxslam-probe-", dir=folder)
        os.close(fd)
        os.unlink(name)
    except OSError as err:
        return err.strerror or str(err)
    return None


def check_output_folder(out_dir) -> None:
    """Raise :class:`OutputError` unless ``out_dir`` can take a run's outputs; call it before any work.

    It must be an existing writable folder or a path that can be made one (its nearest existing
    ancestor is a writable folder), and, for the atomic swap of :func:`publish_folder`, the
    folder beside which it is written must be writable too (else, for an existing folder such as
    a mount point, the files are replaced one by one in place). Nothing is left behind.
    """
    target = Path(os.path.abspath(os.fspath(out_dir)))
    if target.exists() and not target.is_dir():
        raise OutputError(f"{out_dir} is an existing file, not a folder; give a new or existing folder")
    if target.is_dir():
        why = _probe_writable(target) if os.access(target, os.W_OK | os.X_OK) else "no write permission"
        if why:
            raise OutputError(f"{out_dir} is a folder that cannot be written ({why}); give a writable folder")
        return
    _check_creatable(out_dir, target)


def check_free_space(out_dir, need_bytes: int) -> None:
    """Raise :class:`OutputError` when the disk that will hold ``out_dir`` has less than
    ``need_bytes`` free; call it before any work."""
    target = Path(os.path.abspath(os.fspath(out_dir)))
    free = shutil.disk_usage(_nearest_existing(target)).free
    if free < need_bytes:
        raise OutputError(f"{out_dir} is on a disk with {free / 1e6:.0f} MB free, but the run's outputs and checkpoint "
                          f"need about {need_bytes / 1e6:.0f} MB; free some space or choose another folder")


def check_output_file(path) -> None:
    """Raise :class:`OutputError` unless a file can be written at ``path`` (not a folder; its
    folder exists and is writable or can be made); call it before any work."""
    target = Path(os.path.abspath(os.fspath(path)))
    if target.is_dir():
        raise OutputError(f"{path} is an existing folder; give a file path (e.g. {Path(path) / 'errors.json'})")
    if target.exists() and not os.access(target, os.W_OK):
        raise OutputError(f"{path} exists and is not writable")
    _check_creatable(path, target)


def _check_creatable(name, target: Path) -> None:
    """``OutputError`` (naming ``name``) unless ``target``'s nearest existing ancestor is a writable folder."""
    ancestor = _nearest_existing(target.parent)
    if not ancestor.is_dir():
        raise OutputError(f"{name} cannot be created: {ancestor} is a file, not a folder")
    why = _probe_writable(ancestor) if os.access(ancestor, os.W_OK | os.X_OK) else "no write permission"
    if why:
        raise OutputError(f"{name} cannot be created: {ancestor} is not writable ({why})")


def write_file_atomic(path, content) -> None:
    """Write ``content`` to ``path`` through a temporary file beside it, flushed to disk, and one
    rename: readers see the old file or the new one, never a part. ``content`` is text, or a
    callable that writes into the binary file object it is given (e.g. ``np.savez``)."""
    target = Path(path)
    target.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{target.name}.tmp-{os.getpid()}-", dir=target.parent)
    try:
        with os.fdopen(fd, "wb") as f:
            if callable(content):
                content(f)
            else:
                f.write(content.encode("utf-8"))
            f.flush()
            os.fsync(f.fileno())
        os.chmod(tmp, 0o666 & ~_umask())
        os.replace(tmp, target)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


def _link_or_copy(src, dst) -> None:
    """Hard-link ``src`` (a symlink itself, not followed) to ``dst``; copy where links fail."""
    try:
        os.link(src, dst, follow_symlinks=False)
    except OSError:
        if os.path.islink(src):
            os.symlink(os.readlink(src), dst)
        else:
            shutil.copy2(src, dst)


def publish_folder(out_dir, write, replaces: tuple[str, ...]) -> None:
    """Run ``write(folder)`` on a temporary folder, then make it ``out_dir``, whole.

    The temporary folder is ``.{name}.tmp-<pid>-...`` beside ``out_dir`` (the same parent, so
    the renames stay on one file system). Once ``write`` has returned, the entries of an
    existing ``out_dir`` that are not in ``replaces`` (files this kind of run never writes) are
    hard-linked into it, and the swap is: rename ``out_dir`` to a backup name, rename the
    temporary folder to ``out_dir``, delete the backup. So entries named in ``replaces`` that
    this run did not write are removed; if ``write`` fails, or the process dies before the swap,
    ``out_dir`` is untouched (a process killed between the two renames leaves the old folder
    intact under ``.{name}.old-<pid>-...``), and the temporary folder is removed on errors.

    Where the folder cannot be swapped (its parent is not writable, or it is a mount point) the
    files are written into a temporary folder inside it and moved over one by one (each file is
    replaced atomically, the set is not), then the stale ``replaces`` entries are removed.
    """
    target = Path(os.path.realpath(os.fspath(out_dir)))
    if target.exists() and not target.is_dir():
        raise OutputError(f"{out_dir} is an existing file, not a folder")
    parent = target.parent
    parent.mkdir(parents=True, exist_ok=True)
    exists = target.is_dir()
    if exists and (os.path.ismount(target) or not os.access(parent, os.W_OK | os.X_OK)):
        _publish_in_place(target, write, replaces)
        return
    stage = Path(tempfile.mkdtemp(prefix=f".{target.name}.tmp-{os.getpid()}-", dir=parent))
    try:
        write(stage)
        written = {p.name for p in stage.iterdir()}
        if exists:
            for entry in target.iterdir():
                if entry.name in replaces or entry.name in written:
                    continue
                if entry.is_dir() and not entry.is_symlink():
                    shutil.copytree(entry, stage / entry.name, symlinks=True, copy_function=_link_or_copy)
                else:
                    _link_or_copy(entry, stage / entry.name)
            shutil.copymode(target, stage)
        else:
            os.chmod(stage, 0o777 & ~_umask())
        if not exists:
            os.rename(stage, target)
            return
        backup = parent / f".{target.name}.old-{os.getpid()}-{uuid.uuid4().hex[:8]}"
        os.rename(target, backup)
        try:
            os.rename(stage, target)
        except BaseException:
            os.rename(backup, target)
            raise
        shutil.rmtree(backup, ignore_errors=True)
    except BaseException:
        shutil.rmtree(stage, ignore_errors=True)
        raise


def _publish_in_place(target: Path, write, replaces) -> None:
    stage = Path(tempfile.mkdtemp(prefix=f".jaxslam-tmp-{os.getpid()}-", dir=target))
    try:
        write(stage)
        written = sorted(p.name for p in stage.iterdir())
        for name in written:
            os.replace(stage / name, target / name)
        for name in replaces:
            if name not in written and (target / name).is_file():
                (target / name).unlink()
    finally:
        shutil.rmtree(stage, ignore_errors=True)
