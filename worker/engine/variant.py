"""Choosing the Mitsuba variant once per process, with a clean fallback to ``scalar_rgb``.

Dr.Jit's LLVM backend needs LLVM ≥ 16 (the system LLVM 15 crashes it), and it reads the library
path from ``DRJIT_LIBLLVM_PATH`` when the backend starts, so the path is set before Mitsuba is
imported. Nothing here runs at import time.
"""

from __future__ import annotations

import glob
import logging
import os
import re
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

log = logging.getLogger(__name__)

CUDA_VARIANT = "cuda_ad_rgb"
LLVM_VARIANT = "llvm_ad_rgb"
SCALAR_VARIANT = "scalar_rgb"
#: Oldest LLVM major version Dr.Jit runs on here.
LLVM_MIN_MAJOR = 16
_LLVM_GLOBS = (
    "/usr/lib/x86_64-linux-gnu/libLLVM*.so*",
    "/usr/lib/aarch64-linux-gnu/libLLVM*.so*",
    "/usr/lib/llvm-*/lib/libLLVM*.so*",
    "/usr/local/lib/libLLVM*.so*",
    "/opt/homebrew/opt/llvm/lib/libLLVM*.dylib",
)


def _llvm_major(path: str) -> int | None:
    m = re.search(r"libLLVM[-.]?(?:so\.)?(\d+)", os.path.basename(path)) or re.search(
        r"llvm-(\d+)", path
    )
    return int(m.group(1)) if m else None


def find_llvm(explicit: Path | None = None) -> str | None:
    """Path of a libLLVM ≥ 16, or None. ``explicit`` (or $DRJIT_LIBLLVM_PATH) wins if it exists."""
    for candidate in (explicit, os.environ.get("DRJIT_LIBLLVM_PATH")):
        if candidate and Path(candidate).exists():
            return str(candidate)
    found: list[tuple[int, str]] = []
    for pattern in _LLVM_GLOBS:
        for path in glob.glob(pattern):
            major = _llvm_major(path)
            if major is not None and major >= LLVM_MIN_MAJOR:
                found.append((major, path))
    return max(found)[1] if found else None


def choose_variant(requested: str = "auto", llvm_path: Path | None = None) -> str:
    """Set and return the Mitsuba variant for this process (idempotent).

    ``requested`` is 'auto', 'cuda_ad_rgb', 'llvm_ad_rgb' or 'scalar_rgb'. 'auto' takes CUDA
    when Dr.Jit finds a CUDA device (:func:`cuda_available`), else LLVM, used only when a
    library ≥ 16 is found and Dr.Jit reports the backend usable; otherwise scalar_rgb, with a
    log line. A requested 'cuda_ad_rgb' without a device falls back the same way.
    """
    import mitsuba as mi

    current = mi.variant()
    if current is not None:
        return str(current)
    if requested in ("auto", CUDA_VARIANT):
        if cuda_available():
            mi.set_variant(CUDA_VARIANT)
            log.info("mitsuba variant %s", CUDA_VARIANT)
            return CUDA_VARIANT
        if requested == CUDA_VARIANT:
            log.warning("no CUDA device: rendering with the LLVM or scalar variant")
    variant = SCALAR_VARIANT
    if requested in ("auto", CUDA_VARIANT, LLVM_VARIANT):
        lib = find_llvm(llvm_path)
        if lib is None:
            log.info("no LLVM >= %d found: rendering with %s", LLVM_MIN_MAJOR, SCALAR_VARIANT)
        else:
            os.environ["DRJIT_LIBLLVM_PATH"] = lib
            import drjit as dr

            if dr.has_backend(dr.JitBackend.LLVM):
                variant = LLVM_VARIANT
            else:
                log.warning("Dr.Jit cannot use %s: rendering with %s", lib, SCALAR_VARIANT)
    mi.set_variant(variant)
    log.info("mitsuba variant %s", variant)
    return variant


def cuda_available() -> bool:
    """Whether this Mitsuba build has the CUDA variant and Dr.Jit finds a CUDA device."""
    import drjit as dr
    import mitsuba as mi

    if CUDA_VARIANT not in mi.variants():
        return False
    try:
        return bool(dr.has_backend(dr.JitBackend.CUDA))
    except Exception:  # a broken driver is no device
        log.info("Dr.Jit could not start CUDA", exc_info=True)
        return False


@contextmanager
def one_render_thread() -> Iterator[None]:
    """Dr.Jit on one thread meanwhile: Mitsuba's path tracer gives a seeded render that differs
    from run to run on several threads (the order of its atomic accumulations); a seeded
    reference must be the same image every time."""
    import drjit as dr

    threads = dr.thread_count()
    dr.set_thread_count(1)
    try:
        yield
    finally:
        dr.set_thread_count(threads)
