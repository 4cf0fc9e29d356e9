import os
from pathlib import Path

# Subprocesses (``python -m fluoapp``) import the tree under test, not whatever
# checkout the virtual environment's editable install points at (a git worktree
# shares one .venv with the main checkout).  Same as Testing/Python/conftest.py.
_ROOT = Path(__file__).resolve().parents[3]
_TREE = [str(_ROOT / p) for p in ("", "FluoCalib", "FluoNav", "FluoTomo")]
os.environ["PYTHONPATH"] = os.pathsep.join(
    _TREE + [p for p in os.environ.get("PYTHONPATH", "").split(os.pathsep) if p and p not in _TREE])
