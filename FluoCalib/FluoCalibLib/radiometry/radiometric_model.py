"""Radiometric camera model: counts [ADU] <-> radiance [W/mm^2/sr], and noise.

Reference: docs/physics.md section 5.1::

    G = (pi/4) f#^-alpha_lens * T_filter * dt * A_pix * b^2 * (lambda/(h c)) * QE * g_adc
    S = G L + offset,   offset = g_adc (bias_e + I_dark dt)

Noise in electrons: shot sqrt(Ne), dark sqrt(I_d dt), read sigma_r.
The defaults are the thesis camera (PCO Pixelfly USB behind the ICG emission
filter): 1392 x 1040, 6.45 um pixels, 14 bit, QE 15 % at 760 nm, filter
transmittance 0.52, f/1.4, 1.08 ADU/e-, dark 1.1 e-/s, bias 200.3 e-,
read noise 5.6 e-, DR 2821.

Every conversion from counts flags pixels that must not be used: saturated
(at or above the A/D ceiling or the full well) and under-range (signal not above
the offset by ``min_snr`` read-noise sigmas).  Callers get those masks back and
decide; no function silently uses a flagged pixel.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, replace

import numpy as np

from fluoguide.errors import FluoInputError

__all__ = ["PLANCK_J_S", "LIGHT_SPEED_M_PER_S", "RadiometricCamera", "photon_energy_j"]

PLANCK_J_S = 6.62607015e-34
LIGHT_SPEED_M_PER_S = 299792458.0


def photon_energy_j(wavelength_nm):
    """Energy of one photon [J] at ``wavelength_nm``."""
    return PLANCK_J_S * LIGHT_SPEED_M_PER_S / (np.asarray(wavelength_nm, float) * 1e-9)


@dataclass(frozen=True)
class RadiometricCamera:
    """Counts <-> radiance for one camera, lens, filter and exposure setting."""

    exposure_s: float = 0.1
    f_number: float = 1.4
    lens_exponent: float = 2.0  # alpha of (pi/4) f#^-alpha; thesis best fit 1.88
    filter_transmittance: float = 0.52
    pixel_pitch_mm: float = 6.45e-3
    binning: int = 1
    wavelength_nm: float = 760.0  # where the reference quotes QE 15 %
    quantum_efficiency: float = 0.15
    gain_adu_per_e: float = 1.08
    bias_e: float = 200.3
    dark_current_e_per_s: float = 1.1
    read_noise_e: float = 5.6
    full_well_e: float = 16000.0
    bit_depth: int = 14

    def __post_init__(self):
        for name in ("f_number", "filter_transmittance", "pixel_pitch_mm",
                     "wavelength_nm", "quantum_efficiency", "gain_adu_per_e", "full_well_e"):
            v = getattr(self, name)
            if not np.isfinite(v) or v <= 0:
                raise FluoInputError(f"must be a positive finite number", field=name, value=v)
        for name in ("exposure_s", "bias_e", "dark_current_e_per_s", "read_noise_e"):
            v = getattr(self, name)
            if not np.isfinite(v) or v < 0:
                raise FluoInputError("must be a finite number >= 0", field=name, value=v)
        if int(self.binning) < 1:
            raise FluoInputError("must be an integer >= 1", field="binning", value=self.binning)
        if not 1 <= int(self.bit_depth) <= 32:
            raise FluoInputError("must be between 1 and 32", field="bit_depth", value=self.bit_depth)

    # -- factors -------------------------------------------------------------
    @property
    def adc_max_adu(self):
        """Largest count the A/D converter can report."""
        return float(2 ** int(self.bit_depth) - 1)

    @property
    def offset_adu(self):
        """Bias plus dark signal for this exposure [ADU]."""
        return self.gain_adu_per_e * (self.bias_e + self.dark_current_e_per_s * self.exposure_s)

    def electrons_per_radiance(self):
        """Photo-electrons per pixel per unit radiance [e- / (W/mm^2/sr)]."""
        solid = (np.pi / 4.0) * self.f_number ** (-self.lens_exponent)
        area = self.pixel_pitch_mm ** 2 * self.binning ** 2
        photons_per_j = 1.0 / photon_energy_j(self.wavelength_nm)
        return (solid * self.filter_transmittance * self.exposure_s * area * photons_per_j
                * self.quantum_efficiency)

    def gain_adu_per_radiance(self):
        """G of the reference: counts per unit radiance [ADU / (W/mm^2/sr)]."""
        return self.electrons_per_radiance() * self.gain_adu_per_e

    def with_(self, **changes):
        """A copy with some settings changed (e.g. another exposure)."""
        return replace(self, **changes)

    def to_dict(self):
        return {k: float(v) if isinstance(v, (float, np.floating)) else v for k, v in asdict(self).items()}

    @classmethod
    def from_dict(cls, doc):
        known = {k: doc[k] for k in cls.__dataclass_fields__ if k in doc}
        return cls(**known)

    # -- conversions ---------------------------------------------------------
    def counts_from_radiance(self, radiance_w_per_mm2_sr):
        """Noise-free expected counts [ADU] (not clipped)."""
        return self.gain_adu_per_radiance() * np.asarray(radiance_w_per_mm2_sr, float) + self.offset_adu

    def radiance_from_counts(self, counts_adu, min_snr=0.0):
        """Radiance [W/mm^2/sr] from counts, with the masks of pixels not to use.

        Returns ``(radiance, valid, saturated, under_range)``; ``radiance`` is
        NaN where not valid.  ``under_range`` marks pixels whose signal above
        the offset is below ``min_snr`` times the read noise (in ADU) or
        negative.
        """
        if self.exposure_s <= 0:
            raise FluoInputError("a zero exposure carries no radiance information",
                                 field="exposure_s", value=self.exposure_s)
        s = np.asarray(counts_adu, float)
        signal = s - self.offset_adu
        saturated = (s >= self.adc_max_adu) | (signal >= self.full_well_e * self.gain_adu_per_e)
        floor = max(min_snr, 0.0) * self.read_noise_e * self.gain_adu_per_e
        under = ~np.isfinite(s) | (signal <= floor) if min_snr > 0 else ~np.isfinite(s) | (signal < 0)
        valid = ~saturated & ~under
        radiance = np.where(valid, signal, np.nan) / self.gain_adu_per_radiance()
        return radiance, valid, saturated, under

    def exitance_from_radiance(self, radiance_w_per_mm2_sr):
        """Lambertian surface exitance (flux leaving the surface) J = pi L [W/mm^2]."""
        return np.pi * np.asarray(radiance_w_per_mm2_sr, float)

    # -- noise ---------------------------------------------------------------
    def noise_e(self, signal_e):
        """Total noise sigma [e-] for a photo-signal of ``signal_e`` electrons."""
        ne = np.maximum(np.asarray(signal_e, float), 0.0)
        return np.sqrt(ne + self.dark_current_e_per_s * self.exposure_s + self.read_noise_e ** 2)

    def snr(self, signal_e):
        """SNR = Ne / sqrt(Ne + I_d dt + sigma_r^2)."""
        ne = np.maximum(np.asarray(signal_e, float), 0.0)
        return ne / self.noise_e(ne)

    def dynamic_range(self):
        """DR = (N_well - N_bias) / sigma_r (dimensionless; 20 log10 for dB)."""
        if self.read_noise_e == 0:
            return np.inf
        return (self.full_well_e - self.bias_e) / self.read_noise_e

    def sample_counts(self, radiance_w_per_mm2_sr, rng=None):
        """One noisy frame [ADU]: Poisson shot and dark, Gaussian read, quantised, clipped."""
        rng = np.random.default_rng(rng)
        lam = np.maximum(self.electrons_per_radiance() * np.asarray(radiance_w_per_mm2_sr, float), 0.0)
        photo = rng.poisson(lam).astype(float)
        dark = rng.poisson(self.dark_current_e_per_s * self.exposure_s, size=photo.shape)
        electrons = np.minimum(photo + dark, self.full_well_e) + self.bias_e
        electrons = electrons + rng.normal(0.0, self.read_noise_e, size=photo.shape)
        counts = np.round(electrons * self.gain_adu_per_e)
        return np.clip(counts, 0.0, self.adc_max_adu)
