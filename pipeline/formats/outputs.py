"""The output policy of every command (docs/reliability.md): calib never loses a file the user wrote.

1. An output folder never equals, contains or lies inside an input (symlinks resolved): :func:`check_separate`.
2. calib replaces only folders it owns. Every folder it writes holds a marker file ``.calib-output``
   listing the files it wrote with their sha256; a folder may be replaced when it is absent, empty, or
   owned with every file still as calib wrote it. A file calib did not write, or one edited since, is the
   user's: the command stops with ``<file>: ...`` and touches nothing (:func:`check_replaceable`).
3. One writer per output folder: an exclusive ``fcntl.flock`` on a lock file beside it
   (``.<name>.lock``); a second command waits for it (:func:`output_lock`).
4. Temporary folders of killed runs (``.<name>.tmp-*``, ``.<name>.old-*``) are removed by the next
   command that holds the lock (:func:`remove_litter`).
5. A command writes all its folders into temporary siblings and renames them into place only when all
   of them are complete (:func:`publish`): it writes everything or nothing.
"""
from __future__ import annotations

import contextlib
import errno
import fcntl
import hashlib
import json
import os
import shutil
import tempfile
from pathlib import Path

from calib.errors import InputError

MARKER = ".calib-output"
LOCK_SUFFIX = ".lock"
# calib's own bookkeeping inside an owned folder (never listed in the marker, never a user file)
BOOKKEEPING = (MARKER, ".calib-stage.json")
TMP_TAGS = (".tmp-", ".old-")


# ----------------------------------------------------------------------------------------------- checks
def _resolve(p):
    return Path(os.path.realpath(Path(p).expanduser()))


def check_separate(outputs, inputs):
    """Raise InputError if an output equals, contains or lies inside an input (after resolving symlinks)."""
    for out in outputs:
        o = _resolve(out)
        for inp in inputs:
            if inp is None:
                continue
            i = _resolve(inp)
            if o == i:
                raise InputError(f"{out}: the output folder is the input {inp}; choose another output folder")
            if i in o.parents:
                raise InputError(f"{out}: the output folder lies inside the input {inp}; choose a folder outside it")
            if o in i.parents:
                raise InputError(f"{out}: the output folder contains the input {inp}; "
                                 "replacing it would delete the input")


def _sha256(path):
    h = hashlib.sha256()
    with open(path, "rb") as f:
        while block := f.read(1 << 20):
            h.update(block)
    return h.hexdigest()


def _is_bookkeeping(rel):
    name = Path(rel).name
    return name in BOOKKEEPING or (name.startswith(".") and any(t in name for t in TMP_TAGS))


def _files(folder):
    """Relative posix paths of every file (and empty sub-folder) under ``folder``."""
    out = []
    for root, dirs, files in os.walk(folder):
        rel_root = Path(root).relative_to(folder)
        out += [(rel_root / f).as_posix() for f in files]
        out += [(rel_root / d).as_posix() + "/" for d in dirs if not os.listdir(Path(root) / d)]
    return out


def read_marker(folder):
    """{relative file: sha256} of an owned folder, or None when ``folder`` has no valid marker."""
    try:
        data = json.loads((Path(folder) / MARKER).read_text())
        files = data["files"]
        return {str(k): str(v) for k, v in files.items()} if isinstance(files, dict) else None
    except (OSError, ValueError, KeyError, TypeError):
        return None


def write_marker(folder, command):
    """Write ``.calib-output`` into ``folder`` listing every file there with its sha256."""
    files = {rel: _sha256(Path(folder) / rel) for rel in sorted(_files(folder))
             if not rel.endswith("/") and not _is_bookkeeping(rel)}
    (Path(folder) / MARKER).write_text(json.dumps({"written_by": "calib", "command": command, "files": files},
                                                  indent=1) + "\n")


def check_replaceable(folder, edits=True):
    """Raise InputError unless calib may replace ``folder`` (absent, empty, or owned and unedited).

    edits : also refuse files edited since calib wrote them (False: only files calib did not write).
    """
    folder = Path(folder)
    if not folder.exists() and not folder.is_symlink():
        return
    if folder.is_symlink() or not folder.is_dir():
        raise InputError(f"{folder}: exists and is not a folder calib wrote; choose another output or move it")
    entries = [rel for rel in _files(folder) if not _is_bookkeeping(rel)]
    marker = read_marker(folder)
    if marker is None:
        if entries:
            raise InputError(f"{folder / entries[0].rstrip('/')}: the output folder holds files calib did not "
                             f"write (no {MARKER}); choose another output or move them away")
        return
    for rel in sorted(entries):
        p = folder / rel.rstrip("/")
        if rel not in marker:
            raise InputError(f"{p}: not written by calib; move it out of {folder} (calib never deletes your files)")
        if edits and _sha256(p) != marker[rel]:
            raise InputError(f"{p}: edited since calib wrote it; move it away or rename it to keep your edit")


# ----------------------------------------------------------------------------------------------- lock
@contextlib.contextmanager
def output_lock(folder, on_wait=None):
    """Hold an exclusive lock for writing ``folder`` (``.<name>.lock`` beside it); waits for another holder.

    The lock file is removed on release (so a finished command leaves nothing); a waiter that wakes up on
    a removed lock file notices (different inode) and locks the new one.
    on_wait : optional ``on_wait(message)`` called once if another process holds the lock.
    """
    folder = Path(folder)
    parent = folder.resolve().parent
    path = parent / f".{folder.name}{LOCK_SUFFIX}"
    created = _make_parents(parent, folder)
    try:
        with _locked(path, folder, on_wait):
            yield
    finally:
        for d in reversed(created):  # folders made only for this output and left empty (a failed command)
            try:
                d.rmdir()
            except OSError:
                break


def _make_parents(parent, folder):
    """mkdir -p ``parent``; returns the folders it created (outermost first)."""
    missing = []
    p = parent
    while not p.exists() and p != p.parent:
        missing.append(p)
        p = p.parent
    try:
        parent.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise os_error(exc, folder) from None
    return missing[::-1]


@contextlib.contextmanager
def _locked(path, folder, on_wait):
    """flock the file ``path`` (created), retrying if its holder removed it meanwhile; removed on release."""
    told = False
    while True:
        try:
            fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o666)
        except FileNotFoundError:  # another command removed its empty parent folder meanwhile: make it again
            _make_parents(path.parent, folder)
            continue
        except OSError as exc:
            raise InputError(f"{exc.filename or folder}: cannot create the output ({exc.strerror})") from None
        try:
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except BlockingIOError:
                holder = os.pread(fd, 32, 0).decode(errors="replace").strip() or "?"
                if on_wait is not None and not told:
                    on_wait(f"{folder}: another calib (pid {holder}) is writing here; waiting for it to finish")
                    told = True
                fcntl.flock(fd, fcntl.LOCK_EX)
            if _same_file(fd, path):
                break
        except BaseException:
            os.close(fd)
            raise
        os.close(fd)  # the holder removed that lock file while we waited: lock the current one
    try:
        os.ftruncate(fd, 0)
        os.pwrite(fd, f"{os.getpid()}\n".encode(), 0)
        yield
    finally:
        with contextlib.suppress(OSError):
            os.unlink(path)  # while still holding the lock (see the docstring)
        os.close(fd)


def _same_file(fd, path):
    try:
        a, b = os.fstat(fd), os.stat(path)
    except FileNotFoundError:
        return False
    return (a.st_dev, a.st_ino) == (b.st_dev, b.st_ino)


def remove_litter(folder):
    """Remove ``.<name>.tmp-*`` / ``.<name>.old-*`` beside ``folder`` left by killed runs (hold the lock)."""
    folder = Path(folder)
    parent = folder.parent
    if not parent.is_dir():
        return
    for tag in TMP_TAGS:
        for p in parent.glob(f".{folder.name}{tag}*"):
            if p.is_dir() and not p.is_symlink():
                shutil.rmtree(p, ignore_errors=True)
            else:
                with contextlib.suppress(OSError):
                    p.unlink()


# ----------------------------------------------------------------------------------------------- publish
def _umask():
    mask = os.umask(0)
    os.umask(mask)
    return mask


def publish_mode(path, directory=False):
    """mkdtemp/mkstemp create private (0700/0600) entries; give outputs the usual umask-based mode."""
    os.chmod(path, (0o777 if directory else 0o666) & ~_umask())


def os_error(exc, default):
    """InputError for an OSError of the environment (full disk, read-only folder, long name), naming the file."""
    return InputError(f"{exc.filename or default}: {exc.strerror or type(exc).__name__}")


ENVIRONMENT_ERRNOS = {errno.ENOSPC, errno.EACCES, errno.EPERM, errno.EROFS, errno.ENAMETOOLONG, errno.EDQUOT,
                      errno.ENOTDIR, errno.EEXIST, errno.EISDIR, errno.ENOENT, errno.ELOOP, errno.EXDEV}


@contextlib.contextmanager
def publish(folders, command="calib"):
    """Yield temporary folders (one per entry of ``folders``); on success replace all targets with them.

    Each target is checked with :func:`check_replaceable` before any work and again just before the swap;
    each published folder gets a ``.calib-output`` marker. On any exception nothing is published and the
    temporary folders are removed. OSErrors of the environment become InputError naming the file.
    """
    folders = [Path(f) for f in folders]
    for f in folders:
        check_replaceable(f)
    tmps = []
    try:
        try:
            for f in folders:
                f.parent.mkdir(parents=True, exist_ok=True)
                tmp = Path(tempfile.mkdtemp(prefix=f".{f.name}.tmp-", dir=f.parent))
                tmps.append(tmp)
                publish_mode(tmp, directory=True)
        except OSError as exc:
            raise os_error(exc, folders[len(tmps)]) from None
        yield tmps
        try:
            for f, tmp in zip(folders, tmps):
                write_marker(tmp, command)
                check_replaceable(f)
            for f, tmp in zip(folders, tmps):
                _swap(f, tmp)
        except OSError as exc:
            if exc.errno not in ENVIRONMENT_ERRNOS:
                raise
            raise os_error(exc, folders[0]) from None
    except BaseException:
        for tmp in tmps:
            shutil.rmtree(tmp, ignore_errors=True)
        raise


def _swap(target, tmp):
    """Rename ``tmp`` to ``target``; an existing (replaceable) target is moved aside, then removed."""
    old = None
    if target.exists():
        old = target.parent / f".{target.name}.old-{os.getpid()}"
        if old.exists():
            shutil.rmtree(old)
        target.rename(old)
    tmp.rename(target)
    if old is not None:
        shutil.rmtree(old, ignore_errors=True)


@contextlib.contextmanager
def owned_output(folders, inputs=(), *, command="calib", on_wait=None, lock=None, check=True):
    """The whole policy for a command writing ``folders``: separation, lock, litter, replaceability.

    lock : the folder whose lock to hold (default: every one of ``folders``, in a fixed order).
    check : check now that every folder may be replaced; False: only that no folder holds a file calib
        did not write (``calib run`` checks hand-edits per stage: an edit is fine if its stage is skipped).
    Nothing is written here; write with :func:`publish` inside this context.
    """
    folders = [Path(f) for f in folders]
    check_separate(folders, inputs)
    locks = [Path(lock)] if lock is not None else sorted(set(folders), key=lambda f: str(_resolve(f)))
    with contextlib.ExitStack() as stack:
        for f in locks:
            stack.enter_context(output_lock(f, on_wait=on_wait))
        for f in folders:
            remove_litter(f)
            check_replaceable(f, edits=check)
        yield
