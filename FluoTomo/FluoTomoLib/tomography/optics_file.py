"""``optics.json``: the optical properties of every label, written by hand.

::

    {
      "n": 1.37,
      "excitation": {"1": {"mua_per_mm": 0.0026, "musp_per_mm": 0.89},
                     "2": {"mua_per_mm": 0.0030, "musp_per_mm": 1.20}},
      "emission":   {"1": {"mua_per_mm": 0.0029, "musp_per_mm": 0.81},
                     "2": {"mua_per_mm": 0.0032, "musp_per_mm": 1.10}},
      "fluorophore": "ICG",
      "names": {"1": "tissue", "2": "tumour"},
      "boundary": "fresnel"
    }

Labels are the label map's values (label 0 is air and is not listed).  The
properties are the tissue's *without* the fluorophore being reconstructed:
its absorption grows with the yield (``fluorophore``: ``"ICG"`` for the ICG
table's slopes, an object ``{"mua_x_per_yield": .., "mua_m_per_yield": ..}``,
or ``null``/absent for a dye whose absorption is negligible); the simulation
adds it to the truth and the hard-prior reconstruction feeds it back
(self-absorption).  ``n`` is the tissue's refractive index (outside: air).
``boundary`` (optional) is the Robin boundary constant's method
(``optics.robin_A``: ``"fresnel"``, the exact partial-current value, or
``"empirical"``, the Reff polynomial the thesis's tables used); absent: the
library's default (``optics.DEFAULT_BOUNDARY``, Fresnel), the same for the
simulation and the reconstruction.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from fluoguide.errors import FluoInputError

_LABEL_KEYS = {"mua_per_mm", "musp_per_mm"}
_TOP_KEYS = {"n", "excitation", "emission", "fluorophore", "names", "comment", "boundary"}


@dataclass
class Optics:
    """Optical properties per label at excitation (x) and emission (m).

    ``excitation[label] = (mua_per_mm, musp_per_mm)``, likewise ``emission``;
    ``mua_per_yield = (d mua_x / d yield, d mua_m / d yield)`` of the
    fluorophore, (0, 0) when its absorption is not modelled.
    """

    n: float
    excitation: dict
    emission: dict
    mua_per_yield: tuple = (0.0, 0.0)
    fluorophore: str | None = None
    names: dict = field(default_factory=dict)
    source: str | None = None
    boundary: str | None = None        # optics.robin_A's method; None: its default

    @property
    def labels(self):
        return sorted(self.excitation)

    def check_labels(self, labels, what="label map"):
        """Every tissue label of the scene must have properties."""
        missing = [int(v) for v in labels if int(v) not in self.excitation]
        if missing:
            raise FluoInputError(f"labels of the {what} have no optical properties "
                                 f"(add them to optics.json)", file=self.source,
                                 field="excitation", value=missing)

    def per_label_arrays(self, labels):
        """(mua_x, musp_x, mua_m, musp_m) arrays in the order of ``labels``."""
        self.check_labels(labels)
        mx = np.array([self.excitation[int(v)][0] for v in labels])
        sx = np.array([self.excitation[int(v)][1] for v in labels])
        mm = np.array([self.emission[int(v)][0] for v in labels])
        sm = np.array([self.emission[int(v)][1] for v in labels])
        return mx, sx, mm, sm

    def nodal(self, region_labels, fractions, yield_nodes=None):
        """Nodal properties from partial-volume fractions (N, R) over
        ``region_labels``: each property is the fraction-weighted mean of the
        regions' (mua, musp); with ``yield_nodes`` the fluorophore's absorption
        is added.  Returns dicts for FluorescenceModel (props_x, props_m)."""
        mx, sx, mm, sm = self.per_label_arrays(region_labels)
        F = np.asarray(fractions, float)
        mua_x, musp_x, mua_m, musp_m = F @ mx, F @ sx, F @ mm, F @ sm
        if yield_nodes is not None:
            y = np.clip(np.asarray(yield_nodes, float), 0.0, None)
            mua_x = mua_x + self.mua_per_yield[0] * y
            mua_m = mua_m + self.mua_per_yield[1] * y
        px = {"mua_per_mm": mua_x, "musp_per_mm": musp_x, "n": self.n}
        pm = {"mua_per_mm": mua_m, "musp_per_mm": musp_m, "n": self.n}
        if self.boundary is not None:
            px["boundary"] = pm["boundary"] = self.boundary
        return px, pm

    def nodal_from_mesh(self, mesh, yield_by_label=None):
        """Nodal properties of a mesh whose elements carry region labels: each
        node takes the volume-weighted mean over the elements around it (a
        node on an interface shares both sides).  ``yield_by_label`` {label:
        yield 1/mm} also gives the nodal yield, the fluorophore's absorption
        added.  Returns (props_x, props_m, yield_nodes or None)."""
        labels = [int(v) for v in mesh.regions]
        self.check_labels(labels, what="mesh")
        col = {v: k for k, v in enumerate(labels)}
        idx = np.array([col[int(r)] for r in mesh.element_region])
        W = np.zeros((mesh.n_nodes, len(labels)))
        np.add.at(W, (mesh.elements.ravel(), np.repeat(idx, mesh.dim + 1)),
                  np.repeat(mesh.measures, mesh.dim + 1))
        with np.errstate(invalid="ignore"):
            # a node no element uses has no weight: NaN properties, and the mesh
            # check refuses the mesh ("node(s) belong to no element") in one line
            W /= W.sum(axis=1, keepdims=True)
        y = None
        if yield_by_label is not None:
            unknown = [int(k) for k in yield_by_label if int(k) not in col]
            if unknown:
                raise FluoInputError("yield given for labels the mesh does not have",
                                     field="yield", value=unknown)
            y = W @ np.array([float(yield_by_label.get(v, 0.0)) for v in labels])
        px, pm = self.nodal(labels, W, yield_nodes=y)
        return px, pm, y

    def min_mueff(self, labels=None):
        """Smallest effective attenuation [1/mm] over the labels and both
        wavelengths: the longest decay length sets how far light carries."""
        from FluoTomoLib.optics import mueff

        labels = self.labels if labels is None else labels
        mx, sx, mm, sm = self.per_label_arrays(labels)
        return float(min(np.min(mueff(mx, sx)), np.min(mueff(mm, sm))))

    def to_json(self):
        def table(t):
            return {str(k): {"mua_per_mm": v[0], "musp_per_mm": v[1]} for k, v in sorted(t.items())}

        fl = (self.fluorophore if self.fluorophore == "ICG" else
              None if self.mua_per_yield == (0.0, 0.0) else
              {"mua_x_per_yield": self.mua_per_yield[0], "mua_m_per_yield": self.mua_per_yield[1]})
        doc = {"n": self.n, "excitation": table(self.excitation),
               "emission": table(self.emission), "fluorophore": fl}
        if self.names:
            doc["names"] = {str(k): v for k, v in self.names.items()}
        if self.boundary is not None:
            doc["boundary"] = self.boundary
        return doc


def _number(value, file, field, lo=None, strict_lo=False, hi=None):
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise FluoInputError("must be a number", file=file, field=field, value=value)
    v = float(value)
    if not np.isfinite(v):
        raise FluoInputError("must be finite", file=file, field=field, value=value)
    if lo is not None and (v <= lo if strict_lo else v < lo):
        raise FluoInputError(f"must be {'>' if strict_lo else '>='} {lo:g}", file=file,
                             field=field, value=value)
    if hi is not None and v > hi:
        raise FluoInputError(f"must be <= {hi:g}", file=file, field=field, value=value)
    return v


def _label(key, file, field):
    try:
        lab = int(str(key).strip())
    except ValueError:
        raise FluoInputError("label keys must be integers (as strings)", file=file,
                             field=field, value=key) from None
    if str(lab) != str(key).strip() or lab < 0:
        raise FluoInputError("label keys must be integers >= 1", file=file, field=field,
                             value=key)
    if lab == 0:
        raise FluoInputError("label 0 is air: it has no optical properties", file=file,
                             field=f"{field}.0")
    return lab


def _table(doc, key, file):
    t = doc.get(key)
    if not isinstance(t, dict) or not t:
        raise FluoInputError("needs an object of label -> {mua_per_mm, musp_per_mm}",
                             file=file, field=key, value=None if t is None else type(t).__name__)
    out = {}
    for k, entry in t.items():
        lab = _label(k, file, key)
        f = f"{key}.{k}"
        if not isinstance(entry, dict):
            raise FluoInputError("needs {\"mua_per_mm\": .., \"musp_per_mm\": ..}", file=file,
                                 field=f, value=entry)
        extra = set(entry) - _LABEL_KEYS
        if extra:
            raise FluoInputError("unknown key (expected mua_per_mm, musp_per_mm)", file=file,
                                 field=f"{f}.{sorted(extra)[0]}")
        for need in sorted(_LABEL_KEYS):
            if need not in entry:
                raise FluoInputError("missing", file=file, field=f"{f}.{need}")
        mua = _number(entry["mua_per_mm"], file, f"{f}.mua_per_mm", lo=0.0, hi=100.0)
        musp = _number(entry["musp_per_mm"], file, f"{f}.musp_per_mm", lo=0.0, strict_lo=True,
                       hi=1000.0)
        out[lab] = (mua, musp)
    return out


#: the near-infrared tissue range [1/mm] of optics.json's values: beyond it a
#: value is far more likely in 1/cm (ten times larger) than a tissue's. Reduced
#: scattering of soft tissue, fat, muscle, brain and liquid phantoms at 650-850 nm
#: is 0.3-3 /mm; absorption without dye 0.001-0.5 /mm (whole blood ~0.5 /mm)
TISSUE_MUSP_MAX_PER_MM = 5.0
TISSUE_MUA_MAX_PER_MM = 2.0


def _check_tissue_range(table, key, file):
    """Refuse values outside the tissue range, naming the likely unit mistake."""
    for lab, (mua, musp) in table.items():
        for name, value, top in (("musp_per_mm", musp, TISSUE_MUSP_MAX_PER_MM),
                                 ("mua_per_mm", mua, TISSUE_MUA_MAX_PER_MM)):
            if value > top:
                hint = (f"were the optics given in 1/cm? {value:g} /cm is {value / 10:g} /mm"
                        if value / 10 <= top else "check the units (1/mm)")
                raise FluoInputError(
                    f"label {lab}: {value:g} /mm is beyond tissue's {name.split('_')[0]} in the "
                    f"near infrared (at most {top:g} /mm): {hint}", file=file,
                    field=f"{key}.{lab}.{name}", value=value)


def optics_from_dict(doc, file=None):
    """Validate an optics document (the parsed optics.json) into :class:`Optics`."""
    if not isinstance(doc, dict):
        raise FluoInputError("optics must be a JSON object", file=file)
    extra = set(doc) - _TOP_KEYS
    if extra:
        raise FluoInputError(f"unknown key (expected {', '.join(sorted(_TOP_KEYS))})", file=file,
                             field=sorted(extra)[0])
    if "n" not in doc:
        raise FluoInputError("missing (the tissue's refractive index, e.g. 1.37)", file=file,
                             field="n")
    n = _number(doc["n"], file, "n", lo=1.0, hi=3.0)
    ex = _table(doc, "excitation", file)
    em = _table(doc, "emission", file)
    _check_tissue_range(ex, "excitation", file)
    _check_tissue_range(em, "emission", file)
    if set(ex) != set(em):
        odd = sorted(set(ex) ^ set(em))
        raise FluoInputError("excitation and emission must list the same labels", file=file,
                             field="emission", value=odd)
    fl = doc.get("fluorophore")
    names = doc.get("names") or {}
    if not isinstance(names, dict) or not all(isinstance(v, str) for v in names.values()):
        raise FluoInputError("names must map labels to strings", file=file, field="names")
    names = {_label(k, file, "names"): v for k, v in names.items()}
    if fl is None:
        slopes, name = (0.0, 0.0), None
    elif isinstance(fl, str):
        if fl.upper() != "ICG":
            raise FluoInputError("known fluorophores: ICG (or give mua_x_per_yield and "
                                 "mua_m_per_yield)", file=file, field="fluorophore", value=fl)
        from fluoguide.optics_table import icg_absorption_per_yield

        slopes, name = tuple(float(v) for v in icg_absorption_per_yield()), "ICG"
    elif isinstance(fl, dict):
        extra = set(fl) - {"mua_x_per_yield", "mua_m_per_yield", "name"}
        if extra or not {"mua_x_per_yield", "mua_m_per_yield"} <= set(fl):
            raise FluoInputError("needs mua_x_per_yield and mua_m_per_yield (and optionally "
                                 "name)", file=file, field="fluorophore", value=sorted(fl))
        slopes = (_number(fl["mua_x_per_yield"], file, "fluorophore.mua_x_per_yield", lo=0.0),
                  _number(fl["mua_m_per_yield"], file, "fluorophore.mua_m_per_yield", lo=0.0))
        name = str(fl.get("name", "custom"))
    else:
        raise FluoInputError("must be \"ICG\", an object or null", file=file,
                             field="fluorophore", value=fl)
    boundary = doc.get("boundary")
    if boundary is not None:
        from FluoTomoLib.optics import BOUNDARY_METHODS

        if boundary not in BOUNDARY_METHODS:
            raise FluoInputError(f"must be one of {', '.join(BOUNDARY_METHODS)} (or absent: "
                                 "the default)", file=file, field="boundary", value=boundary)
    return Optics(n, ex, em, slopes, name, names, None if file is None else str(file), boundary)


def read_optics(path):
    """Read and validate ``optics.json``."""
    from fluoguide.jsonable import read_json

    p = Path(path)
    return optics_from_dict(read_json(p), p)


def homogeneous_optics(mua_per_mm, musp_per_mm, n, labels=(1,)):
    """One material at both wavelengths for every label (``fluo forward
    --mua --musp``)."""
    doc = {"n": n, "excitation": {}, "emission": {}}
    for lab in labels:
        entry = {"mua_per_mm": mua_per_mm, "musp_per_mm": musp_per_mm}
        doc["excitation"][str(int(lab))] = entry
        doc["emission"][str(int(lab))] = entry
    return optics_from_dict(doc)


def optics_from_phantom(phantom_optics, n=None):
    """:class:`Optics` from a phantom's per-label optics dicts (fluoguide.phantoms):
    the liquid's properties without the dye (``optics_table.without_icg``), ICG slopes."""
    from fluoguide.optics_table import icg_absorption_per_yield, without_icg

    base = without_icg(phantom_optics)
    ex = {int(k): (v[0], v[1]) for k, v in base.items()}
    em = {int(k): (v[2], v[3]) for k, v in base.items()}
    first = next(iter(phantom_optics.values()))
    return Optics(float(n if n is not None else first["n"]), ex, em,
                  tuple(float(v) for v in icg_absorption_per_yield()), "ICG")
