"""The output policy of every command (docs/reliability.md): calib never replaces or deletes a file it did
not write, nor an input of the command.

1. An output never equals, contains or lies inside an input (symlinks resolved), and two outputs of one
   command never overlap: :func:`check_separate`, :func:`check_distinct`.
2. calib replaces only what it wrote. Every folder holding something calib wrote has a manifest
   ``.calib-output`` (JSON: the sha256 of every file calib wrote there). A folder may be replaced when it is
   absent, empty, or holds only files of its manifest, unedited (:func:`check_replaceable`); a single file
   when it is absent or listed, unedited, in its folder's manifest (:func:`check_file_replaceable`). A file
   calib did not write, a hand edit and any symbolic link are the user's: the command stops and touches
   nothing. Every writer goes through :func:`publish` (folders) or :func:`write_file` (single files).
3. One writer per output: an exclusive ``fcntl.flock`` on ``.<name>.calib-lock`` beside it; a second command
   waits (:func:`output_lock`). A command locks its folder and every sub-folder it writes, in one global
   order, so ``calib run -o OUT`` and ``calib features -o OUT/features`` serialise.
4. Temporaries are named ``.<name>.calib-tmp-<32 hex>`` / ``.<name>.calib-old-<32 hex>``, and a temporary
   folder holds ``.calib-tmp`` with that token: only calib makes them, so a user's ``.x.tmp-mine`` is never
   taken for litter. The next command holding the lock removes those of killed runs (:func:`remove_litter`).
   Nothing is ever deleted through a symbolic link.
5. A command writes all its folders into temporary siblings and renames them into place only when all of
   them are complete (:func:`publish`): it writes everything or nothing. Folders made only to hold an output
   are removed again when the command fails (:func:`owned_output`).
"""
from __future__ import annotations

import contextlib
import errno
import fcntl
import hashlib
import json
import os
import re
import secrets
import shutil
from pathlib import Path

from calib.errors import InputError
from calib.interrupts import deferred

MARKER = ".calib-output"
STAGE_STAMP = ".calib-stage.json"
LOCK_SUFFIX = ".calib-lock"
TMP_MARK = ".calib-tmp"  # inside a temporary folder: its token (proof that calib made it)
# calib's own bookkeeping inside an owned folder (never listed in the marker, never a user file)
BOOKKEEPING = (MARKER, STAGE_STAMP, TMP_MARK)
_TEMP = re.compile(r"^\.(?P<name>.+)\.calib-(?P<kind>tmp|old)-(?P<token>[0-9a-f]{32})$")


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


def check_distinct(outputs):
    """Raise InputError if two outputs of one command are the same folder or one lies inside the other."""
    res = [(_resolve(o), o) for o in outputs]
    for k, (a, oa) in enumerate(res):
        for b, ob in res[k + 1:]:
            if a == b or a in b.parents or b in a.parents:
                raise InputError(f"{ob}: the same folder as (or nested with) the other output {oa}; "
                                 "give the outputs separate folders")


def _sha256(path):
    h = hashlib.sha256()
    with open(path, "rb") as f:
        while block := f.read(1 << 20):
            h.update(block)
    return h.hexdigest()


def temp_token():
    """A fresh 32-hex token for a temporary's name (only calib makes names with one)."""
    return secrets.token_hex(16)


def temp_path(target, kind="tmp", token=None):
    """``.<name>.calib-<kind>-<token>`` beside ``target``: the name of one of calib's temporaries."""
    target = Path(target)
    return target.parent / f".{target.name}.calib-{kind}-{token or temp_token()}"


def is_own_temp(path, name=None):
    """Whether ``path`` is a temporary calib made (of the output ``name``, if given); never a symlink.

    A file needs the exact name pattern (a 128-bit token); a folder also its ``.calib-tmp`` holding the token.
    """
    path = Path(path)
    m = _TEMP.match(path.name)
    if m is None or (name is not None and m["name"] != name) or path.is_symlink():
        return False
    if path.is_dir():
        try:
            return (path / TMP_MARK).read_text().strip() == m["token"]
        except OSError:
            return False
    return path.is_file()


def _is_lock(name):
    return name.startswith(".") and name.endswith(LOCK_SUFFIX)


def _is_bookkeeping(folder, rel):
    """calib's own entries inside an owned folder: the manifest, stamps, locks, its temporaries."""
    name = Path(rel.rstrip("/")).name
    return name in BOOKKEEPING or _is_lock(name) or is_own_temp(Path(folder) / rel.rstrip("/"))


def _entries(folder):
    """(relative posix paths of every file and empty sub-folder under ``folder``, those of symlinks).

    Symlinks are listed, never followed (a symlinked folder is one entry)."""
    out, links = [], []
    for root, dirs, files in os.walk(folder):
        rel_root = Path(root).relative_to(folder)
        for d in list(dirs):
            if (Path(root) / d).is_symlink():
                links.append((rel_root / d).as_posix())
                dirs.remove(d)
            elif _is_bookkeeping(folder, (rel_root / d).as_posix()):
                dirs.remove(d)  # one of calib's temporaries: not walked
            elif not os.listdir(Path(root) / d):
                out.append((rel_root / d).as_posix() + "/")
        for f in files:
            (links if (Path(root) / f).is_symlink() else out).append((rel_root / f).as_posix())
    return out, links


def read_marker(folder):
    """{relative file: sha256} of the files calib wrote in ``folder``, or None when it has no valid manifest."""
    data = _read_manifest(folder)
    return None if data is None else {str(k): str(v) for k, v in data["files"].items()}


def _read_manifest(folder):
    """The manifest's dict (``files``, ``command``, ``writers``), or None when absent or not valid."""
    try:
        data = json.loads((Path(folder) / MARKER).read_text())
        if isinstance(data, dict) and isinstance(data.get("files"), dict):
            return data
    except (OSError, ValueError, RecursionError):
        pass
    return None


def _writer(folder, name):
    """The command that wrote the file ``name`` of ``folder`` (its own entry, else the folder's), or None."""
    data = _read_manifest(folder) or {}
    writers = data.get("writers") if isinstance(data.get("writers"), dict) else {}
    return str(writers.get(name) or data.get("command") or "") or None


def _write_manifest(folder, files, command, writers=None):
    data = {"written_by": "calib", "command": command, "files": dict(sorted(files.items()))}
    if writers:
        data["writers"] = dict(sorted(writers.items()))
    write_replacing(Path(folder) / MARKER, json.dumps(data, indent=1) + "\n")


def _update_manifest(folder, name, digest, command):
    """Record (or, ``digest`` None, forget) the single file ``name`` calib wrote in ``folder`` (hold its lock)."""
    data = _read_manifest(folder) or {"command": command, "files": {}}
    files = {str(k): str(v) for k, v in data["files"].items()}
    writers = data.get("writers") if isinstance(data.get("writers"), dict) else {}
    if digest is None:
        files.pop(name, None)
        writers.pop(name, None)
    else:
        files[name] = digest
        writers[name] = command
    if files:
        _write_manifest(folder, files, data.get("command") or command, writers)
    else:
        (Path(folder) / MARKER).unlink()


def write_marker(folder, command):
    """Write ``.calib-output`` into ``folder`` (calib's own new folder) listing every file with its sha256."""
    out, _ = _entries(folder)
    files = {rel: _sha256(Path(folder) / rel) for rel in out
             if not rel.endswith("/") and not _is_bookkeeping(folder, rel)}
    _write_manifest(folder, files, command)


def check_replaceable(folder, edits=True):
    """Raise InputError unless calib may replace ``folder`` (absent, empty, or owned and unedited).

    edits : also refuse files edited since calib wrote them (False: only files calib did not write).
    Symbolic links are never calib's: one anywhere inside stops the command.
    """
    folder = Path(folder)
    if not folder.exists() and not folder.is_symlink():
        return
    if folder.is_symlink() or not folder.is_dir():
        raise InputError(f"{folder}: exists and is not a folder calib wrote; choose another output or move it")
    out, links = _entries(folder)
    if links:
        raise InputError(f"{folder / links[0]}: a symbolic link calib did not create; move it out of {folder} "
                         "(calib never deletes your files)")
    entries = [rel for rel in out if not _is_bookkeeping(folder, rel)]
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


def _command_name(command):
    return " ".join(str(command).split()[:2])  # "calib export --format yaml" → "calib export"


def check_file_replaceable(path, inputs=(), replace=True, command=None, kin=()):
    """Raise InputError unless calib may write the single file ``path``.

    It may when ``path`` is absent, or a plain file listed in its folder's manifest and unedited (and
    ``replace``), written by the same command (``command``, when given: `calib export` does not replace a
    calibration's arrays.csv) or by one of ``kin``, the commands that write the same file for the same use
    (`calib init` replaces the session.toml of `calib simulate`); never when it is an input (``inputs``,
    symlinks resolved), a folder or a symbolic link.
    """
    path = Path(path)
    for inp in inputs:
        if inp is not None and _resolve(inp) == _resolve(path):
            raise InputError(f"{path}: is an input of this command ({inp}); write the output elsewhere")
    if not path.exists() and not path.is_symlink():
        return
    if path.is_symlink() or not path.is_file():
        raise InputError(f"{path}: exists and is not a file calib wrote; choose another output or move it")
    marker = read_marker(path.parent) or {}
    if path.name not in marker:
        raise InputError(f"{path}: exists and calib did not write it; choose another output or move it "
                         "(calib never replaces your files)")
    if _sha256(path) != marker[path.name]:
        raise InputError(f"{path}: edited since calib wrote it; move it away or rename it to keep your edit")
    writer = _writer(path.parent, path.name)
    if command is not None and writer is not None and \
            _command_name(writer) not in {_command_name(c) for c in (command, *kin)}:
        raise InputError(f"{path}: written by `{_command_name(writer)}`, not by `{_command_name(command)}`; "
                         "choose another output")
    if not replace:
        raise InputError(f"{path}: exists (use --force to replace it)")


# ----------------------------------------------------------------------------------------------- lock
def lock_path(target):
    target = Path(target)
    return _resolve(target).parent / f".{target.name}{LOCK_SUFFIX}"


@contextlib.contextmanager
def output_lock(folder, on_wait=None):
    """Hold an exclusive lock for writing ``folder`` (``.<name>.calib-lock`` beside it); waits for another holder.

    The lock file is removed on release (so a finished command leaves nothing); a waiter that wakes up on
    a removed lock file notices (different inode) and locks the new one.
    on_wait : optional ``on_wait(message)`` called once if another process holds the lock.
    """
    folder = Path(folder)
    path = lock_path(folder)
    created = []
    try:
        with deferred():
            created = _make_parents(path.parent, folder)
        with _locked(path, folder, on_wait):
            yield
    finally:
        remove_made(created)  # folders made only for this output and left empty (a failed command)


def remove_made(created):
    """rmdir the folders of ``created`` (outermost first) that are still empty, innermost first."""
    for d in reversed(created):
        try:
            d.rmdir()
        except OSError:
            break


def _make_parents(parent, folder):
    """mkdir -p ``parent``; returns the folders it created (outermost first)."""
    missing = _missing(parent)
    try:
        parent.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise os_error(exc, folder) from None
    return missing


def _missing(path):
    """The folders of ``path`` and its parents that do not exist yet (outermost first)."""
    missing = []
    p = Path(path)
    while not p.exists() and not p.is_symlink() and p != p.parent:
        missing.append(p)
        p = p.parent
    return missing[::-1]


@contextlib.contextmanager
def _locked(path, folder, on_wait):
    """flock the file ``path`` (created), retrying if its holder removed it meanwhile; removed on release."""
    held = []  # the locked descriptor, once this process holds the lock
    try:
        _acquire(path, folder, on_wait, held)
        os.ftruncate(held[0], 0)
        os.pwrite(held[0], f"{os.getpid()}\n".encode(), 0)
        yield
    finally:
        if held:
            with contextlib.suppress(OSError):
                os.unlink(path)  # while still holding the lock (see output_lock)
            os.close(held[0])


def _acquire(path, folder, on_wait, held):
    """Lock ``path`` and append its descriptor to ``held``; an interrupt on the way leaves no lock file."""
    told = False
    while True:
        fd = None
        try:
            with deferred():
                fd = _open_lock_file(path, folder)
            told = _wait_for(fd, folder, on_wait, told)
            with deferred():
                if _same_file(fd, path):
                    held.append(fd)
                    return
        except BaseException:
            if fd is not None and not held:
                _discard_lock_file(fd, path)
            raise
        os.close(fd)  # the holder removed that lock file while we waited: lock the current one


def _open_lock_file(path, folder):
    while True:
        try:
            return os.open(path, os.O_RDWR | os.O_CREAT | os.O_NOFOLLOW, 0o666)
        except FileNotFoundError:  # another command removed its empty parent folder meanwhile: make it again
            _make_parents(path.parent, folder)
        except OSError as exc:
            raise InputError(f"{exc.filename or folder}: cannot create the output ({exc.strerror})") from None


def _wait_for(fd, folder, on_wait, told):
    """flock ``fd``, waiting (interruptibly) for another holder; returns whether the wait was announced."""
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        holder = os.pread(fd, 32, 0).decode(errors="replace").strip() or "?"
        if on_wait is not None and not told:
            on_wait(f"{folder}: another calib (pid {holder}) is writing here; waiting for it to finish")
            told = True
        fcntl.flock(fd, fcntl.LOCK_EX)
    return told


def _discard_lock_file(fd, path):
    """Close ``fd`` after an interrupt; the lock file goes too when no other command holds it."""
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        if _same_file(fd, path):
            os.unlink(path)
    except OSError:
        pass  # another command holds it: it removes the file on release
    finally:
        os.close(fd)


def _same_file(fd, path):
    try:
        a, b = os.fstat(fd), os.stat(path, follow_symlinks=False)
    except FileNotFoundError:
        return False
    return (a.st_dev, a.st_ino) == (b.st_dev, b.st_ino)


def remove_temp(path):
    """Remove one of calib's temporaries (a folder: its tree, symlinks inside removed, never followed)."""
    path = Path(path)
    if path.is_dir() and not path.is_symlink():
        shutil.rmtree(path, ignore_errors=True)
    else:
        with contextlib.suppress(OSError):
            path.unlink()


@contextlib.contextmanager
def removed_on_error(tmp):
    """Remove the temporary ``tmp`` if the block that makes it raises (an interrupt included).

    The block creates ``tmp``: an interrupt may land between its creation and any code that would note it,
    so the clean-up looks at the path itself. Its name carries a fresh 128-bit token (:func:`temp_path`):
    whatever is there, calib made it."""
    try:
        yield tmp
    except BaseException:
        remove_temp(tmp)
        raise


def remove_litter(target):
    """Remove calib's temporaries of ``target`` left beside it by killed runs (hold its lock).

    Only names ``.<name>.calib-tmp-<token>`` / ``.<name>.calib-old-<token>`` that :func:`is_own_temp` proves
    calib's; a user's ``.<name>.tmp-mine`` or ``.<name>.old-v1/`` is never touched."""
    target = Path(target)
    parent = target.parent
    if not parent.is_dir():
        return
    for p in parent.glob(f".{glob_escape(target.name)}.calib-*"):
        if is_own_temp(p, target.name):
            remove_temp(p)


def glob_escape(name):
    return re.sub(r"([*?\[])", r"[\1]", name)


# ----------------------------------------------------------------------------------------------- publish
def _umask():
    mask = os.umask(0)
    os.umask(mask)
    return mask


def publish_mode(path, directory=False):
    """Temporaries are created private (0700/0600); give outputs the usual umask-based mode."""
    os.chmod(path, (0o777 if directory else 0o666) & ~_umask())


def os_error(exc, default):
    """InputError for an OSError of the environment (full disk, read-only folder, long name), naming the file."""
    return InputError(f"{exc.filename or default}: {exc.strerror or type(exc).__name__}")


ENVIRONMENT_ERRNOS = {errno.ENOSPC, errno.EACCES, errno.EPERM, errno.EROFS, errno.ENAMETOOLONG, errno.EDQUOT,
                      errno.ENOTDIR, errno.EEXIST, errno.EISDIR, errno.ENOENT, errno.ELOOP, errno.EXDEV}


def make_temp_dir(target):
    """A new temporary folder beside ``target`` (``.<name>.calib-tmp-<token>``, holding ``.calib-tmp``)."""
    token = temp_token()
    tmp = temp_path(target, "tmp", token)
    with removed_on_error(tmp):
        tmp.mkdir(mode=0o700)
        (tmp / TMP_MARK).write_text(token + "\n")
    return tmp


def _drop_temp_mark(folder):
    with contextlib.suppress(FileNotFoundError):
        (Path(folder) / TMP_MARK).unlink()


@contextlib.contextmanager
def publish(folders, command="calib"):
    """Yield temporary folders (one per entry of ``folders``); on success replace all targets with them.

    Each target is checked with :func:`check_replaceable` before any work and again just before the swap;
    each published folder gets a ``.calib-output`` marker. On any exception nothing is published and the
    temporary folders are removed. OSErrors of the environment become InputError naming the file.
    """
    folders = [Path(f) for f in folders]
    check_distinct(folders)
    for f in folders:
        check_replaceable(f)
    tmps = []
    try:
        try:
            for f in folders:
                f.parent.mkdir(parents=True, exist_ok=True)
                with deferred():
                    tmps.append(make_temp_dir(f))
                publish_mode(tmps[-1], directory=True)
        except OSError as exc:
            raise os_error(exc, folders[len(tmps)]) from None
        yield tmps
        try:
            for f, tmp in zip(folders, tmps):
                write_marker(tmp, command)
                check_replaceable(f)
            with deferred():  # every folder, or (an OSError) none: an interrupt waits for the renames
                for f, tmp in zip(folders, tmps):
                    _swap(f, tmp)
        except OSError as exc:
            if exc.errno not in ENVIRONMENT_ERRNOS:
                raise
            raise os_error(exc, folders[0]) from None
    except BaseException:
        for tmp in tmps:
            if is_own_temp(tmp):
                remove_temp(tmp)
        raise


def _swap(target, tmp):
    """Rename ``tmp`` to ``target``; an existing (replaceable) target is moved aside, then removed."""
    old = None
    if target.is_dir() and not target.is_symlink():
        if not os.listdir(target):
            target.rmdir()  # an empty folder: nothing to keep aside
        else:
            token = temp_token()
            (target / TMP_MARK).write_text(token + "\n")  # calib's own folder: mark it as a temporary
            old = temp_path(target, "old", token)
            target.rename(old)
    try:
        tmp.rename(target)
    except BaseException:  # an interrupt or a failed rename: the previous output goes back in place
        if old is not None and not target.exists():
            old.rename(target)
            _drop_temp_mark(target)
        raise
    _drop_temp_mark(target)  # after the rename: until then the temporary stays provably calib's (is_own_temp)
    if old is not None:
        remove_temp(old)


# ----------------------------------------------------------------------------------------------- files
@contextlib.contextmanager
def _manifest_lock(folder):
    """Lock ``folder``'s manifest for a read-modify-write (innermost lock: held briefly, never nested)."""
    with _locked(Path(folder) / f"{MARKER}{LOCK_SUFFIX}", folder, None):
        yield


def write_new(tmp, data):
    """Write the new file ``tmp`` (created here: never an existing file, never through a symlink) with ``data``
    (bytes, str as UTF-8, or a function writing to a given path), with an output's mode (:func:`publish_mode`)."""
    if callable(data):
        data(tmp)
    else:
        fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL | os.O_NOFOLLOW, 0o600)
        with os.fdopen(fd, "wb") as f:
            f.write(data.encode() if isinstance(data, str) else data)
    publish_mode(tmp)


def write_replacing(path, data):
    """Write ``path`` through a new temporary beside it (:func:`write_new`) and a rename, for calib's own files in a
    folder it writes (a temporary of :func:`publish`, a stage's stamp, a manifest); a file a user names goes
    through :func:`write_file` (the output policy)."""
    tmp = temp_path(path)
    with removed_on_error(tmp):
        write_new(tmp, data)
        os.replace(tmp, path)


def write_file(path, data, *, command="calib", inputs=(), replace=True, kin=()):
    """Write the single file ``path`` (an output a user names) under the policy; returns ``path``.

    data : bytes, str (UTF-8) or a function ``data(tmp_path)`` that writes the file (give it an explicit format:
        the temporary's name has no usual suffix).
    command : the command writing it (recorded; a file of another command is not replaced).
    inputs : the command's inputs; ``path`` may not be one of them.
    replace : whether an existing file calib wrote may be replaced (False: ``--force`` was not given).
    kin : other commands whose file ``path`` may be replaced (:func:`check_file_replaceable`).
    The file is written to a temporary beside it and renamed into place; its sha256 goes into the folder's
    manifest ``.calib-output``, which is what makes it replaceable by calib later. A folder made for it is
    removed again if the write fails.
    """
    path = Path(path)
    check_file_replaceable(path, inputs, replace, command, kin)
    try:
        with output_lock(path):
            remove_litter(path)
            tmp = temp_path(path)
            try:
                write_new(tmp, data)
                digest = _sha256(tmp)
                with _manifest_lock(path.parent):
                    check_file_replaceable(path, inputs, replace, command, kin)
                    with deferred():  # the file and its manifest entry together
                        os.replace(tmp, path)
                        _update_manifest(path.parent, path.name, digest, command)
            finally:
                remove_temp(tmp)  # still there if the write failed (an interrupt included)
    except OSError as exc:
        if exc.errno not in ENVIRONMENT_ERRNOS:
            raise
        raise os_error(exc, path) from None
    return path


def remove_owned_file(path):
    """Delete ``path`` only if calib wrote it (listed, unedited, in its folder's manifest); True if deleted."""
    path = Path(path)
    if path.is_symlink() or not path.is_file():
        return False
    with _manifest_lock(path.parent):
        if (read_marker(path.parent) or {}).get(path.name) != _sha256(path):
            return False
        path.unlink()
        _update_manifest(path.parent, path.name, None, "calib")
    return True


# ----------------------------------------------------------------------------------------------- context
@contextlib.contextmanager
def owned_output(folders, inputs=(), *, command="calib", on_wait=None, lock=None, check=True):
    """The whole policy for a command writing ``folders``: separation, lock, litter, replaceability.

    lock : a folder that holds every one of ``folders`` (``calib run``'s OUT): locked too.
    check : check now that every folder may be replaced (True); False: only that no folder holds a file
        calib did not write (``calib run`` checks hand-edits per stage: an edit is fine if its stage is
        skipped); None: no check (a command that writes single files, each checked by :func:`write_file`).
    Locks are taken in one global order (resolved paths), so commands writing nested folders serialise
    without deadlock. Folders made here that are still empty when the command fails are removed.
    Nothing is written here; write with :func:`publish` or :func:`write_file` inside this context.
    """
    folders = [Path(f) for f in folders]
    check_distinct(folders)
    check_separate(folders, inputs)
    targets = folders + ([Path(lock)] if lock is not None else [])
    locks = sorted({_resolve(f): f for f in targets}.items())
    created = sorted({d for f in targets for d in _missing(f)}, key=lambda d: len(d.parts))
    ok = False
    try:
        with contextlib.ExitStack() as stack:
            for _, f in locks:
                stack.enter_context(output_lock(f, on_wait=on_wait))
            for f in folders:
                remove_litter(f)
                if check is not None:
                    check_replaceable(f, edits=check)
            yield
        ok = True
    finally:
        if not ok:
            for d in sorted(created, key=lambda d: -len(d.parts)):
                with contextlib.suppress(OSError):
                    d.rmdir()  # only if still empty: a folder made for this output alone
