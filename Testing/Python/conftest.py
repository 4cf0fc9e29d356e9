import os
from pathlib import Path

# VTK/MRML print warnings straight to stderr; keep test logs readable.
os.environ.setdefault("VTK_LOG_LEVEL", "ERROR")

# Subprocesses (``python -m fluoapp``) import the tree under test, not whatever
# checkout the virtual environment's editable install points at (a git worktree
# shares one .venv with the main checkout).
_ROOT = Path(__file__).resolve().parents[2]
_TREE = [str(_ROOT / p) for p in ("", "FluoCalib", "FluoNav", "FluoTomo")]
os.environ["PYTHONPATH"] = os.pathsep.join(
    _TREE + [p for p in os.environ.get("PYTHONPATH", "").split(os.pathsep) if p and p not in _TREE])
