"""The Python packages the modules need inside 3D Slicer, installed on first use.

``slicer_requirements.txt`` (beside this file, shipped by the extension's
CMake) lists them with version ranges. :func:`missing_requirements` says which
are not installed in the running Python; :func:`ensure_dependencies` asks the
user and installs those with ``slicer.util.pip_install``. Outside Slicer
(pytest, the ``fluo`` CLI, the web app) the virtual environment of
``pyproject.toml`` has them all and nothing is installed.

Refused whatever the file says (``FORBIDDEN``): vtk, slicer-core, the web-app
stack and packages that pull vtk in; installing them into Slicer's Python
breaks Slicer.
"""

from __future__ import annotations

import logging
import re
from pathlib import Path

from fluoguide.errors import FluoInputError

__all__ = ["REQUIREMENTS_FILE", "FORBIDDEN", "read_requirements", "missing_requirements",
           "ensure_dependencies"]

REQUIREMENTS_FILE = Path(__file__).resolve().parent / "slicer_requirements.txt"
#: Distributions never installed into Slicer's Python (normalised names).
FORBIDDEN = frozenset({"vtk", "slicer-core", "slicer-layer-dm", "trame", "trame-slicer",
                       "trame-client", "trame-server", "trame-vuetify", "trame-rca", "pyvista",
                       "wslink"})

_NAME = re.compile(r"^([A-Za-z0-9][A-Za-z0-9._-]*)")

log = logging.getLogger("fluoguide.slicer")


def _normalise(name):
    return re.sub(r"[-_.]+", "-", name).lower()


def read_requirements(path=REQUIREMENTS_FILE):
    """[(distribution name, full requirement line)] of a requirements file.

    Raises FluoInputError for a line that is not a plain requirement or that
    names a forbidden distribution.
    """
    path = Path(path)
    out = []
    for lineno, raw in enumerate(path.read_text().splitlines(), 1):
        line = raw.split("#", 1)[0].strip()
        if not line:
            continue
        m = _NAME.match(line)
        if m is None or line.startswith("-"):
            raise FluoInputError(f"line {lineno} is not a requirement", file=path, value=raw)
        name = _normalise(m.group(1))
        if name in FORBIDDEN:
            raise FluoInputError(f"line {lineno}: {name} must never be installed into "
                                 "Slicer's Python", file=path, value=raw)
        out.append((name, line))
    return out


def missing_requirements(path=REQUIREMENTS_FILE):
    """Requirement lines whose distribution is not installed in this Python."""
    from importlib import metadata

    missing = []
    for name, line in read_requirements(path):
        try:
            metadata.distribution(name)
        except metadata.PackageNotFoundError:
            missing.append(line)
    return missing


def ensure_dependencies(ask=True, path=REQUIREMENTS_FILE):
    """Install the missing requirements into Slicer's Python; True when all are there.

    ``ask``: show Slicer's OK/Cancel dialog first (the user may decline; then
    False and nothing is installed). Outside the Slicer application this only
    reports: it never runs pip in someone's virtual environment.
    """
    missing = missing_requirements(path)
    if not missing:
        return True
    from fluoguide.slicer_compat import in_slicer_application

    if not in_slicer_application():
        log.warning("FluoGuide needs these Python packages: %s", ", ".join(missing))
        return False
    import slicer

    if ask and not slicer.util.confirmOkCancelDisplay(
            "FluoGuide needs these Python packages, which this Slicer does not have yet:\n\n"
            + "\n".join(missing) + "\n\nInstall them now (a few minutes; needs the internet)?",
            windowTitle="FluoGuide: install Python packages"):
        return False
    with slicer.util.WaitCursor():
        slicer.util.pip_install(missing)
    still = missing_requirements(path)
    if still:
        slicer.util.errorDisplay("Could not install: " + ", ".join(still))
        return False
    return True

