"""The main job: ``fluo demo``, end to end on the digital phantoms.

Stages run in order; each one records its numbers in ``metrics.json`` and its
figures in the output folder as soon as it finishes, so a stage that fails
stops the demo with a clear message and keeps everything earlier stages made.
``report.html`` is written at the end (also after a failure) from what exists.
"""

from __future__ import annotations

import html
import time
import traceback
from dataclasses import dataclass, field
from pathlib import Path

from fluoguide import atomic
from fluoguide.errors import FluoError, FluoInputError, check_number
from fluoguide.progress import check_cancel, report, scaled


# The stages in the order they run: name, title, and the stages whose results
# (``ctx.state``) it needs; ``--only`` runs those first.  Functions:
# stages.py:STAGE_FUNCTIONS (imported only when the demo runs: the CLI reads
# this table at start-up).
STAGE_TABLE = [
    ("phantoms", "digital phantoms", ()),
    ("camera_calibration", "camera and hand-eye calibration", ("phantoms",)),
    ("light_calibration", "radiometric, illumination and laser calibration", ("phantoms",)),
    ("surface_mapping", "tracked views and surface-flux mapping", ()),
    ("tomography", "tracked acquisition and reconstruction", ("phantoms",)),
    ("tomography_mc", "the tube reconstructed from Monte Carlo data", ()),
    ("oral_tomography", "oral-cavity acquisition and reconstruction", ("phantoms",)),
]
STAGE_NAMES = [name for name, _, _ in STAGE_TABLE]


def stages_to_run(only):
    """Names of the stages ``only`` asks for plus those they need, in run order
    (every stage for None); FluoInputError naming an unknown stage."""
    if only is None:
        return list(STAGE_NAMES)
    asked = [s.strip() for s in only if s.strip()]
    if not asked:
        raise FluoInputError(f"name at least one stage ({', '.join(STAGE_NAMES)})",
                             field="--only", value=",".join(only))
    needs = {name: deps for name, _, deps in STAGE_TABLE}
    for s in asked:
        if s not in needs:
            raise FluoInputError(f"unknown stage (stages: {', '.join(STAGE_NAMES)})",
                                 field="--only", value=s)
    wanted, todo = set(), list(asked)
    while todo:
        s = todo.pop()
        if s not in wanted:
            wanted.add(s)
            todo += needs[s]
    return [s for s in STAGE_NAMES if s in wanted]


@dataclass
class DemoContext:
    out: Path
    quick: bool = False
    seed: int = 0
    metrics: dict = field(default_factory=dict)
    figures: list = field(default_factory=list)   # (stage, file name, caption)
    notes: list = field(default_factory=list)     # (stage, text)
    state: dict = field(default_factory=dict)     # objects handed between stages
    progress: object = None                       # progress(fraction, message) of the running stage
    cancel: object = None                         # CancelToken of the whole demo
    # the tomography cases' run engine (fluoguide.runs): None = serial here;
    # BLAS/OpenMP threads per case (None: the process's); reuse finished cases
    executor: object = None
    threads: int | None = None
    resume: bool = False
    # options of the tube cases (FluoTomoLogic.tomographyCaseTasks) over the
    # mode's own: a test's coarser tube, say
    case_options: dict = field(default_factory=dict)

    def figure(self, stage, name, caption):
        self.figures.append((stage, name, caption))

    def note(self, stage, text):
        self.notes.append((stage, text))


def _write_json_atomic(path, data):
    from fluoapp.cli import dumps

    atomic.write_text(path, dumps(data))


def _stages():
    """(name, title, function) of every stage, in run order."""
    from fluoapp.demo.stages import STAGE_FUNCTIONS

    return [(name, title, STAGE_FUNCTIONS[name]) for name, title, _ in STAGE_TABLE]


def run_demo(out_dir, quick=False, seed=0, progress=None, cancel=None, only=None,
             executor=None, threads=None, resume=False, case_options=None):
    """Run the demo stages into ``out_dir``; returns the metrics dict.

    ``only``: stage names (:data:`STAGE_NAMES`) to run, with the stages they need.
    ``executor``, ``threads``: where the tomography cases run (one
    ``fluoguide.runs`` task per tube depth and one for the oral cavity; default
    serial in this process) and the library threads of each; ``resume``: reuse
    the cases an earlier (killed) demo finished in ``out_dir/runs``.
    ``case_options``: options of the tube cases over the mode's own
    (``FluoTomoLogic.tomographyCaseTasks``: ``fine_mm``, ``n_sources``, ...;
    a test's coarser tube); an unknown one is a FluoInputError before any work.
    Raises FluoInputError for an unknown stage name (before anything is
    written) and FluoError (after writing metrics.json and report.html) when a
    stage fails; the message names the stage.
    """
    names = stages_to_run(only)
    if case_options:
        from fluoapp.commands import module_logic

        # checks the option names
        module_logic("FluoTomo").tomographyCaseTasks((), tubeOptions=dict(case_options))
    out = Path(out_dir).resolve()
    check_number("seed", seed, 0, 2**32 - 1, integer=True)
    try:
        out.mkdir(parents=True, exist_ok=True)
        probe = out / ".write-test"
        probe.write_text("")
        probe.unlink()
    except OSError as exc:
        raise FluoInputError(f"output folder is not writable ({exc.strerror})",
                             file=out_dir) from None      # as the user gave it
    ctx = DemoContext(out=out, quick=quick, seed=seed, cancel=cancel, executor=executor,
                      threads=threads, resume=bool(resume), case_options=dict(case_options or {}))
    stages = [s for s in _stages() if s[0] in names]
    ctx.metrics = {"quick": quick, "seed": seed, "stage_seconds": {}, "stages_completed": [],
                   "stages_failed": {}}
    t_all = time.perf_counter()
    failure = None
    for i, (name, title, fn) in enumerate(stages):
        check_cancel(cancel)
        report(progress, i / len(stages), title)
        ctx.progress = scaled(progress, i / len(stages), (i + 1) / len(stages), title)
        t0 = time.perf_counter()
        (out / f"{name}.error.txt").unlink(missing_ok=True)  # from an earlier run
        try:
            fn(ctx)
        except Exception as exc:  # recorded, reported, then re-raised as one message
            ctx.metrics["stages_failed"][name] = f"{type(exc).__name__}: {exc}"
            atomic.write_text(out / f"{name}.error.txt", traceback.format_exc())
            failure = (name, exc)
            break
        finally:
            ctx.metrics["stage_seconds"][name] = round(time.perf_counter() - t0, 3)
            _write_json_atomic(out / "metrics.json", ctx.metrics)
        ctx.metrics["stages_completed"].append(name)
    ctx.metrics["total_seconds"] = round(time.perf_counter() - t_all, 3)
    _write_json_atomic(out / "metrics.json", ctx.metrics)
    write_report(ctx)
    report(progress, 1.0, "done" if failure is None else f"failed in {failure[0]}")
    if failure is not None:
        name, exc = failure
        raise FluoError(f"demo stage '{name}' failed: {exc} (details in {out / (name + '.error.txt')}; "
                        f"earlier results kept in {out})")
    return ctx.metrics


def _fmt(v):
    if isinstance(v, float):
        return f"{v:.4g}"
    if isinstance(v, (list, tuple)) and len(v) <= 12:
        return "[" + ", ".join(_fmt(x) for x in v) + "]"
    if isinstance(v, dict):
        return "; ".join(f"{k}: {_fmt(x)}" for k, x in v.items())
    return html.escape(str(v))


# The thesis's phantom experiment (real data, the reference this demo repeats on
# digital phantoms): mean |yield error| and mean |centroid error| [%]
THESIS_TUBE = {"NP": (85.0, None), "SP": (18.0, 1.8), "HP": (16.0, 1.2)}
# the figures that show what the demo found, in the order the summary shows them
KEY_FIGURES = ("tomo_errors.png", "tomo_profiles.png", "tomography_mc.png", "oral_sections.png",
               "mapping_mismatch.png")


def _mean_abs(values):
    vals = [abs(float(v)) for v in values or [] if v is not None]
    return sum(vals) / len(vals) if vals else None


def _pct(v, digits=1):
    return "-" if v is None else f"{v:.{digits}f} %"


def summary_html(m, figures):
    """The report's first section: what the demo showed, in a few lines and one
    table (the quantification with and without priors against the truth and the
    thesis), then the key figures. ``m``: metrics.json's dict; ``figures``:
    (stage, file, caption) of the figures written."""
    e = html.escape
    out = ["<h2>What the demo showed</h2>"]
    tomo, mc, oral = m.get("tomography"), m.get("tomography_mc"), m.get("oral_tomography")
    if not (tomo or mc or oral):
        out.append("<p>The tomography stages did not run (see the stages below): no "
                   "quantification to report.</p>")
    else:
        rows = []
        for meth in ("NP", "SP", "HP"):
            cells = [f"<td>{meth}</td>"]
            if tomo:
                cells += [f"<td>{_pct(tomo.get(f'{meth} mean |yield error| %'))}</td>",
                          f"<td>{_pct(tomo.get(f'{meth} mean |centroid error| %'))}</td>"]
            else:
                cells += ["<td>-</td>", "<td>-</td>"]
            if mc:
                cells.append("<td>" + _pct(_mean_abs(
                    mc.get(f"{meth} from Monte Carlo data: tube yield error % per depth")))
                    + "</td>")
            else:
                cells.append("<td>-</td>")
            t_y, t_c = THESIS_TUBE[meth]
            cells += [f"<td>{_pct(t_y, 0)}</td>", f"<td>{_pct(t_c)}</td>"]
            cells.append("<td>" + (_pct(oral.get(f"{meth} tongue yield error %"))
                                   if oral else "-") + "</td>")
            rows.append("<tr>" + "".join(cells) + "</tr>")
        depths = m.get("tube_depths_mm") or []
        out.append(
            "<p>Fluorescence yield recovered without a prior (NP), with the CBCT as a soft "
            "prior (SP) and as a hard prior (HP), against the known truth of digital "
            "phantoms: the cylinder tube at depths "
            f"{', '.join(f'{d:g}' for d in depths) or '-'} mm (diffusion data from a finer, "
            "independent model" + ("; stored Monte Carlo data, photon transport written "
                                   "outside the project, as an independent check" if mc else "")
            + ") and the oral cavity's tongue. The thesis's phantom experiment (real data) is "
            "the reference.</p>")
        out.append(
            "<table><tr><th>method</th><th>tube: mean |yield error|</th>"
            "<th>tube: mean |centroid error|</th><th>tube from Monte Carlo data: mean "
            "|yield error|</th><th>thesis: yield</th><th>thesis: centroid</th>"
            "<th>oral cavity: tongue yield error</th></tr>" + "".join(rows) + "</table>")
        warned = [w for sec in (tomo, mc, oral) if sec
                  for w in sec.get("reconstruction warnings", [])]
        out.append(f"<p>{len(warned)} reconstruction warning(s) in all (listed with each "
                   "stage below).</p>" if warned else
                   "<p>No reconstruction carried a warning.</p>")
    if m.get("stages_failed"):
        out.append("<p class='fail'>Failed: " + e(", ".join(m["stages_failed"])) + "</p>")
    names = {name: (stage, caption) for stage, name, caption in figures}
    for name in KEY_FIGURES:
        if name in names:
            out.append(f"<figure><img src='{e(name)}' alt='{e(names[name][1])}'>"
                       f"<figcaption>{e(names[name][1])}</figcaption></figure>")
    return "\n".join(out)


def write_report(ctx):
    """``report.html``: what the demo showed first (summary_html), then every
    stage's numbers, notes and figures."""
    m = ctx.metrics
    rows = []
    for stage in list(m["stage_seconds"]):
        status = "failed" if stage in m["stages_failed"] else "ok"
        rows.append(f"<tr><td>{html.escape(stage)}</td><td>{status}</td>"
                    f"<td>{m['stage_seconds'][stage]:.1f}</td></tr>")
    parts = [
        "<!doctype html><html><head><meta charset='utf-8'><title>FluoGuide demo report</title>",
        "<style>body{font-family:sans-serif;max-width:1100px;margin:2em auto;color:#222}"
        "table{border-collapse:collapse;margin:1em 0}td,th{border:1px solid #bbb;padding:4px 8px;"
        "text-align:left;vertical-align:top}th{background:#eee}img{max-width:100%;border:1px solid #ccc}"
        ".fail{color:#b00}</style></head><body>",
        "<h1>FluoGuide end-to-end demo</h1>",
        f"<p>Mode: {'quick' if m.get('quick') else 'full'}; seed {m.get('seed')}; total "
        f"{m.get('total_seconds', 0):.1f} s. Numbers: <a href='metrics.json'>metrics.json</a>; "
        "scene: <a href='scene.mrml'>scene.mrml</a>.</p>",
        summary_html(m, ctx.figures),
        "<h2>Details</h2>",
        "<h3>Stages</h3><table><tr><th>stage</th><th>status</th><th>seconds</th></tr>",
        *rows, "</table>",
    ]
    for stage, err in m["stages_failed"].items():
        parts.append(f"<p class='fail'>Stage {html.escape(stage)} failed: {html.escape(err)}</p>")
    for stage in m["stages_completed"]:
        section = m.get(stage)
        figs = [f for f in ctx.figures if f[0] == stage]
        notes = [n for n in ctx.notes if n[0] == stage]
        if section is None and not figs and not notes:
            continue
        parts.append(f"<h3>{html.escape(stage)}</h3>")
        for _, text in notes:
            parts.append(f"<p>{html.escape(text)}</p>")
        if isinstance(section, dict):
            parts.append("<table>")
            for k, v in section.items():
                parts.append(f"<tr><th>{html.escape(str(k))}</th><td>{_fmt(v)}</td></tr>")
            parts.append("</table>")
        for _, name, caption in figs:
            if name in KEY_FIGURES:           # shown in the summary at the top
                parts.append(f"<p>Figure {html.escape(name)}: in the summary above.</p>")
                continue
            parts.append(f"<figure><img src='{html.escape(name)}' alt='{html.escape(caption)}'>"
                         f"<figcaption>{html.escape(caption)}</figcaption></figure>")
    parts.append("</body></html>")
    atomic.write_text(ctx.out / "report.html", "\n".join(parts))
