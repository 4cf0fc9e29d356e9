"""What the C and C++ libraries (ITK through SimpleITK, OpenCV, libpng, HDF5,
NIfTI, MetaIO) say when a file is bad, in the project's words.

Their exception texts carry their build's source paths and line numbers
(``/tmp/SimpleITK-build/ITK/Modules/IO/NRRD/src/itkNrrdImageIO.cxx:410``),
object addresses and function names, and some of them also print lines of
their own on the process's standard error (``libpng error: ...``,
``MetaImage: M_ReadElementsData: ...``, ``HDF5-DIAG: ...`` with the build's
paths) before the project's one-line message. A user needs what failed and
the file as they gave it (docs/reliability.md, promise 1):

- :func:`image_read_problem` and :func:`image_write_problem` turn an ITK
  exception into a few words (``damaged NRRD header``) and the header field
  it names, if any, for a :class:`~fluoguide.errors.FluoInputError` that
  names the file itself;
- :func:`opencv_problem` does the same for ``cv2.error``;
- :func:`scrub` takes the libraries' internals out of any text (the CLI's
  last resort uses it: a bug's message may still be a library's);
- :func:`native_stderr_quiet` keeps what the libraries write to file
  descriptor 2 during a call off the terminal (kept in the log at debug
  level).
"""

from __future__ import annotations

import contextlib
import logging
import os
import re
import sys
import tempfile
import threading

from fluoguide.errors import one_line

__all__ = ["image_read_problem", "image_write_problem", "opencv_problem", "scrub",
           "native_stderr_quiet"]

log = logging.getLogger("fluoguide.native")

# "Exception thrown in SimpleITK ImageFileReader_Execute: /path/file.cxx:99:"
_SITK_PREFIX = re.compile(r"Exception thrown in SimpleITK \w+:\s*(?:\S+?:\d+:)?")
# "OpenCV(4.10.0) /io/opencv/modules/core/src/x.cpp:123: error: (-215:Assertion failed) "
_CV_PREFIX = re.compile(r"OpenCV\([^)]*\)\s*(?:\S+?:\d+:)?\s*error:\s*")
# "itk::ERROR: NrrdImageIO(0x5639...): ", "ITK ERROR: ...", "sitk::ERROR: "
_ITK_TAG = re.compile(r"(?:s?itk::)?(?:ITK )?(?:ERROR|WARNING):\s*(?:\w+\s*\(0x[0-9a-fA-F]+\):\s*)?")
# a source position: "/tmp/SimpleITK-build/.../itkNrrdImageIO.cxx:410" (any absolute path
# of a source file, with or without its line)
_SOURCE = re.compile(r"(?:/[^\s:'\"()]+)+\.(?:c|cc|cpp|cxx|h|hh|hpp|hxx|txx)\b(?::\d+:?)?")
# any other absolute path: shown by its last part
_ABS_PATH = re.compile(r"(?<![\w.~-])/(?:[^\s/:'\"(),;]+/)+([^\s/:'\"(),;]+)")
_ADDRESS = re.compile(r"\s*\(0x[0-9a-fA-F]+\)")
# teem's (NRRD) chain: "[nrrd] _nrrdReadNrrdParse_sizes: trouble"
_TEEM = re.compile(r"^\[\w+\]\s*(\w+):\s*(.*)$")


def scrub(text, limit=300):
    """``text`` without a C++ library's internals: the SimpleITK and OpenCV
    prefixes, ITK's ``ERROR`` tags and object addresses, source files and
    their lines, absolute paths (their last part kept); one line of at most
    ``limit`` characters."""
    text = _SITK_PREFIX.sub("", str(text))
    text = _CV_PREFIX.sub("", text)
    text = _ITK_TAG.sub("", text)
    text = _SOURCE.sub("", text)
    text = _ABS_PATH.sub(lambda m: m.group(1), text)
    text = _ADDRESS.sub("", text)
    text = " ".join(part.strip() for part in text.splitlines() if part.strip())
    return one_line(re.sub(r"\s+", " ", text).strip(" :"), limit=limit)


def _teem_detail(lines):
    """The innermost reason of teem's chain of ``[nrrd] function: text`` lines
    (the outer ones only say ``trouble``), in words."""
    reasons = [m.group(2).strip() for m in map(_TEEM.match, lines) if m]
    reasons = [r for r in reasons if r and r.rstrip(".!") != "trouble"
               and not r.startswith("trouble reading")]
    if not reasons:
        return None
    # teem's text stops at a NUL it quotes: "hit invalid character ('"
    r = re.sub(r"\s*\(['\"]?$", "", reasons[-1]).rstrip(".! ")
    m = re.match(r"fread got only (\d+) (\d+)-sized things, not (\d+)", r)
    if m:
        return f"data cut short: {m.group(1)} of {m.group(3)} values"
    m = re.match(r"expected (\d+) bytes but received (\d+)", r)
    if m:
        return f"data cut short: {m.group(2)} of {m.group(1)} bytes"
    return scrub(r, limit=120)


def image_read_problem(exc):
    """``(problem, field)`` for an ITK exception raised reading an image file.

    ``problem`` says what is wrong in words (``damaged NRRD header: axis 1 size
    is zero``); ``field`` is the header field ITK named (``sizes``), else None.
    The caller names the file as the user gave it.
    """
    text = str(exc)
    lines = [ln.strip() for ln in text.splitlines() if ln.strip()]
    if "does not exist" in text:
        return "file not found", None
    if "Unable to determine ImageIO reader" in text:
        return "damaged file or an unknown image format", None
    if any(ln.startswith("[nrrd]") for ln in lines):
        field = None
        for ln in lines:
            m = re.search(r"trouble parsing (\w+) info", ln)
            if m:
                field = m.group(1)
        part = "header" if "ReadImageInformation" in text or field else "data"
        detail = _teem_detail(lines)
        return f"damaged NRRD {part}" + (f": {detail}" if detail else ""), field
    if "MetaImageIO" in text:
        # MetaIO's "Reason: No such file or directory" is errno left over, not the cause
        return "damaged MetaImage file: its header or data cannot be read", None
    if "NiftiImageIO" in text or "NIFTI" in text:
        return "damaged NIfTI file: its header or data cannot be read", None
    m = re.search(r"\b(PNG|JPEG|TIFF|BMP|VTK|GDCM|Bruker|Gipl|HDF5|MRC|Stimulate)ImageIO\b", text)
    if m:
        return f"damaged {m.group(1)} image", None
    detail = scrub(text, limit=120)
    return "damaged file" + (f": {detail}" if detail else ""), None


# the errno texts a write may end with, in the words the C library uses
_OS_REASONS = ("Permission denied", "No space left on device", "No such file or directory",
               "Read-only file system", "Is a directory", "Disk quota exceeded",
               "File name too long", "Not a directory")


def image_write_problem(exc):
    """What failed when ITK could not write an image: ``cannot write (REASON)``
    with the system's reason where ITK gives one."""
    text = str(exc)
    reason = next((r for r in _OS_REASONS if r in text), None)
    return f"cannot write ({reason})" if reason else "cannot write the image file"


def opencv_problem(exc):
    """An OpenCV error (``cv2.error``) in words, without its source file, line
    and function: ``OpenCV: Assertion failed``, or OpenCV's own sentence where
    it has one (``OpenCV: the function is not implemented``)."""
    text = " ".join(str(exc).split())
    # a file OpenCV parses (FileStorage) puts the line and the reason where the
    # function's name goes: "in function 'calib.yaml(5): Missing , between the elements'"
    parsed = re.search(r"\((-?\d+):Parsing error\).*in function '.*?\((\d+)\):\s*([^']*)'", text)
    if parsed:
        return f"OpenCV: parsing error at line {parsed.group(2)}: {scrub(parsed.group(3), 120)}"
    m = re.search(r"\((-?\d+):([^)]*)\)\s*(.*?)(?:\s+in function '[^']*')?\s*$", text)
    if not m:
        return "OpenCV: " + (scrub(text, limit=120) or "error")
    kind, what = m.group(2).strip(), scrub(m.group(3), limit=120)
    if kind == "Assertion failed" or not what:
        # the asserted expression is OpenCV's own code, not something the user can act on
        return f"OpenCV: {kind.lower() or 'error'}"
    return f"OpenCV: {what}"


# -- the libraries' own lines on file descriptor 2 ---------------------------

_quiet_lock = threading.Lock()
_quiet = {"depth": 0, "saved": None, "file": None}


@contextlib.contextmanager
def native_stderr_quiet():
    """Keep what C and C++ code writes to file descriptor 2 during the block
    off the terminal: libpng's ``libpng error: Not enough image data``,
    MetaIO's ``M_ReadElementsData``, HDF5's diagnostics with the build's
    paths, NIfTI's ``** ERROR``. The project reports the failure itself, in
    one line (``FluoInputError``), after the block.

    What was written is logged (logger ``fluoguide.native``, debug level).
    Nested and concurrent blocks share one redirection (the first in starts
    it, the last out ends it); Python's ``sys.stderr`` is flushed before, so
    lines written before the block still reach the terminal. Where file
    descriptor 2 cannot be duplicated the block runs as is.
    """
    with _quiet_lock:
        if _quiet["depth"] == 0:
            try:
                sys.stderr.flush()
            except (AttributeError, OSError, ValueError):
                pass
            try:
                saved = os.dup(2)
            except OSError:
                saved = None
            if saved is not None:
                sink = tempfile.TemporaryFile()
                os.dup2(sink.fileno(), 2)
                _quiet["saved"], _quiet["file"] = saved, sink
        _quiet["depth"] += 1
    try:
        yield
    finally:
        with _quiet_lock:
            _quiet["depth"] -= 1
            if _quiet["depth"] == 0 and _quiet["saved"] is not None:
                try:
                    sys.stderr.flush()     # Python's lines of the block go with the rest
                except (AttributeError, OSError, ValueError):
                    pass
                os.dup2(_quiet["saved"], 2)
                os.close(_quiet["saved"])
                sink = _quiet["file"]
                _quiet["saved"] = _quiet["file"] = None
                sink.seek(0)
                said = sink.read(65536).decode("utf-8", "replace").strip()
                sink.close()
                if said:
                    log.debug("native libraries wrote to stderr: %s", said)
