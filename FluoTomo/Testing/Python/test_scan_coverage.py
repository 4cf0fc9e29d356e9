"""The default scan covers every inclusion, and what a scan sees of each region
is said before any reconstruction (issue #31, item 8).

The scene is built here, not drawn from the family: a domed block 64 mm long
with two inclusions 34 mm apart under its top. The coverage screen (half-space
Green's functions, no mesh) is graded against the FEM on the project's own
simulation mesh: each region's share of the best pair's signal at equal yield,
from three noise-free simulations (yield in every label, in one inclusion, in
the other).
"""

from __future__ import annotations

import json

import numpy as np
import pytest

from FluoTomoLib.tomography import LabelMap, optics_from_dict, simulate_acquisition
from FluoTomoLib.tomography.coverage import scan_coverage
from FluoTomoLib.tomography.simulate import default_scan, scan_pairs

#: the screen's share against the FEM's, as a ratio: the screen ignores the
#: inclusions' own optics and the dome's curvature (measured 1.15-1.5)
SHARE_FACTOR = 2.0


def _optics():
    p = lambda a, b: {"mua_per_mm": a, "musp_per_mm": b}                  # noqa: E731
    return optics_from_dict({"n": 1.37,
                             "excitation": {"3": p(0.01, 1.0), "7": p(0.012, 1.1),
                                            "8": p(0.012, 1.1)},
                             "emission": {"3": p(0.008, 0.9), "7": p(0.009, 1.0),
                                          "8": p(0.009, 1.0)}})


@pytest.fixture(scope="module")
def scene():
    sp = 0.8
    k, j, i = np.indices((40, 50, 90))
    x, y, z = (i + 0.5) * sp, (j + 0.5) * sp, (k + 0.5) * sp
    top = 26.0 - 0.004 * (x - 36) ** 2
    body = (x > 4) & (x < 68) & (y > 4) & (y < 36) & (z > 4) & (z < top)
    lab = np.where(body, 3, 0).astype(np.uint8)
    for c, r, v in (((22, 20, 26.0 - 0.004 * 14 ** 2 - 5.0), 3.0, 7),
                    ((56, 20, 26.0 - 0.004 * 20 ** 2 - 4.0), 2.5, 8)):
        lab[((x - c[0]) ** 2 + (y - c[1]) ** 2 + (z - c[2]) ** 2 < r * r) & body] = v
    # LPS-like direction and an origin far from zero: nothing may assume RAS
    lm = LabelMap(lab, np.array([sp] * 3), np.array([130.0, 60.0, -80.0]),
                  np.diag([-1.0, -1.0, 1.0]))
    return lm, _optics()


def _fem_shares(lm, optics, targets):
    kw = dict(noise_pct=0.0, accuracy="fast", scan_targets=targets)
    every, info = simulate_acquisition(lm, optics, {3: 1.0, 7: 1.0, 8: 1.0}, **kw)
    m = every.mask
    shares = {}
    for lab in (7, 8):
        one, _ = simulate_acquisition(lm, optics, {lab: 1.0}, **kw)
        shares[lab] = float(np.max(one.clean[m] / every.clean[m]))
    return shares, info, every


def test_the_default_scan_covers_every_inclusion(scene):
    lm, optics = scene
    assert lm.inclusion_labels() == [8, 7]                  # smallest first
    src, det, cfg = default_scan(lm, [8, 7])
    assert len(cfg["patches"]) == 2 and len(src) == 32 and len(det) == 98
    pairs = scan_pairs(cfg, len(src), len(det))
    assert pairs.sum() == 2 * 16 * 49                       # no pair across patches
    for n, lab in enumerate((8, 7)):
        # each patch lies over its own inclusion, not over the other
        centre = np.asarray(cfg["patches"][n]["centre_ras_mm"])
        own = lm.to_ras(lm.region_centroid_local(lab))[0]
        assert np.linalg.norm((centre - own)[:2]) < 2.0


@pytest.mark.slow      # three FEM simulations: 18 s alone on 2 cores
def test_the_screen_against_the_fem(scene):
    """One target scanned: the far inclusion is not seen, said in the warnings
    (naming it) before anything is solved; the screen's shares within
    SHARE_FACTOR of the FEM's."""
    lm, optics = scene
    fem, info, acq = _fem_shares(lm, optics, [7])
    cov = info["scan_coverage"]["regions"]
    for lab in (7, 8):
        ratio = cov[str(lab)]["share"] / fem[lab]
        assert 1 / SHARE_FACTOR < ratio < SHARE_FACTOR, (lab, cov[str(lab)], fem[lab])
    assert fem[8] < 1e-6 < 0.05 < fem[7]
    # at the data's 1 % noise the far inclusion needs more contrast than any dye gives
    at1 = scan_coverage(lm, optics, acq.sources_ras_mm, acq.detectors_ras_mm, acq.mask, 1.0)
    assert at1["regions"]["7"]["seen"] and not at1["regions"]["8"]["seen"]
    assert at1["regions"]["8"]["nearest_optode_mm"] > 20
    assert len(at1["warnings"]) == 1 and "region 8" in at1["warnings"][0]
    json.dumps(at1, allow_nan=False)                        # the JSON stays strict


def test_the_default_scan_sees_both(scene):
    lm, optics = scene
    fem, info, acq = _fem_shares(lm, optics, None)
    cov = info["scan_coverage"]["regions"]
    for lab in (7, 8):
        assert cov[str(lab)]["seen"] and cov[str(lab)]["pairs_seeing"] > 100
        assert 1 / SHARE_FACTOR < cov[str(lab)]["share"] / fem[lab] < SHARE_FACTOR
        assert fem[lab] > 0.05
    assert not any("does not see" in w for w in info["warnings"])
    assert acq.mask.sum() <= 2 * 16 * 49
