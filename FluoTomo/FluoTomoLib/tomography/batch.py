"""Many own scenes at once: a batch file of (label map, optics, acquisition)
triples reconstructed on the run engine, one task per case.

A batch file is a CSV with a header, or a JSON / YAML mapping whose ``cases``
is a list of rows (plus optional ``methods``, ``lambda``, ``accuracy``
defaults for every row). One row per case::

    # lines starting with '#' are comments
    name,labels,optics,acquisition,methods,target,truth
    p01,p01/labels.nrrd,optics.json,p01/acq,"NP,SP,HP",7,0.0026
    p02,p02/labels.nrrd,optics.json,p02/acq,HP,,

Paths are relative to the batch file's folder and must stay inside it (the
batch file names its data the way an acquisition.json does). Every row is
checked, and every input read, before any work: a typo in row 180 is refused
at once, not after hours.

Each task (:func:`reconstruct_case`) reconstructs every method of its case on
ONE model (one mesh, one Jacobian: ``reconstruct_labelmap_methods``) and
returns the case's row plus plain arrays (a float32 yield volume per method,
the grid, each method's summary as JSON text): a mesh carries caches a worker
cannot send back. :func:`write_case_outputs` turns the arrays into
``cases/NAME/METHOD/yield.nrrd`` + ``reconstruction.json`` in this process.
"""

from __future__ import annotations

import csv
import hashlib
import io
import json
import math
import re
from pathlib import Path
from types import SimpleNamespace

import numpy as np

from fluoguide.errors import FluoInputError

#: the columns (keys) a batch row may have; the first three are required
COLUMNS = ("labels", "optics", "acquisition", "name", "methods", "lambda", "accuracy", "target",
           "truth")
REQUIRED = COLUMNS[:3]
#: keys of a JSON/YAML batch file besides ``cases``: defaults for every row
FILE_DEFAULTS = ("methods", "lambda", "accuracy")
METHODS = ("NP", "SP", "HP")
#: a case name is a folder name (cases/NAME/): no separators, no leading dot
_NAME = re.compile(r"^[A-Za-z0-9][A-Za-z0-9._-]{0,63}$")


# ----------------------------------------------------------------- the batch file
def _read_rows(path):
    """(rows, defaults, where) of a batch file: rows as dicts of raw values and
    ``where(i)`` naming row i for messages (CSV: its line)."""
    from fluoguide.runs.grid import load_study_file, read_small_text

    p = Path(path)
    suffix = p.suffix.lower()
    if suffix in (".json", ".yaml", ".yml"):
        doc = load_study_file(p, "batch file")
        unknown = [k for k in doc if k not in ("cases",) + FILE_DEFAULTS]
        if unknown:
            raise FluoInputError(f"unknown key (expected cases, {', '.join(FILE_DEFAULTS)})",
                                 file=p, field=unknown[0])
        rows = doc.get("cases")
        if not isinstance(rows, list) or not rows:
            raise FluoInputError("expected 'cases': a list of rows (labels, optics, "
                                 "acquisition, ...)", file=p, field="cases",
                                 value=type(rows).__name__)
        for i, r in enumerate(rows):
            if not isinstance(r, dict):
                raise FluoInputError("a case is a mapping of column: value", file=p,
                                     field=f"cases[{i}]", value=type(r).__name__)
        return rows, {k: doc[k] for k in FILE_DEFAULTS if k in doc}, lambda i: f"cases[{i}]"
    if suffix != ".csv":
        raise FluoInputError("a batch file ends in .csv, .json, .yaml or .yml", file=p,
                             value=p.suffix)
    text = read_small_text(p, "batch file", encoding="utf-8-sig")     # a spreadsheet's BOM
    try:
        table = list(csv.reader(io.StringIO(text)))
    except csv.Error as exc:
        raise FluoInputError(f"not a CSV file ({exc})", file=p) from None
    # blank lines and comment lines (first cell starting with '#') are not rows
    lines = [(n + 1, r) for n, r in enumerate(table)
             if any(c.strip() for c in r) and not r[0].lstrip().startswith("#")]
    if not lines:
        raise FluoInputError("the batch file is empty (expected a header and one row per case)",
                             file=p)
    header = [c.strip().lower() for c in lines[0][1]]
    for c in header:
        if c not in COLUMNS:
            raise FluoInputError(f"unknown column (expected {', '.join(COLUMNS)})", file=p,
                                 field="header", value=c)
    if len(set(header)) != len(header):
        raise FluoInputError("a column is named twice", file=p, field="header",
                             value=next(c for c in header if header.count(c) > 1))
    rows, line_of = [], []
    for n, r in lines[1:]:
        if len(r) > len(header):
            raise FluoInputError(f"{len(r)} values under {len(header)} columns", file=p,
                                 field=f"line {n}", value=",".join(r))
        rows.append({c: v.strip() for c, v in zip(header, r) if v.strip() != ""})
        line_of.append(n)
    if not rows:
        raise FluoInputError("the batch file has a header but no cases", file=p)
    return rows, {}, lambda i: f"line {line_of[i]}"


def _methods(value, file, field):
    items = value if isinstance(value, (list, tuple)) else str(value).split(",")
    out = []
    for m in items:
        m = str(m).strip().upper()
        if m not in METHODS:
            raise FluoInputError("methods are NP, SP and HP (comma-separated)", file=file,
                                 field=field, value=value)
        if m in out:
            raise FluoInputError("a method is named twice", file=file, field=field, value=value)
        out.append(m)
    if not out:
        raise FluoInputError("expected one or more of NP, SP, HP", file=file, field=field,
                             value=value)
    return out


def check_settings(methods=None, lam=None, accuracy=None, file=None, where=""):
    """The methods (list), lambda (float or None) and accuracy of a case,
    checked; ``where`` prefixes the field names in messages."""
    from fluoguide.runs.grid import convert
    from FluoTomoLib.tomography.accuracy import DEFAULT, LEVELS
    from FluoTomoLib.tomography.reconstruct import MAX_LAMBDA

    out_methods = list(METHODS) if methods is None else _methods(methods, file, where + "methods")
    if lam is not None:
        lam = convert(lam, where + "lambda", float, file)
        if not 0 < lam <= MAX_LAMBDA:
            raise FluoInputError(f"lambda must be in (0, {MAX_LAMBDA:g}]", file=file,
                                 field=where + "lambda", value=lam)
    accuracy = DEFAULT if accuracy is None else str(accuracy).strip()
    if accuracy not in LEVELS:
        raise FluoInputError(f"accuracy must be one of {', '.join(LEVELS)}", file=file,
                             field=where + "accuracy", value=accuracy)
    return out_methods, lam, accuracy


def _digest(path):
    """SHA-1 of a file's bytes, or of a folder's files (names and bytes, sorted),
    so a resumed run recomputes a case whose inputs changed under the same name."""
    p = Path(path)
    h = hashlib.sha1()
    files = [p] if p.is_file() else sorted(q for q in p.rglob("*") if q.is_file())
    for f in files:
        h.update(str(f.relative_to(p) if f != p else f.name).encode() + b"\0")
        with open(f, "rb") as fh:
            for chunk in iter(lambda: fh.read(1 << 20), b""):
                h.update(chunk)
    return h.hexdigest()[:16]


def load_batch(path, methods=None, lam=None, accuracy=None):
    """Every case of a batch file, checked and with its inputs read once.

    Parameters
    ----------
    path : path
        The batch file (.csv with a header, .json, .yaml, .yml).
    methods, lam, accuracy :
        Values for the rows that leave the field empty (the command line's);
        None: a JSON/YAML file's own default, else methods "NP,SP,HP", lambda
        10 (the reconstruction's), accuracy "balanced".

    Returns
    -------
    list of dict
        One task-parameter dict per case, in file order: ``name``, absolute
        ``labels``, ``optics``, ``acquisition``, ``methods`` ("NP,SP,HP"),
        ``lambda`` (None: the reconstruction's default), ``accuracy``,
        ``target`` (the label graded: given, or the label map's default),
        ``truth`` (1/mm or None) and ``inputs_sha1`` (of the three inputs).

    Raises
    ------
    FluoInputError
        Naming the batch file, the row and field, and the value: a missing or
        unknown column, a path outside the batch file's folder or not there,
        an input that does not read, an unknown method or accuracy, a target
        not in the label map, a bad truth, a duplicate name.
    """
    from fluoguide.runs.grid import MAX_TASKS

    p = Path(path)
    rows, file_defaults, where = _read_rows(p)
    if len(rows) > MAX_TASKS:
        raise FluoInputError(f"the batch has {len(rows)} cases; at most {MAX_TASKS} in one run",
                             file=p, value=len(rows))
    check_settings(methods, lam, accuracy, where="--")      # the command line's, named so
    # a row's own value, else the command line's, else the file's default
    defaults = check_settings(*(file_defaults.get(k) if v is None else v for k, v in (
        ("methods", methods), ("lambda", lam), ("accuracy", accuracy))), file=p)
    seen_maps, seen_optics, digests = {}, {}, {}
    cases = [_batch_case(p, row, where(i), defaults, seen_maps, seen_optics, digests)
             for i, row in enumerate(rows)]
    _name_cases(cases, p)
    return cases


def _batch_case(p, row, at, defaults, seen_maps, seen_optics, digests):
    """One row of batch file ``p`` (named ``at`` in messages) checked, its inputs
    read, as the case's task-parameter dict (:func:`load_batch`'s, plus ``_derived``
    and ``_at`` for :func:`_name_cases`).  ``defaults``: the (methods, lambda,
    accuracy) of a row that leaves them empty; ``seen_maps``, ``seen_optics``,
    ``digests``: what earlier rows read and hashed, updated."""
    from fluoguide.runs.grid import convert

    _check_columns(p, row, at)
    lab_path = _case_path(p, row, at, "labels", "file")
    opt_path = _case_path(p, row, at, "optics", "file")
    acq_path = _case_path(p, row, at, "acquisition", "folder")
    labels, default_target = _read_case_inputs(p, at, lab_path, opt_path, acq_path, seen_maps,
                                               seen_optics)
    m, lam_i, acc = check_settings(row.get("methods", ",".join(defaults[0])),
                                   row.get("lambda", defaults[1]),
                                   row.get("accuracy", defaults[2]), file=p, where=f"{at}, ")
    target = _case_target(p, row, at, labels, default_target)
    truth = None
    if row.get("truth") is not None:
        truth = convert(row["truth"], f"{at}, truth", float, p)
        if not 0 < truth < 1e3:
            raise FluoInputError("the true yield is a positive number [1/mm]", file=p,
                                 field=f"{at}, truth", value=truth)
    name = row.get("name")
    if name is not None and not _NAME.match(str(name)):
        raise FluoInputError("a case name is 1-64 letters, digits, '.', '_' or '-' (it "
                             "names a folder)", file=p, field=f"{at}, name", value=name)
    # an acquisition.json names its data files inside its folder: hash the folder
    hashed = (lab_path, opt_path, acq_path.parent if acq_path.is_file() else acq_path)
    for q in hashed:
        if q not in digests:
            digests[q] = _digest(q)
    sha = hashlib.sha1("".join(digests[q] for q in hashed).encode()).hexdigest()[:16]
    lab_abs, opt_abs, acq_abs = (q.resolve() for q in (lab_path, opt_path, acq_path))
    return {"name": None if name is None else str(name), "_derived": _derived(
        lab_abs, acq_abs), "_at": at, "labels": str(lab_abs), "optics": str(opt_abs),
        "acquisition": str(acq_abs), "methods": ",".join(m), "lambda": lam_i,
        "accuracy": acc, "target": target, "truth": truth, "inputs_sha1": sha}


def _check_columns(p, row, at):
    """Refuse a row with a column not in COLUMNS or one of REQUIRED empty."""
    for k in row:
        if k not in COLUMNS:
            raise FluoInputError(f"unknown column (expected {', '.join(COLUMNS)})", file=p,
                                 field=f"{at}, {k}")
    for k in REQUIRED:
        if row.get(k) in (None, ""):
            raise FluoInputError("missing (every case names its labels, optics and "
                                 "acquisition)", file=p, field=f"{at}, {k}")


def _case_path(p, row, at, key, kind):
    """The path in column ``key`` of a row, inside the batch file's folder and there
    (``kind`` "file" or "folder"; an acquisition: a folder or a .json file)."""
    from fluoguide.paths import inside

    # as given (beside the batch file as the user named it): the readers'
    # messages name it so; the case records hold the resolved path
    q = inside(p.parent, row[key], file=p, field=f"{at}, {key}", what=kind,
               root_name="the batch file's folder", given=True)
    ok = q.is_dir() if kind == "folder" else q.is_file()
    if key == "acquisition":
        ok = q.is_dir() or (q.is_file() and q.suffix.lower() == ".json")
    if not ok:
        raise FluoInputError(f"{kind} not found", file=p, field=f"{at}, {key}",
                             value=str(row[key]))
    return q


def _case_read(p, at, key, read, q):
    """``read(q)``, its FluoInputError naming the batch file, the row and ``key``."""
    try:
        return read(q)
    except FluoInputError as exc:
        raise FluoInputError(str(exc), file=p, field=f"{at}, {key}") from None


def _read_case_inputs(p, at, lab_path, opt_path, acq_path, seen_maps, seen_optics):
    """A row's label map, optics and acquisition read and checked against each
    other (a label map or optics read by an earlier row is not read again: the
    maps kept in ``seen_maps``, the optics in ``seen_optics``).  Returns (the
    label map's labels, its default target)."""
    from FluoTomoLib.tomography.acquisition_file import read_acquisition
    from FluoTomoLib.tomography.labelmap import LabelMap
    from FluoTomoLib.tomography.optics_file import read_optics

    if lab_path not in seen_maps:
        lm = _case_read(p, at, "labels", LabelMap.from_file, lab_path)
        seen_maps.clear()                                   # the last map only
        seen_maps[lab_path] = (lm, lm.labels, lm.default_target())
    lm, labels, default_target = seen_maps[lab_path]
    if opt_path not in seen_optics:
        seen_optics[opt_path] = _case_read(p, at, "optics", read_optics, opt_path)
    optics = seen_optics[opt_path]
    try:
        optics.check_labels(labels)
    except FluoInputError as exc:
        raise FluoInputError(str(exc), file=p, field=f"{at}, optics") from None
    _case_read(p, at, "acquisition", lambda q: read_acquisition(q, labelmap=lm, optics=optics),
               acq_path)
    return labels, default_target


def _case_target(p, row, at, labels, default_target):
    """The label a row grades: its own (in ``labels``), else the label map's default
    (refused when the map has one tissue label)."""
    from fluoguide.runs.grid import convert

    if row.get("target") is not None:
        target = convert(row["target"], f"{at}, target", int, p)
        if target not in labels:
            raise FluoInputError(f"target label is not in the label map (labels {labels})",
                                 file=p, field=f"{at}, target", value=target)
    elif default_target is None:
        raise FluoInputError("the label map has one tissue label: name the target label "
                             "to grade", file=p, field=f"{at}, target")
    else:
        target = int(default_target)
    return target


def _derived(lab_path, acq_path):
    stem = lab_path.name.split(".")[0]
    text = f"{stem}-{acq_path.stem if acq_path.is_file() else acq_path.name}"
    text = re.sub(r"[^A-Za-z0-9._-]+", "_", text).lstrip("._-") or "case"
    return text[:56]


def _name_cases(cases, file):
    """Refuse duplicate given names; give every unnamed case a unique derived one."""
    given = {}
    for c in cases:
        if c["name"] is not None:
            if c["name"] in given:
                raise FluoInputError(f"duplicate case name (also {given[c['name']]})", file=file,
                                     field=f"{c['_at']}, name", value=c["name"])
            given[c["name"]] = c["_at"]
    taken = set(given)
    for c in cases:
        if c["name"] is None:
            name, k = c["_derived"], 2
            while name in taken:
                name, k = f"{c['_derived']}-{k}", k + 1
            c["name"] = name
            taken.add(name)
    for c in cases:
        del c["_derived"], c["_at"]


# ----------------------------------------------------------------- one case
def reconstruct_case(params):
    """The task of one case (module level: a Dask worker imports it by name).

    Reads the three inputs, runs every method of the case on one model and
    returns the row: mesh nodes, measurements, the target label's centroid,
    and per method M the target region's mean yield ``M_yield_per_mm``, the
    peak ``M_peak_per_mm``, the half-maximum centroid ``M_centroid_ras_mm``,
    with ``truth``: ``M_error_pct`` and ``M_centroid_error_mm`` (to the target
    label's centroid), ``M_iterations``, ``M_warnings_n`` and ``M_warnings``
    (text, " | " between), ``M_seconds``; and ``arrays``: ``yield_M`` (float32,
    K x J x I on the label map's grid), ``summary_M`` (the method's summary as
    JSON text), ``spacing_mm``, ``origin_mm``, ``direction``.
    """
    from fluoguide.jsonable import dumps
    from FluoTomoLib.tomography.acquisition_file import read_acquisition
    from FluoTomoLib.tomography.labelmap import LabelMap
    from FluoTomoLib.tomography.optics_file import read_optics
    from FluoTomoLib.tomography.reconstruct import reconstruct_labelmap_methods

    lm = LabelMap.from_file(params["labels"])
    optics = read_optics(params["optics"])
    acq = read_acquisition(params["acquisition"], labelmap=lm, optics=optics)
    methods = params["methods"].split(",")
    target = int(params["target"])
    out = reconstruct_labelmap_methods(lm, optics, acq, methods, lam=params["lambda"],
                                       target=target, accuracy=params["accuracy"])
    truth = params.get("truth")
    first = out[methods[0]]["summary"]
    label_centroid = first["target_label_centroid_ras_mm"]
    row = {"mesh_nodes": first["mesh"]["nodes"], "measurements": first["measurements"],
           "target_label_centroid_ras_mm": label_centroid}
    arrays = {"spacing_mm": np.asarray(lm.spacing_mm, float),
              "origin_mm": np.asarray(lm.origin_mm, float),
              "direction": np.asarray(lm.direction, float)}
    for m in methods:
        s = out[m]["summary"]
        mean = s["regions"][str(target)]["yield_per_mm"]
        cen = s["target_centroid_ras_mm"]
        row[f"{m}_yield_per_mm"] = mean
        row[f"{m}_peak_per_mm"] = s["peak_yield_per_mm"]
        row[f"{m}_centroid_ras_mm"] = cen
        if truth is not None:
            row[f"{m}_error_pct"] = 100.0 * (mean - truth) / truth
            row[f"{m}_centroid_error_mm"] = (None if cen is None else float(
                np.linalg.norm(np.subtract(cen, label_centroid))))
        row[f"{m}_iterations"] = s["solver"]["iterations"]
        row[f"{m}_warnings_n"] = len(s["warnings"])
        row[f"{m}_warnings"] = " | ".join(s["warnings"])
        row[f"{m}_seconds"] = s["seconds"]
        arrays[f"yield_{m}"] = np.asarray(out[m]["yield_kji"], np.float32)
        arrays[f"summary_{m}"] = np.array(dumps(s))
    row["arrays"] = arrays
    return row


# ----------------------------------------------------------------- the run
def batch_tasks(cases):
    """One :class:`fluoguide.runs.Task` per case (parameters: the case's dict)."""
    from fluoguide.runs.tasks import Task

    return [Task(reconstruct_case, dict(c)) for c in cases]


def case_warnings(record):
    """A finished case's warnings, each once, prefixed with the case name (and
    the methods when not every method gave it)."""
    params, res = record["params"], record.get("result") or {}
    name, methods = params["name"], params["methods"].split(",")
    if record["status"] != "ok":
        return [f"{name}: failed: {record.get('error')}"]
    seen = {}
    for m in methods:
        text = res.get(f"{m}_warnings") or ""
        for w in (text.split(" | ") if text else []):
            seen.setdefault(w, []).append(m)
    return [f"{name}: {w}" if len(ms) == len(methods) else f"{name}, {'/'.join(ms)}: {w}"
            for w, ms in seen.items()]


def write_case_outputs(out_dir, records, arrays_of):
    """``out_dir/cases/NAME/METHOD/yield.nrrd`` + ``reconstruction.json`` of every
    ok case (computed now or resumed), from its arrays.  Returns the folders."""
    from FluoTomoLib.tomography.reconstruct import write_reconstruction

    folders = []
    for rec in records:
        if rec["status"] != "ok":
            continue
        arrays = arrays_of(rec)
        grid = SimpleNamespace(spacing_mm=arrays["spacing_mm"], origin_mm=arrays["origin_mm"],
                               direction=arrays["direction"])
        for m in rec["params"]["methods"].split(","):
            folder = Path(out_dir) / "cases" / rec["params"]["name"] / m
            summary = json.loads(str(arrays[f"summary_{m}"]))
            write_reconstruction(folder, grid, {"summary": summary,
                                                "yield_kji": arrays[f"yield_{m}"]})
            folders.append(str(folder))
    return folders


def run_batch(cases, out_dir, executor=None, threads=1, resume=False, progress=None,
              cancel=None, label="tomo batch"):
    """Reconstruct every case on the run engine and write the run folder.

    Parameters
    ----------
    cases : list of dict
        From :func:`load_batch`.
    out_dir : path
        ``table.csv`` and ``tasks/`` (the run engine's), ``cases/NAME/METHOD/``.
    executor, threads, resume, progress, cancel :
        As :func:`fluoguide.runs.engine.run_tasks` (``resume`` reuses the
        finished cases of a killed run in ``out_dir``).

    Returns
    -------
    dict
        The run's counts (``tasks``, ``computed``, ``reused``, ``failures``),
        ``rows`` (table order), ``failed``, ``outputs`` (case folders) and
        ``warnings`` (every case's, prefixed with its name; a line per failed
        case), executor and timings.
    """
    from fluoguide.runs.engine import run_tasks
    from fluoguide.runs.store import RunStore

    store = RunStore(out_dir, resume=resume)
    out = run_tasks(batch_tasks(cases), store=store, executor=executor, threads=threads,
                    progress=progress, cancel=cancel, label=label)
    records = out.pop("records")
    out["outputs"] = write_case_outputs(out_dir, records, store.arrays)
    out["warnings"] = [w for rec in records for w in case_warnings(rec)]
    if out["failures"]:
        out["warnings"].append(f"{out['failures']} of {out['tasks']} cases failed: their rows "
                               "have status 'failed' and the error")
    out["table"] = str(store.table_path)
    for r in out["rows"]:           # NaN-free rows for the JSON (the table keeps its text)
        for k, v in r.items():
            if isinstance(v, float) and not math.isfinite(v):
                r[k] = None
    return out
