"""The accuracy knob of the label-map pipelines: one word for the element
sizes and tolerances, or explicit sizes.

Each level's error and time were measured (docs/tomography-own-scene.md,
"Accuracy levels"; benchmarks/bench_own_scene.py reproduces them).
"""

from __future__ import annotations

import numpy as np

from fluoguide.errors import FluoInputError

#: recon_mm: reconstruction element size (capped at the sources' burial depth,
#: 1 transport mean free path: with 1.2 mm cells on tissue of MFP' 1 mm the
#: data of the issue's scene fell by 26 %, with 1.0 mm they were within 1 %); a
#: band of cells half as thick lies under the optodes (model.surface_band) and
#: the target is refined to ``refine_factor`` of it; recon_coarse_mm: the cells
#: away from the optodes and the target (``grading``, optode-aware: off by
#: default, = recon_mm; see docs: with the refinement bands running through
#: coarse cells the data of the issue's scene moved by -11 % to +1 %);
#: truncation_pct: largest estimated change of the data by the
#: region-of-interest cut; simulate_mm / simulate_coarse_mm: the simulation mesh
#: near the optodes and target / elsewhere (graded: within 0.1 % (0.5 mm), 1.4 %
#: (0.6 mm) and 3 % (0.8 mm) of a uniform 0.5 mm mesh of the issue's scene).
LEVELS = {
    "fast": {"recon_mm": 1.0, "recon_coarse_mm": 2.0, "refine_factor": 0.5,
             "truncation_pct": 2.0, "simulate_mm": 0.8, "simulate_coarse_mm": 1.6},
    "balanced": {"recon_mm": 0.8, "recon_coarse_mm": 1.6, "refine_factor": 0.5,
                 "truncation_pct": 1.0, "simulate_mm": 0.6, "simulate_coarse_mm": 1.5},
    "fine": {"recon_mm": 0.7, "recon_coarse_mm": 1.4, "refine_factor": 0.5,
             "truncation_pct": 0.5, "simulate_mm": 0.5, "simulate_coarse_mm": 1.25},
}
DEFAULT = "balanced"


def accuracy_settings(accuracy=DEFAULT, **override):
    """The settings of a level, with explicit values (not None) overriding it
    (``recon_mm`` alone also sets ``recon_coarse_mm`` to twice it unless that
    is given too)."""
    if accuracy not in LEVELS:
        raise FluoInputError(f"accuracy must be one of {', '.join(LEVELS)}", field="accuracy",
                             value=accuracy)
    out = dict(LEVELS[accuracy])
    for key, value in override.items():
        if value is None:
            continue
        if key not in out:
            raise FluoInputError("unknown accuracy setting", field=key)
        v = float(value)
        if not (v > 0 and v < 1e3):
            raise FluoInputError("must be a positive number", field=key, value=value)
        out[key] = v
    if override.get("recon_mm") is not None and override.get("recon_coarse_mm") is None:
        out["recon_coarse_mm"] = max(out["recon_coarse_mm"], 2.0 * out["recon_mm"])
    if override.get("simulate_mm") is not None and override.get("simulate_coarse_mm") is None:
        out["simulate_coarse_mm"] = max(out["simulate_coarse_mm"], 2.5 * out["simulate_mm"])
    out["level"] = accuracy
    return out


def cap_at_burial(size_mm, optics, labels):
    """The element size near the optodes, at most the sources' burial depth (1
    transport mean free path of the most scattering tissue, 1/(mua + musp'))."""
    mx, sx, _, _ = optics.per_label_arrays(labels)
    mfp = float(1.0 / np.max(mx + sx))
    return min(float(size_mm), mfp), mfp
