#!/usr/bin/env python3
"""Shrink a virtual environment's site-packages for the image: ``slim.py SITE_PACKAGES``.

- Wheels cannot hold symbolic links, so a shared library shipped as ``libx.so``,
  ``libx.so.3`` and ``libx.so.3.7`` is three copies (casadi, numpy.libs...): every copy after
  the first in a directory becomes a symbolic link to it (measured on the locked set: 135 MB).
- Test suites that packages ship inside themselves (``numpy/*/tests``, ``scipy/**/tests``,
  ``pyarrow/tests``: 72 MB) are removed; nothing imports them at run time.

Prints what it saved. Run in the image's build stage after the locked install.
"""

from __future__ import annotations

import hashlib
import os
import shutil
import sys
from collections import defaultdict
from pathlib import Path


def digest(path: Path) -> str:
    h = hashlib.sha256()
    with path.open("rb") as f:
        while chunk := f.read(1 << 20):
            h.update(chunk)
    return h.hexdigest()


def link_duplicates(site: Path, min_size: int = 100_000) -> int:
    """Replace identical files of one directory by links to one of them; bytes saved."""
    groups: dict[tuple[Path, int], list[Path]] = defaultdict(list)
    for path in site.rglob("*"):
        if path.is_file() and not path.is_symlink() and path.stat().st_size >= min_size:
            groups[(path.parent, path.stat().st_size)].append(path)
    saved = 0
    for (_, size), paths in groups.items():
        if len(paths) < 2:
            continue
        by_hash: dict[str, list[Path]] = defaultdict(list)
        for path in paths:
            by_hash[digest(path)].append(path)
        for same in by_hash.values():
            keep, *copies = sorted(same, key=lambda p: (len(p.name), p.name))
            for copy in copies:
                copy.unlink()
                os.symlink(keep.name, copy)
                saved += size
    return saved


def remove_tests(site: Path) -> int:
    """Remove ``tests`` directories inside installed packages; bytes saved."""
    saved = 0
    for path in sorted(site.glob("*/**/tests"), key=lambda p: len(p.parts)):
        if path.is_dir() and not path.is_symlink() and path.exists():
            saved += sum(f.stat().st_size for f in path.rglob("*") if f.is_file())
            shutil.rmtree(path)
    return saved


def main(site: str) -> None:
    root = Path(site)
    linked, tests = link_duplicates(root), remove_tests(root)
    print(f"slim: {linked / 1e6:.0f} MB of duplicate files linked, "
          f"{tests / 1e6:.0f} MB of test suites removed")


if __name__ == "__main__":
    main(sys.argv[1])
