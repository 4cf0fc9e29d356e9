import os

# VTK/MRML print warnings straight to stderr; keep test logs readable.
os.environ.setdefault("VTK_LOG_LEVEL", "ERROR")
