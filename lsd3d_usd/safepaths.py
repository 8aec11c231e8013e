"""Destructive file steps that stay inside the folder they belong to.

A scene folder (or a batch output root) may hold a planted symbolic link: ``viewer_cache``
pointing at someone's data, ``layers/proxy_chunks`` pointing elsewhere. Writing, replacing or
deleting through such a link changes files outside the folder. Every destructive step here
first checks the *lexical* path below its root component by component (no component may be a
symbolic link) and then the *real* path (it must lie inside the root's real path), and refuses
with one line (``InputError``) before anything is touched.

Bottom layer: imports only ``errors``.
"""
from __future__ import annotations

import os
import shutil
from contextlib import contextmanager
from pathlib import Path

from lsd3d_usd.errors import InputError


def _abs(p) -> Path:
    return Path(os.path.abspath(os.fspath(p)))


def link_below(path, root) -> Path | None:
    """The first component of ``path`` below ``root`` (``path`` itself included) that is a
    symbolic link, or None. ``path`` outside ``root`` lexically counts as its own answer."""
    p, r = _abs(path), _abs(root)
    try:
        rel = p.relative_to(r)
    except ValueError:
        return p
    cur = r
    for part in rel.parts:
        cur = cur / part
        if cur.is_symlink():
            return cur
    return None


def check_inside(path, root, what: str = "path") -> Path:
    """``path`` (absolute), refused with one line when it lies outside ``root`` or reaches
    there through a symbolic link. Parts that do not exist yet are fine."""
    p, r = _abs(path), _abs(root)
    link = link_below(p, r)
    if link is not None:
        if link == p and not p.is_symlink():
            raise InputError(f"{p}: {what} lies outside {r}; refusing to write or delete there")
        raise InputError(f"{link}: {what} is a symbolic link (to {os.readlink(link)}); "
                         f"refusing to write or delete through it")
    real = p.resolve()
    if not real.is_relative_to(r.resolve()):
        raise InputError(f"{p}: {what} resolves to {real}, outside {r}; refusing to write "
                         "or delete there")
    return p


def links_in_tree(folder, limit: int = 10) -> list[Path]:
    """Symbolic links at or below ``folder`` (not followed), at most ``limit``."""
    f = _abs(folder)
    if f.is_symlink():
        return [f]
    found: list[Path] = []
    if not f.is_dir():
        return found
    for dirpath, dirnames, filenames in os.walk(f, followlinks=False):
        for name in dirnames + filenames:
            q = Path(dirpath) / name
            if q.is_symlink():
                found.append(q)
                if len(found) >= limit:
                    return found
    return found


def check_tree(folder, root, what: str = "folder") -> None:
    """Refuse (one line) when ``folder`` is reached through a link, lies outside ``root`` or
    holds a symbolic link anywhere below it: a step that rewrites or prunes the folder
    would otherwise follow it."""
    check_inside(folder, root, what)
    links = links_in_tree(folder, 1)
    if links:
        raise InputError(f"{links[0]}: symbolic link (to {os.readlink(links[0])}) inside the "
                         f"{what}; refusing to write or delete there (replace it with a real "
                         "file or folder)")


def unlink(path, root, what: str = "file", missing_ok: bool = True) -> None:
    """Remove one file (a symlink at ``path`` itself is refused, not followed)."""
    p = check_inside(path, root, what)
    p.unlink(missing_ok=missing_ok)


def rmtree(path, root, what: str = "folder", missing_ok: bool = True) -> None:
    """Remove a folder tree that lies inside ``root`` and holds no symbolic links."""
    p = _abs(path)
    if not p.exists() and not p.is_symlink():
        if missing_ok:
            return
        raise InputError(f"{p}: no such {what}")
    check_tree(p, root, what)
    shutil.rmtree(p)


def replace(src, dst, root, what: str = "path") -> None:
    """``os.replace(src, dst)`` with both inside ``root`` and reached without links."""
    check_inside(src, root, what)
    check_inside(dst, root, what)
    os.replace(src, dst)


@contextmanager
def removed_on_error(folder, keep=None, errors=(InputError,)):
    """Run the block; when it raises one of ``errors`` and ``folder`` was missing or empty
    before, empty it again (and remove it if it was missing): a refused run leaves nothing
    that a plain re-run would then refuse as "not empty". ``keep()`` true at that point
    (e.g. a finished log worth resuming) keeps everything."""
    f = _abs(folder)
    existed = f.is_dir() and not f.is_symlink()
    fresh = (not f.exists() and not f.is_symlink()) or (existed and not any(f.iterdir()))
    try:
        yield
    except errors:
        if fresh and f.is_dir() and not f.is_symlink() and not (keep and keep()):
            if existed:
                for child in list(f.iterdir()):
                    if child.is_dir() and not child.is_symlink():
                        rmtree(child, f, "output folder")
                    else:
                        unlink(child, f, "output file")
            else:
                rmtree(f, f.parent, "output folder")
        raise
