"""The Python packages the modules need inside 3D Slicer, installed on first use.

``slicer_requirements.txt`` (beside this file, shipped by the extension's
CMake) lists them with version ranges, PEP 508 platform markers where a package
has no build for some platforms, and ``# optional: ...`` for the packages the
modules work without (what each adds is said: PARDISO from ``mkl``, the quality
mesher from ``pytetwild``, the Embree ray caster from ``embreex``).
:func:`missing_requirements` says which are not installed in the running
Python; :func:`install_requirements` installs them one by one with
``slicer.util.pip_install`` (one without a wheel for this platform does not stop
the others). The module panels offer the installation inside the panel, not in
a dialog (``fluoguide.slicer_module``); :func:`ensure_dependencies` is the
scripted form. Outside Slicer (pytest, the ``fluo`` CLI, the web app) the
virtual environment of ``pyproject.toml`` has them all and nothing is installed.

Refused whatever the file says (``FORBIDDEN``): vtk, slicer-core, the web-app
stack and packages that pull vtk in; installing them into Slicer's Python
breaks Slicer.
"""

from __future__ import annotations

import logging
import re
from pathlib import Path
from typing import NamedTuple

from fluoguide.errors import FluoInputError

__all__ = ["REQUIREMENTS_FILE", "FORBIDDEN", "Requirement", "requirements", "read_requirements",
           "missing_requirements", "install_requirements", "ensure_dependencies"]

REQUIREMENTS_FILE = Path(__file__).resolve().parent / "slicer_requirements.txt"
#: Distributions never installed into Slicer's Python (normalised names).
FORBIDDEN = frozenset({"vtk", "slicer-core", "slicer-layer-dm", "trame", "trame-slicer",
                       "trame-client", "trame-server", "trame-vuetify", "trame-rca", "pyvista",
                       "wslink"})

_NAME = re.compile(r"^([A-Za-z0-9][A-Za-z0-9._-]*)")

log = logging.getLogger("fluoguide.slicer")


def _normalise(name):
    return re.sub(r"[-_.]+", "-", name).lower()


class Requirement(NamedTuple):
    """One line of ``slicer_requirements.txt``.

    ``spec``: the requirement without its marker (``mkl>=2023``); ``marker``:
    its PEP 508 environment marker or None; ``optional``: what the package adds
    when it is optional (``# optional: ...`` after the line), None when the
    modules need it."""
    name: str
    spec: str
    marker: str | None
    optional: str | None
    line: str


def requirements(path=REQUIREMENTS_FILE):
    """Every requirement of a requirements file (:class:`Requirement`).

    Raises FluoInputError for a line that is not a plain requirement or that
    names a forbidden distribution.
    """
    path = Path(path)
    out = []
    for lineno, raw in enumerate(path.read_text().splitlines(), 1):
        line, _, comment = raw.partition("#")
        line = line.strip()
        if not line:
            continue
        m = _NAME.match(line)
        if m is None or line.startswith("-"):
            raise FluoInputError(f"line {lineno} is not a requirement", file=path, value=raw)
        name = _normalise(m.group(1))
        if name in FORBIDDEN:
            raise FluoInputError(f"line {lineno}: {name} must never be installed into "
                                 "Slicer's Python", file=path, value=raw)
        spec, _, marker = line.partition(";")
        comment = comment.strip()
        optional = comment[len("optional:"):].strip() if comment.startswith("optional:") else None
        out.append(Requirement(name, spec.strip(), marker.strip() or None, optional or None,
                               line))
    return out


def read_requirements(path=REQUIREMENTS_FILE):
    """[(distribution name, requirement without its marker)] of a requirements file."""
    return [(r.name, r.spec) for r in requirements(path)]


def applies_here(req):
    """Whether a requirement's marker holds for this Python and platform (a
    marker that cannot be evaluated here counts as holding: pip decides)."""
    if req.marker is None:
        return True
    try:
        from packaging.markers import Marker
    except ImportError:
        try:
            from pip._vendor.packaging.markers import Marker
        except ImportError:
            return True
    return bool(Marker(req.marker).evaluate())


def _installed(name):
    from importlib import metadata

    try:
        metadata.distribution(name)
    except metadata.PackageNotFoundError:
        return False
    return True


def missing_requirements(path=REQUIREMENTS_FILE, optional=True):
    """Requirement lines (with their markers) not installed in this Python, of
    those whose marker holds here; ``optional=False`` leaves out the optional ones."""
    return [r.line for r in requirements(path)
            if applies_here(r) and (optional or r.optional is None) and not _installed(r.name)]


def install_requirements(lines, pip_install):
    """Install requirement ``lines`` one by one with ``pip_install(line)`` (Slicer's
    ``slicer.util.pip_install``): a package that fails (no wheel for this platform,
    no network) does not stop the others. Returns {line: None or the error text}."""
    out = {}
    for line in lines:
        try:
            pip_install(line)
            out[line] = None
        except Exception as exc:  # pip's failure is reported per package, not raised
            last = (str(exc).strip().splitlines() or [""])[-1]
            out[line] = f"{type(exc).__name__}: {last}"
    return out


def install_summary(path=REQUIREMENTS_FILE):
    """What this Python lacks, in words: (missing required lines, [(missing
    optional line, what it adds)])."""
    reqs = [r for r in requirements(path) if applies_here(r) and not _installed(r.name)]
    return ([r.line for r in reqs if r.optional is None],
            [(r.line, r.optional) for r in reqs if r.optional is not None])


def ensure_dependencies(ask=True, path=REQUIREMENTS_FILE):
    """Install the missing requirements into Slicer's Python, each on its own;
    True when every required one is there (an optional one may fail: what it
    adds is then unavailable, and said).

    ``ask``: show Slicer's OK/Cancel dialog first (modal: for a script or a
    test; the module panels offer the installation in the panel instead,
    ``slicer_module``). Outside the Slicer application this only reports: it
    never runs pip in someone's virtual environment.
    """
    required, optional = install_summary(path)
    missing = required + [line for line, _ in optional]
    if not missing:
        return True
    from fluoguide.slicer_compat import in_slicer_application

    if not in_slicer_application():
        log.warning("FluoGuide needs these Python packages: %s", ", ".join(missing))
        return not required
    import slicer

    if ask and not slicer.util.confirmOkCancelDisplay(
            "FluoGuide needs these Python packages, which this Slicer does not have yet:\n\n"
            + "\n".join(missing) + "\n\nInstall them now (a few minutes; needs the internet)?",
            windowTitle="FluoGuide: install Python packages"):
        return False
    with slicer.util.WaitCursor():
        failed = {k: v for k, v in install_requirements(missing, slicer.util.pip_install).items()
                  if v is not None}
    required_left, optional_left = install_summary(path)
    if failed:
        log.warning("FluoGuide: could not install %s", "; ".join(f"{k} ({v})"
                                                                 for k, v in failed.items()))
    if required_left:
        slicer.util.errorDisplay("Could not install: " + ", ".join(required_left))
        return False
    return True
