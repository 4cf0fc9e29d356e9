"""Readable text of a command's result: what ``fluo ...`` prints without ``--json``.

Every handler returns a dict (the JSON result, unchanged by anything here);
:func:`format_result` turns it into short ``key: value`` lines and tables:

- numbers to 4 significant digits, ``-`` for a missing value (JSON null);
- every key carries its unit: keys already named with one (``penetration_depth_mm``,
  ``volume_error_pct``, ``"rms reprojection [px]"``) print as they are, the others
  through :data:`KEYS` (``R_rho`` -> ``reflectance_per_mm2``); ``dimensionless``
  where a quantity has no unit;
- a list of row dicts, or a dict of dicts with the same keys, is a table; a short
  list is printed inline, a long one or a large matrix as its size and range
  (``--json`` gives every value);
- a ``warnings`` list is always printed, after everything else (``warnings: none``
  when it is empty), so a result that may be wrong never looks clean;
- no line is longer than :data:`LINE_WIDTH`: a table cell longer than
  :data:`CELL_WIDTH` is cut (``...``), a table too wide is split into several
  side by side parts, each repeating its first column, and a long ``key: value``
  or warning continues on indented lines.

A command may add its own presentation in :data:`COMMANDS` (columns printed
together as one table, key names that differ from the global ones).  New result
keys of any command print sensibly without an entry here; add one when a key
hides its unit.
"""

from __future__ import annotations

import math
import re
import textwrap

import numpy as np

from fluoguide.errors import one_line
from fluoguide.jsonable import to_jsonable

SIGNIFICANT = 4          # significant digits of every printed number
INLINE_ITEMS = 8         # longer lists are summarised
TABLE_ROWS = 40          # longer tables are cut (the rest: --json)
MATRIX_CELLS = 16        # larger matrices are summarised (4 x 4 transforms print whole)
LINE_WIDTH = 200         # characters of the longest printed line (a terminal or a log)
CELL_WIDTH = 48          # a longer table cell is cut: a table stays a table (all of it: --json)
WRAP_INDENT = "    "     # continuation lines of a wrapped value, under its key

# JSON key -> printed key, for keys whose name does not say their unit or meaning.
KEYS = {
    # fluo analytic / forward: diffusion theory (docs/physics.md sections 1-3)
    "n": "refractive_index_n",
    "Rd": "diffuse_reflectance_Rd",
    "mueff": "mueff_per_mm",
    "D": "diffusion_coefficient_D_mm",
    "A": "boundary_coefficient_A",
    "R_rho": "reflectance_per_mm2",
    "robin_surface_fluence": "robin_surface_fluence_per_mm2",
    "ln_robin_surface_fluence": "ln_robin_surface_fluence [ln of 1/mm^2]",
    "rho_diffusive": "diffusive (dimensionless)",
    "F": "diffuse_fluorescence_F",
    "detector_fluence": "detector_fluence_per_mm2 (per W of source power)",
    "jacobian_mua_norm": "jacobian_mua_norm_per_mm",
    "jacobian_shape": "jacobian_shape (measurements, nodes)",
    # meshes
    "tets": "tetrahedra",
    "forward_mesh": "forward_mesh (nodes, elements)",
    "reconstruction_mesh": "reconstruction_mesh (nodes, elements)",
    # cameras: pixels, and distortion coefficients that have no unit
    "fx": "fx_px", "fy": "fy_px", "cx": "cx_px", "cy": "cy_px",
    "width": "width_px", "height": "height_px", "image": "image_size_px",
    "dist": "distortion_coefficients",
    "axis": "axis (unit vector)", "direction": "direction (unit vector)",
    "exposures_saturated": "exposures_saturated_s",
    "e_per_radiance_s": "electrons_per_s_per_W_per_mm2_sr",
    "spectral_e_per_radiance_s": "electrons_per_s_per_W_per_mm2_sr",
    # studies and reconstructions
    "true_peak": "true_peak_per_mm",
    "peak": "peak_per_mm",
    "residual_ss": "residual_ss (data units^2)",
    "initial_residual_ss": "initial_residual_ss (data units^2)",
    # surface mapping
    "visible_within_5pct": "visible_within_5pct (fraction)",
    "tracking_sd": "tracking_sd (mm, deg)",
    "hand_eye_error": "hand_eye_error (mm, deg)",
    "max_model_error": "max_model_error (fraction)",
}

# Quantities without a unit: printed with "(dimensionless)" after their name.
DIMENSIONLESS = re.compile(
    r"(^|_)(n|Rd|A|F|alpha|lambda|ratio|ratio_mean|ratio_sd|r2|k[1-6]|p[12]|f_number|"
    r"f_numbers|bic|bic_axisymmetric|bic_crescent|transport|transport_median|transport_iqr|"
    r"transport_truth|aspect_ratio_mean|aspect_ratio_max|dynamic_range|lens_exponent|"
    r"quantum_efficiency|filter_transmittance|nonlinearity|asym_amplitude|"
    r"distortion_coefficients|agreement|agreement_binned|agreement_decimated|"
    r"agreement_vs_embree|fraction|clipped_fraction|log_valid_fraction|"
    r"refractive_index_n|diffuse_reflectance_Rd|boundary_coefficient_A|"
    r"diffuse_fluorescence_F|surface_transport_median)$")

# Per command (``"calib handeye"``): ``keys`` override :data:`KEYS`; ``columns``
# lists groups of equal-length lists printed side by side as one table;
# ``group_rows_by`` splits a table into one per value of that column.
COMMANDS = {
    "analytic": {"columns": [("rho_mm", "R_rho", "robin_surface_fluence",
                              "ln_robin_surface_fluence", "rho_diffusive")]},
    "study": {"group_rows_by": "case"},
}

# A key names its unit when it ends in one of these (or holds "[unit]", "%").
_UNIT_SUFFIX = re.compile(
    r"(_|^)(mm|mm2|mm3|per_mm|per_mm2|pct|px|deg|rad|s|ms|seconds|hz|fps|adu|e|e_per_s|"
    r"adu_per_e|w_per_mm2|w_per_mm2_sr|sr|ijk|kji|db|bits|um|nm|mw|w)$")
_UNIT_WORDS = re.compile(r"\[.+\]|%|/s\b|\((dimensionless|fraction|unit vector|per W|data units|"
                         r"4x4|nodes|measurements)|^fps_|_per_")


def has_unit(label):
    """Whether a printed key states its unit or says it has none (the CLI tests hold
    every number of a result to this)."""
    return bool(_UNIT_SUFFIX.search(label) or _UNIT_WORDS.search(label) or "seconds" in label)


def number(v):
    """A number to :data:`SIGNIFICANT` digits (ints whole, NaN and None as ``-``)."""
    if v is None:
        return "-"
    if isinstance(v, bool):
        return "yes" if v else "no"
    if isinstance(v, int):
        return str(v)
    if isinstance(v, float):
        if not math.isfinite(v):
            return "-"
        return f"{v:.{SIGNIFICANT}g}"
    return str(v)


def _scalar(v):
    return v is None or isinstance(v, (bool, int, float, str))


def _numeric_list(v):
    return isinstance(v, list) and all(
        x is None or (isinstance(x, (int, float)) and not isinstance(x, bool)) for x in v)


def _flag_list(v):
    return isinstance(v, list) and len(v) > 0 and all(isinstance(x, bool) for x in v)


def _matrix(v):
    return (isinstance(v, list) and len(v) > 0 and all(_numeric_list(r) and r for r in v)
            and len({len(r) for r in v}) == 1)


def _summary(values):
    a = np.array([np.nan if x is None else x for x in np.ravel(values)], dtype=float)
    ok = a[np.isfinite(a)]
    shape = " x ".join(str(s) for s in np.shape(values))
    if ok.size == 0:
        return f"{shape} values, none finite (all of them: --json)"
    return (f"{shape} values, {number(float(ok.min()))} .. {number(float(ok.max()))}, "
            f"median {number(float(np.median(ok)))} (all of them: --json)")


def _inline(v):
    """One-line text of a value, or None when it needs lines of its own."""
    if _scalar(v):
        return number(v)
    if isinstance(v, (list, dict)) and not v:
        return "none"
    if _numeric_list(v):
        if len(v) <= INLINE_ITEMS:
            return "[" + ", ".join(number(x) for x in v) + "]"
        return _summary(v)
    if isinstance(v, list) and all(isinstance(x, str) for x in v) and len(v) <= INLINE_ITEMS:
        return ", ".join(v)
    if _matrix(v):
        cells = len(v) * len(v[0])
        if cells <= INLINE_ITEMS and len(v) < 3:
            return "[" + ", ".join(_inline(r) for r in v) + "]"
        if cells > MATRIX_CELLS:
            return _summary(v)
    return None


class _Writer:
    def __init__(self, command):
        spec = COMMANDS.get(command, {})
        self.keys = {**KEYS, **spec.get("keys", {})}
        self.columns = spec.get("columns", [])
        self.group_by = spec.get("group_rows_by")
        self.lines = []

    def label(self, key, value=None):
        name = self.keys.get(str(key), str(key))
        if DIMENSIONLESS.search(name) and not has_unit(name):
            name += " (dimensionless)"
        elif _matrix(value) and len(value) == 4 == len(value[0]) and not has_unit(name):
            name += " (4x4, translation in mm)"
        return name

    def emit(self, text, indent):
        # a path or a name holding a newline must not make a line of its own
        line = "  " * indent + one_line(text)
        if len(line) <= LINE_WIDTH:
            self.lines.append(line)
            return
        # a long message or path: continued under its key, cut nowhere (a long
        # word, a path without spaces, is broken where the line ends)
        self.lines += textwrap.wrap(line, width=LINE_WIDTH, subsequent_indent="  " * indent
                                    + WRAP_INDENT, break_on_hyphens=False)

    def _group_columns(self, d):
        """The command's column groups: equal-length lists become one table."""
        for group in self.columns:
            present = [k for k in group if k in d]
            # numbers and yes/no flags side by side (bools are not numeric elsewhere)
            if len(present) > 1 and all(_numeric_list(d[k]) or _flag_list(d[k])
                                        for k in present) and \
                    len({len(d[k]) for k in present}) == 1:
                rows = [{k: d[k][i] for k in present} for i in range(len(d[present[0]]))]
                d = {(_Table(rows) if k == present[0] else k): v for k, v in d.items()
                     if k not in present[1:]}
        return d

    def block(self, d, indent=0):
        """A dict: aligned ``key: value`` lines, nested blocks and tables."""
        d = self._group_columns(dict(d))
        top_warnings = indent == 0 and "warnings" in d
        inline = {k: _inline(v) for k, v in d.items() if not isinstance(k, _Table)}
        width = max((len(self.label(k, d[k])) for k, t in inline.items() if t is not None),
                    default=0)
        for key, value in d.items():
            if isinstance(key, _Table):
                self.table(key.rows, indent)
            elif key == "warnings" and top_warnings:
                continue
            elif inline[key] is not None:
                self.emit(f"{(self.label(key, value) + ':').ljust(width + 1)} {inline[key]}",
                          indent)
            else:
                self.emit(f"{self.label(key, value)}:", indent)
                self.nested(value, indent + 1)
        if top_warnings:
            self.warnings(d["warnings"])

    def nested(self, v, indent):
        if isinstance(v, dict):
            inner = list(v.values())
            if len(inner) > 1 and all(isinstance(x, dict) and x for x in inner) and \
                    all(any(_inline(x) is not None for x in r.values()) for r in inner):
                self.table([{"": k, **r} for k, r in v.items()], indent)
            else:
                self.block(v, indent)
        elif _matrix(v):
            cells = [[number(x) for x in row] for row in v]
            w = max(len(c) for row in cells for c in row)
            for row in cells:
                self.emit("  ".join(c.rjust(w) for c in row), indent)
        elif isinstance(v, list) and v and all(isinstance(x, dict) for x in v):
            self.table(v, indent)
        elif isinstance(v, list):
            for x in v[:TABLE_ROWS]:
                text = _inline(x)
                self.emit(f"- {text}" if text is not None else "-", indent)
                if text is None:
                    self.nested(x, indent + 1)
            if len(v) > TABLE_ROWS:
                self.emit(f"... {len(v) - TABLE_ROWS} more (all of them: --json)", indent)
        else:
            self.emit(number(v), indent)

    def table(self, rows, indent):
        """Rows of dicts as aligned columns; one table per value of the command's
        ``group_rows_by`` column when the rows have it."""
        key = self.group_by
        if key and all(isinstance(r.get(key), str) for r in rows):
            groups = {}
            for r in rows:
                groups.setdefault(r[key], []).append({k: v for k, v in r.items() if k != key})
            if len(groups) < len(rows):
                for name, members in groups.items():
                    self.emit(f"{name}:", indent)
                    self._table(members, indent + 1)
                return
        self._table(rows, indent)

    def _table(self, rows, indent):
        """Rows of dicts as aligned columns.  A column with one value in every row is
        printed once above the table; cells that are not one-liners are left out and
        named below it."""
        cols = []
        for r in rows:
            cols += [k for k in r if k not in cols]
        text = [{k: _cell(_inline(r[k])) if k in r else "" for k in cols} for r in rows]
        hidden = [k for k in cols if k != "" and any(t[k] is None for t in text)]
        cols = [k for k in cols if k not in hidden]
        if len(rows) >= 3:
            same = [k for k in cols if k != "" and len({t[k] for t in text}) == 1
                    and all(k in r for r in rows)]
            if same and len(same) < len(cols):
                self.block({k: rows[0][k] for k in same}, indent)
                cols = [k for k in cols if k not in same]
        shown = text[:TABLE_ROWS]
        heads = ["" if k == "" else _cell(self.label(k, rows[0].get(k))) for k in cols]
        grid = [heads] + [[t[k] for k in cols] for t in shown]
        if len(cols) > 6 and len(cols) > len(shown) + 1:
            # few rows, many columns: one line per column reads better
            grid = [list(r) for r in zip(*grid)]
        widths = [max(len(row[j]) for row in grid) for j in range(len(grid[0]))]
        for i, part in enumerate(_column_parts(widths, LINE_WIDTH - 2 * indent)):
            if i:
                self.emit("", 0)      # a blank line between the parts of a wide table
            for row in grid:
                self.emit("  ".join(row[j].ljust(widths[j]) for j in part).rstrip(), indent)
        if len(rows) > len(shown):
            self.emit(f"... {len(rows) - len(shown)} more rows (all of them: --json)", indent)
        if hidden:
            self.emit(f"(not shown: {', '.join(map(str, hidden))}; all of them: --json)", indent)

    def warnings(self, w):
        if not w:
            self.emit("warnings: none", 0)
            return
        for x in (w if isinstance(w, list) else [w]):
            self.emit(f"warning: {x if isinstance(x, str) else _inline(x) or x}", 0)


def _cell(text):
    """A table cell of at most :data:`CELL_WIDTH` characters (None: not a one-liner)."""
    if text is None or len(text) <= CELL_WIDTH:
        return text
    return text[:CELL_WIDTH - 3] + "..."


def _column_parts(widths, room):
    """Column indices of a table in parts whose lines fit ``room`` characters.

    The first column (the row's name, or the column names of a table printed one
    line per column) opens every part, so each part reads on its own; the others
    are taken in order while the line (two spaces between columns) fits.
    """
    parts, part, used = [], [0], widths[0]
    for j in range(1, len(widths)):
        if len(part) > 1 and used + 2 + widths[j] > room:
            parts.append(part)
            part, used = [0], widths[0]
        part.append(j)
        used += 2 + widths[j]
    parts.append(part)
    return parts


class _Table:
    """Placeholder key of a column group in a block (keeps the group's position)."""

    def __init__(self, rows):
        self.rows = rows


def format_result(result, command=""):
    """Text of a handler's result dict for a terminal (``command``: ``"calib camera"``)."""
    w = _Writer(command)
    data = to_jsonable(result)
    if isinstance(data, dict):
        w.block(data)
    else:
        w.nested(data, 0)
    return "\n".join(w.lines)


def command_name(args):
    """``"calib camera"`` from parsed arguments (group dests are ``<group>_command``)."""
    parts = [getattr(args, "command", None) or ""]
    sub = getattr(args, f"{parts[0]}_command", None)
    if sub:
        parts.append(sub)
    return " ".join(parts)
