"""Sensor presets: the two cameras of the Airbus Robotic Telescope (ART).

Every number carries its unit in its name and its source in ``SOURCES``. The reference thesis (an image
simulator for ART) takes its detector values from the manufacturers' data sheets; the same data sheets are
cited here. Where a data sheet gives a range (gain settings, temperatures) the value used on ART is chosen
and the choice is stated. Any value can be overridden from the scene file's ``[detector]`` table.

QE curves are coarse tabulations (every 50 nm) read off the published curves; they are used as the mean
conversion of photons to photo-electrons *before* the single Poisson draw (thesis eqs. 30-31).
"""

from __future__ import annotations

PRESETS: dict[str, dict] = {
    "imx411": {
        "name": "imx411",
        "kind": "cmos",
        "sensor_width_px": 14192,
        "sensor_height_px": 10640,
        "pixel_pitch_um": 3.76,
        "shutter": "rolling",
        # Full-frame readout at about 2 frames/s (16-bit mode): 1 / (2 * 10640 rows) = 47 us per row.
        "line_time_s": 4.7e-5,
        "bit_depth": 16,
        "gain_e_per_adu": 1.22,  # 80 ke- full well over 16 bits at the lowest conversion gain
        "bias_adu": 500.0,  # user-set offset; 500 ADU keeps the read-noise tail above 0
        "read_noise_e": 3.5,  # at gain 0 (low conversion gain); 1.0 e- at high gain
        # data sheet, at -20 C. The thesis measures ART's camera at 0.0034-0.0036 ADU/s (-25..-15 C, Table 5),
        # 0.0042 e-/s at an assumed 1.22 e-/ADU, and quotes a declared 0.006 e-/s: docs/detector.md
        "dark_current_e_per_s": 0.0022,  # at -20 C
        "full_well_e": 80000.0,
        "temperature_c": -20.0,
        "qe_wavelength_nm": [350, 400, 450, 500, 550, 600, 650, 700, 750, 800, 850, 900, 950, 1000, 1050],
        "qe": [0.25, 0.55, 0.74, 0.80, 0.78, 0.72, 0.64, 0.55, 0.45, 0.36, 0.27, 0.19, 0.12, 0.06, 0.02],
    },
    "ml11002": {
        "name": "ml11002",
        "kind": "ccd",
        "sensor_width_px": 4008,
        "sensor_height_px": 2672,
        "pixel_pitch_um": 9.0,
        "shutter": "global",
        "line_time_s": 0.0,
        "bit_depth": 16,
        "gain_e_per_adu": 1.4,
        "bias_adu": 1000.0,
        # ART reads the CCD at 2 or 12 MHz (thesis Table 1); the thesis's fit to a real ART frame uses 10.64 e-
        # (Table 32); the bias frames' std is 12.98 ADU at both rates (Tables 2, 6)
        "read_noise_e": 11.0,
        "dark_current_e_per_s": 0.05,  # at -25 C (data sheet: 0.5 e-/s at 0 C, halving every ~6-7 C)
        "full_well_e": 50000.0,  # usable linear full well of the KAI-11002 (60 ke- saturation)
        "temperature_c": -25.0,
        "qe_wavelength_nm": [350, 400, 450, 500, 550, 600, 650, 700, 750, 800, 850, 900, 950, 1000, 1050],
        "qe": [0.10, 0.30, 0.45, 0.50, 0.48, 0.43, 0.37, 0.30, 0.23, 0.17, 0.11, 0.07, 0.04, 0.02, 0.01],
    },
}

SOURCES: dict[str, str] = {
    "imx411": (
        "Sony IMX411AQR data sheet and the QHY411M camera data sheet (QHYCCD, 2021): 14192x10640 active "
        "pixels of 3.76 um, rolling shutter, 16-bit ADC, full well ~80 ke-, read noise 3.5 e- at gain 0, "
        "dark current 0.0022 e-/px/s at -20 C (the thesis measures ~2x that on ART's unit, Table 5, in ADU), "
        "peak QE ~80 % near 500 nm. Row time "
        "from the ~2 fps full-frame 16-bit readout (thesis eq. 10 uses t_row = t_frame / N_rows). Checked "
        "against the thesis's Tables 1-8, 27: docs/detector.md."
    ),
    "ml11002": (
        "FLI MicroLine ML11002 data sheet (Finger Lakes Instrumentation) and the ON Semiconductor KAI-11002 "
        "interline CCD data sheet: 4008x2672 pixels of 9 um, global (electronic) shutter, 16-bit, read at 2 "
        "or 12 MHz on ART (thesis Table 1), read noise 11 e- (the thesis fits 10.64 e-, Table 32), usable "
        "full well 50 ke-, gain ~1.4 e-/ADU, dark current 0.05 e-/px/s at -25 C, peak QE ~50 % at 500 nm "
        "(monochrome, no microlens enhancement). Checked against the thesis's Tables 1-8, 32: docs/detector.md."
    ),
}


def preset_names() -> list[str]:
    return sorted(PRESETS)
