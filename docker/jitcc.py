#!/usr/bin/env python3
"""A caching C compiler front for CasADi's jit (``CC`` of the image), like ccache.

CasADi compiles the motion model's generated C with ``$CC -O1 -fPIC -c f.c -o f.o`` and links
it with ``$CC f.o -o f.so -shared``. This front answers both from a cache keyed by the SHA-256
of the input file and the arguments, and fills the cache with the real compiler when it has
one. The image's build stage runs the warm-up with gcc behind it; the final stage has the cache
and no compiler, so the service loads the compiled code built at image build time (the seed
track refines in 0.33 s compiled, 0.86 s interpreted). A function not in the cache (and no
compiler) fails here, and the solver interprets that one (``solver/compiled.py``).

Environment: ``TRAJRECON_JITCC_CACHE`` (default ``/opt/trajrecon-jit``), ``TRAJRECON_JITCC_REAL``
(the real compiler, default ``gcc``; used only when found).
"""

from __future__ import annotations

import hashlib
import os
import shutil
import subprocess
import sys
from pathlib import Path


def split(args: list[str]) -> tuple[Path, Path, list[str]]:
    """``(input, output, other arguments)`` of a compile or link command line."""
    out = Path(args[args.index("-o") + 1])
    rest = [a for i, a in enumerate(args) if a != "-o" and (i == 0 or args[i - 1] != "-o")]
    (source,) = [a for a in rest if a.endswith((".c", ".o"))]
    flags = [a for a in rest if a != source]
    return Path(source), out, flags


def main(args: list[str]) -> int:
    cache = Path(os.environ.get("TRAJRECON_JITCC_CACHE", "/opt/trajrecon-jit"))
    try:
        source, out, flags = split(args)
    except (ValueError, IndexError):
        print(f"jitcc: unsupported command line: {args}", file=sys.stderr)
        return 2
    key = hashlib.sha256(source.read_bytes() + "\0".join(flags).encode()).hexdigest()
    cached = cache / f"{key}{out.suffix}"
    if cached.exists():
        shutil.copyfile(cached, out)
        return 0
    real = shutil.which(os.environ.get("TRAJRECON_JITCC_REAL", "gcc"))
    if real is None:
        print(f"jitcc: {source.name} is not in {cache} and there is no compiler", file=sys.stderr)
        return 1
    code = subprocess.call([real, *args])
    if code == 0 and os.access(cache, os.W_OK):
        shutil.copyfile(out, cached)
    return code


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
