"""The accuracy knob of the label-map pipelines: one word for the element
sizes and tolerances, or explicit sizes.

Each level's error and time were measured (docs/tomography-own-scene.md,
"Accuracy levels"; benchmarks/bench_own_scene.py reproduces them).
"""

from __future__ import annotations

from fluoguide.errors import FluoInputError

#: recon_mm: reconstruction element size; refine_factor: cell size across the
#: target relative to it; truncation_pct: largest estimated change of the data
#: by the region-of-interest cut; simulate_mm / simulate_coarse_mm: the
#: simulation mesh near the optodes and target / elsewhere
LEVELS = {
    "fast": {"recon_mm": 1.5, "refine_factor": 0.5, "truncation_pct": 2.0,
             "simulate_mm": 1.0, "simulate_coarse_mm": 2.5},
    "balanced": {"recon_mm": 1.0, "refine_factor": 0.5, "truncation_pct": 1.0,
                 "simulate_mm": 0.8, "simulate_coarse_mm": 2.0},
    "fine": {"recon_mm": 0.7, "refine_factor": 0.5, "truncation_pct": 0.5,
             "simulate_mm": 0.6, "simulate_coarse_mm": 1.5},
}
DEFAULT = "balanced"


def accuracy_settings(accuracy=DEFAULT, **override):
    """The settings of a level, with explicit values (not None) overriding it."""
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
    out["level"] = accuracy
    return out
