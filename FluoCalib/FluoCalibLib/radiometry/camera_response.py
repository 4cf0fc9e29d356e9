"""Camera response characterisation from image stacks, reported as EMVA 1288 does.

Input: frames with exposure times, dark (shutter closed / cap on) or light
(uniform illumination), at least two frames per exposure so temporal noise
comes from frame differences (fixed-pattern noise cancels).

Outputs (docs/physics.md section 5.2):

- dark signal vs exposure: slope = dark current, intercept = bias (in ADU,
  converted to e- with the gain);
- read noise = rms(dark_1 - dark_2) / sqrt(2) at the shortest exposure, less
  the dark-current shot noise of that exposure;
- photon-transfer curve: temporal variance vs mean signal above dark; its
  slope is the system gain K [ADU/e-] (fit below 70 % of saturation, as the
  standard does);
- linearity: mean signal vs exposure, R^2 and NL = 100 (|+dev_max| +
  |-dev_max|) / S_max over 5-95 % of saturation;
- saturation capacity, full well and dynamic range;
- optional: lens f-number exponent (frames at several f-numbers) and spectral
  responsivity (frames at several wavelengths with known radiance).

Pixels at the A/D ceiling are excluded from every mean and variance; an
exposure where more than half the pixels saturate is reported and not used.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from fluoguide.errors import FluoInputError

__all__ = ["Frame", "load_stack", "write_stack", "characterize"]


@dataclass
class Frame:
    """One image [ADU] and its acquisition settings."""

    image: np.ndarray
    exposure_s: float
    kind: str = "light"              # "light" or "dark"
    f_number: float | None = None
    wavelength_nm: float | None = None
    radiance_w_per_mm2_sr: float | None = None
    name: str = ""


def _read_image(path):
    from fluoguide.images import read_image

    return read_image(path)


def load_stack(folder):
    """Frames of a stack folder: ``stack.json`` lists ``frames`` with ``file``,
    ``exposure_s``, ``kind`` (light/dark) and optionally ``f_number``,
    ``wavelength_nm``, ``radiance_w_per_mm2_sr``; images are 16-bit PNG/TIFF
    or .npy.  Returns (frames, metadata dict)."""
    from fluoguide import atomic
    from fluoguide.errors import check_number
    from fluoguide.jsonable import read_json
    from fluoguide.paths import inside

    folder = Path(folder)
    if folder.is_dir():
        atomic.recover(folder)   # finish a write_stack a crash interrupted: the new set, whole
    meta_path = folder / "stack.json"
    if not meta_path.is_file():
        raise FluoInputError("stack folder needs a stack.json", file=meta_path)
    meta = read_json(meta_path)
    entries = meta.get("frames") if isinstance(meta, dict) else None
    if not isinstance(entries, list) or not entries:
        raise FluoInputError("needs a non-empty 'frames' list", file=meta_path, field="frames")
    frames = []
    for i, e in enumerate(entries):
        where = f"frames[{i}]"
        if not isinstance(e, dict) or "file" not in e or "exposure_s" not in e:
            raise FluoInputError("each frame needs 'file' and 'exposure_s'", file=meta_path,
                                 field=where)
        kind = str(e.get("kind", "light"))
        if kind not in ("light", "dark"):
            raise FluoInputError("kind must be 'light' or 'dark'", file=meta_path,
                                 field=f"{where}.kind", value=kind)
        t = check_number(f"{where}.exposure_s", e["exposure_s"], 0.0, 3600.0, file=meta_path,
                         what="exposure must be a number of seconds within 0..3600")
        optional = {}
        for key, hi in (("f_number", 1000.0), ("wavelength_nm", 1e5), ("radiance_w_per_mm2_sr", None)):
            if e.get(key) is not None:
                optional[key] = check_number(f"{where}.{key}", e[key], 0.0, hi, lo_open=True,
                                             file=meta_path)
        # the manifest names files in its own folder, never ../ or absolute paths
        img = _read_image(inside(folder, e["file"], file=meta_path, field=f"{where}.file",
                                  given=True))   # messages name it as given
        frames.append(Frame(img, float(t), kind, optional.get("f_number"),
                            optional.get("wavelength_nm"), optional.get("radiance_w_per_mm2_sr"),
                            str(e["file"])))
    return frames, meta


def write_stack(folder, frames, extra=None):
    """Write frames as 16-bit PNGs plus ``stack.json``, the folder as a whole
    (``fluoguide.atomic.staged_folder``: a kill leaves the old set or the new one)."""
    import cv2

    from fluoguide import atomic

    folder = Path(folder)
    with atomic.staged_folder(folder, last=("stack.json",)) as stage:
        entries = []
        for i, f in enumerate(frames):
            name = f.name or f"{f.kind}_{i:03d}.png"
            img = np.clip(np.round(f.image), 0, 65535).astype(np.uint16)
            if not cv2.imwrite(str(stage / name), img):
                raise FluoInputError("cannot write image", file=folder / name)
            e = {"file": name, "exposure_s": float(f.exposure_s), "kind": f.kind}
            for k in ("f_number", "wavelength_nm", "radiance_w_per_mm2_sr"):
                if getattr(f, k) is not None:
                    e[k] = float(getattr(f, k))
            entries.append(e)
        doc = {"frames": entries, **(extra or {})}
        (stage / "stack.json").write_text(json.dumps(doc, indent=1, allow_nan=False))
    return folder


@dataclass
class _Level:
    exposure_s: float
    mean_adu: float
    var_adu2: float          # temporal variance of one frame (from pair differences)
    n_frames: int
    saturated_fraction: float
    f_number: float | None = None
    wavelength_nm: float | None = None
    radiance: float | None = None


def _levels(frames, kind, adc_max):
    """Mean and temporal variance per (exposure, f#, wavelength) group."""
    groups = {}
    for f in frames:
        if f.kind != kind:
            continue
        key = (round(f.exposure_s, 12), f.f_number, f.wavelength_nm)
        groups.setdefault(key, []).append(f)
    out = []
    for (t, fn, wl), fs in sorted(groups.items(), key=lambda kv: (kv[0][0], str(kv[0][1:]))):
        imgs = [np.asarray(f.image, float) for f in fs]
        shape = imgs[0].shape
        for f, im in zip(fs, imgs):
            if im.shape != shape:
                raise FluoInputError("frames of one exposure differ in size", field=f.name,
                                     value=(im.shape, shape))
        sat = np.zeros(shape, bool)
        for im in imgs:
            sat |= im >= adc_max
        ok = ~sat
        frac = float(sat.mean())
        mean = float(np.mean([im[ok].mean() for im in imgs])) if ok.any() else float(adc_max)
        if len(imgs) >= 2 and ok.sum() > 10:
            diffs = [(imgs[i] - imgs[i + 1])[ok] for i in range(0, len(imgs) - 1, 2)]
            var = float(np.mean([np.var(d) / 2.0 for d in diffs]))
        else:
            var = float("nan")
        out.append(_Level(t, mean, var, len(imgs), frac, fn, wl, fs[0].radiance_w_per_mm2_sr))
    return out


def _linfit(x, y):
    """Least-squares line: (slope, intercept, R^2)."""
    x = np.asarray(x, float)
    y = np.asarray(y, float)
    A = np.stack([x, np.ones_like(x)], axis=1)
    (a, b), *_ = np.linalg.lstsq(A, y, rcond=None)
    ss_res = float(np.sum((y - (a * x + b)) ** 2))
    ss_tot = float(np.sum((y - y.mean()) ** 2))
    r2 = 1.0 - ss_res / ss_tot if ss_tot > 0 else 1.0
    return float(a), float(b), r2


def _check_frames(frames):
    """Raise unless ``frames`` is a non-empty list of finite 2D images of one
    size, with exposures >= 0 s (> 0 s for light frames)."""
    if not frames:
        raise FluoInputError("no frames", field="frames")
    for f in frames:
        if not np.isfinite(f.exposure_s) or f.exposure_s < 0:
            raise FluoInputError("exposure must be >= 0 s", field=f.name or "exposure_s",
                                 value=f.exposure_s)
        if f.kind == "light" and f.exposure_s == 0:
            raise FluoInputError("a light frame with zero exposure carries no signal",
                                 field=f.name or "exposure_s", value=0.0)
        img = np.asarray(f.image)
        if img.ndim != 2 or img.size < 100:
            raise FluoInputError("frames must be 2D images of at least 100 pixels",
                                 field=f.name, value=getattr(img, "shape", None))
        if not np.all(np.isfinite(img)):
            raise FluoInputError("frame has NaN or infinite values", field=f.name)
    # every statistic compares frames pixel by pixel or pools them: one size only
    shapes = {np.shape(f.image) for f in frames}
    if len(shapes) > 1:
        odd = next(f for f in frames if np.shape(f.image) != np.shape(frames[0].image))
        raise FluoInputError("frames differ in size", field=odd.name or "frames",
                             value=sorted(shapes))


def _series(frames, adc_max, saturation_limit):
    """The exposure levels of the gain/linearity series: (dark levels, dark
    levels with a pair, light levels, unsaturated light levels with a pair);
    raise when they cannot give the dark line or the photon-transfer curve."""
    # The gain/linearity series is the light frames of the most frequent
    # (f-number, wavelength) setting; frames at other f-numbers or wavelengths
    # (usually at other radiances) only feed the lens and spectral fits: mixed
    # into the series they would bend the linearity.  Dark frames do not depend
    # on either setting and are all used.
    setting = _main_setting(frames)
    main = [f for f in frames if f.kind == "dark" or (f.f_number, f.wavelength_nm) == setting]
    dark = _levels(main, "dark", adc_max)
    light = _levels(main, "light", adc_max)
    dark_pairs = [d for d in dark if np.isfinite(d.var_adu2)]
    if len({d.exposure_s for d in dark}) < 2 or not dark_pairs:
        raise FluoInputError("need dark frames at >= 2 exposures, with a pair at one of them "
                             f"(got {len(dark)} dark exposure(s))", field="dark frames",
                             value=len(dark))
    if any(d.saturated_fraction > saturation_limit for d in dark):
        raise FluoInputError("dark frames are saturated: check the lens cap / shutter",
                             field="dark frames")
    unsaturated = [lv for lv in light if lv.saturated_fraction <= saturation_limit]
    usable = [lv for lv in unsaturated if np.isfinite(lv.var_adu2)]
    if len(light) and not unsaturated:
        raise FluoInputError("every light exposure is saturated: shorten the exposures",
                             field="light frames", value=[float(lv.exposure_s) for lv in light])
    if len(usable) < 3:
        raise FluoInputError("need light frame pairs at >= 3 unsaturated exposures for the "
                             f"photon-transfer curve (got {len(usable)})", field="light frames",
                             value=len(usable))
    return dark, dark_pairs, light, usable


def _dark_lines(dark, dark_pairs):
    """Dark signal vs exposure (slope [ADU/s], intercept [ADU]) and the
    functions of exposure [s] giving the dark mean [ADU] and the dark temporal
    variance [ADU^2] the photon-transfer curve subtracts."""
    dark_slope, dark_icpt, _ = _linfit([d.exposure_s for d in dark], [d.mean_adu for d in dark])
    dvar = [(d.exposure_s, d.var_adu2) for d in dark_pairs]
    if len(dvar) >= 2:
        dv_slope, dv_icpt, _ = _linfit(*zip(*dvar))
    else:
        dv_slope, dv_icpt = 0.0, dvar[0][1]

    def dark_mean(t):
        return dark_slope * t + dark_icpt

    def dark_var(t):
        return max(dv_slope * t + dv_icpt, 0.0)

    return dark_slope, dark_icpt, dark_mean, dark_var


def _photon_transfer(usable, dark_mean, dark_var):
    """Photon-transfer curve of the usable light levels: signal above dark mu
    [ADU], temporal variance above dark [ADU^2], saturation signal [ADU], the
    points fitted, the gain K [ADU/e-] and the fit's R^2."""
    mu = np.array([lv.mean_adu - dark_mean(lv.exposure_s) for lv in usable])
    var = np.array([lv.var_adu2 - dark_var(lv.exposure_s) for lv in usable])
    if np.max(mu) <= 10.0 * np.sqrt(max(dark_var(0.0), 1e-12)):
        raise FluoInputError("light frames are no brighter than dark ones (black stack): "
                             "check the illumination and exposure", field="light frames",
                             value=float(np.max(mu)))
    # saturation: mean of the brightest exposure that is still mostly unsaturated
    mu_sat = float(np.max(mu))
    fit = mu <= 0.7 * mu_sat
    if fit.sum() < 3:
        fit = np.ones_like(mu, bool)
    K, _, ptc_r2 = _linfit(mu[fit], var[fit])
    if not (np.isfinite(K) and K > 0):
        raise FluoInputError("photon-transfer slope is not positive: frames of one exposure "
                             "differ by more than noise (moving scene or flicker?)",
                             field="light frames", value=K)
    return mu, var, mu_sat, fit, K, ptc_r2


def _linearity(usable, mu, mu_sat):
    """Signal vs exposure over 5-95 % of the saturation signal: exposures [s],
    slope [ADU/s], intercept [ADU], R^2 and nonlinearity [%]."""
    t = np.array([lv.exposure_s for lv in usable])
    lin = (mu >= 0.05 * mu_sat) & (mu <= 0.95 * mu_sat)
    if lin.sum() < 3:
        lin = np.ones_like(mu, bool)
    a, b, r2 = _linfit(t[lin], mu[lin])
    dev = mu[lin] - (a * t[lin] + b)
    nl = 100.0 * (abs(max(dev.max(), 0.0)) + abs(min(dev.min(), 0.0))) / mu_sat
    return t, a, b, r2, nl


def characterize(frames, bit_depth=14, saturation_limit=0.5):
    """EMVA-1288-style characterisation of a camera from ``frames``.

    Returns a dict with ``gain_adu_per_e``, ``dark_current_e_per_s``, ``bias_e``,
    ``read_noise_e``, ``linearity_r2``, ``nonlinearity_pct``,
    ``saturation_capacity_e``, ``dynamic_range`` (and ``_db``), optional
    ``lens_exponent`` / ``spectral_responsivity``, plus the curves (``ptc``,
    ``linearity``, ``dark``) for plots.
    """
    from fluoguide.errors import check_number

    check_number("bit_depth", bit_depth, 1, 32, integer=True, what="must be 1..32 bits")
    adc_max = float(2 ** int(bit_depth) - 1)
    _check_frames(frames)
    dark, dark_pairs, light, usable = _series(frames, adc_max, saturation_limit)
    dark_slope, dark_icpt, dark_mean, dark_var = _dark_lines(dark, dark_pairs)
    mu, var, mu_sat, fit, K, ptc_r2 = _photon_transfer(usable, dark_mean, dark_var)
    # dark: ADU -> e-
    dark_current = dark_slope / K
    bias = dark_icpt / K
    d0 = min(dark_pairs, key=lambda d: d.exposure_s)
    read_var_e = d0.var_adu2 / K ** 2 - max(dark_current, 0.0) * d0.exposure_s
    read_noise = float(np.sqrt(max(read_var_e, 0.0)))
    t, a, b, r2, nl = _linearity(usable, mu, mu_sat)
    sat_e = mu_sat / K
    dr = sat_e / read_noise if read_noise > 0 else float("inf")
    out = {
        "gain_adu_per_e": K, "dark_current_e_per_s": dark_current, "bias_e": bias,
        "read_noise_e": read_noise, "linearity_r2": r2, "nonlinearity_pct": nl,
        "ptc_r2": ptc_r2, "saturation_capacity_e": sat_e,
        "full_well_e": sat_e + bias, "dynamic_range": dr,
        "dynamic_range_db": 20 * np.log10(dr) if np.isfinite(dr) and dr > 0 else None,
        "exposures_used": int(len(usable)),
        "exposures_saturated": [lv.exposure_s for lv in light if lv.saturated_fraction > saturation_limit],
        "ptc": {"mean_adu": mu.tolist(), "var_adu2": var.tolist(), "fit": fit.tolist()},
        "linearity": {"exposure_s": t.tolist(), "mean_adu": mu.tolist(), "slope_adu_per_s": a,
                      "intercept_adu": b},
        "dark": {"exposure_s": [d.exposure_s for d in dark], "mean_adu": [d.mean_adu for d in dark]},
    }
    lens = _lens_exponent(frames, adc_max, dark_mean)
    if lens is not None:
        out["lens_exponent"] = lens
    spectral = _spectral(frames, adc_max, dark_mean, K)
    if spectral is not None:
        out["spectral_responsivity"] = spectral
    return out


def _main_setting(frames):
    """Most frequent (f_number, wavelength_nm) among light frames, None counting
    as a value; ties go to the unlabelled setting, then to the first seen."""
    counts = {}
    for f in frames:
        if f.kind == "light":
            key = (f.f_number, f.wavelength_nm)
            counts[key] = counts.get(key, 0) + 1
    if not counts:
        return (None, None)
    top = max(counts.values())
    best = [k for k, c in counts.items() if c == top]
    return (None, None) if (None, None) in best else best[0]


def _lens_exponent(frames, adc_max, dark_mean):
    """alpha of S ~ f#^-alpha from light frames of one exposure at >= 3 f-numbers."""
    groups = {}
    for f in frames:
        if f.kind == "light" and f.f_number is not None:
            groups.setdefault(round(f.exposure_s, 12), {}).setdefault(float(f.f_number), []).append(f)
    best = max(groups.values(), key=len, default={})
    if len(best) < 3:
        return None
    fn, s = [], []
    for k, fs in sorted(best.items()):
        im = np.mean([np.asarray(f.image, float) for f in fs], axis=0)
        ok = im < adc_max
        sig = float(im[ok].mean()) - dark_mean(fs[0].exposure_s) if ok.any() else 0.0
        if sig > 0:
            fn.append(k)
            s.append(sig)
    if len(fn) < 3:
        return None
    slope, _, r2 = _linfit(np.log(fn), np.log(s))
    return {"alpha": -slope, "r2": r2, "f_numbers": fn}


def _spectral(frames, adc_max, dark_mean, K):
    """Responsivity [e- per (W/mm^2/sr) per s] at each wavelength with known radiance."""
    rows = {}
    for f in frames:
        if f.kind == "light" and f.wavelength_nm is not None and f.radiance_w_per_mm2_sr:
            im = np.asarray(f.image, float)
            ok = im < adc_max
            if not ok.any() or f.exposure_s <= 0:
                continue
            e = (float(im[ok].mean()) - dark_mean(f.exposure_s)) / K
            rows.setdefault(float(f.wavelength_nm), []).append(e / (f.radiance_w_per_mm2_sr * f.exposure_s))
    if len(rows) < 2:
        return None
    return {"wavelength_nm": sorted(rows), "e_per_radiance_s": [float(np.mean(rows[w])) for w in sorted(rows)]}
