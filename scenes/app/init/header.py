"""What a FITS header says about the camera and the observation, in the conventions cameras and
observatories write (MaxIm DL / SBIG / ASCOM / N.I.N.A. / ZWO, IRAF, observatory pipelines).

Every value comes back as a :class:`Value` (value, source, card): ``source`` is ``"header"`` when a card
gave it, ``"measured"`` when the data did (bit depth and saturation), ``"assumed"`` otherwise, so a
scene written from it can say where each number came from.
"""

from __future__ import annotations

import math
import re
from dataclasses import asdict, dataclass
from typing import Any

import numpy as np


@dataclass
class Value:
    """A number (or text) and where it came from: ``source`` in measured | header | assumed."""

    value: Any
    source: str
    card: str | None = None
    note: str | None = None

    def to_json(self) -> dict:
        return {k: v for k, v in asdict(self).items() if v is not None}


def number(v) -> float | None:
    """A card's value as a float: numbers, and numbers written as strings ('2.06', ' 1.5E-3 '); None otherwise."""
    if isinstance(v, bool) or v is None:
        return None
    if isinstance(v, (int, float, np.integer, np.floating)):
        return float(v) if math.isfinite(float(v)) else None
    try:
        f = float(str(v).strip().replace("D", "E"))
    except ValueError:
        return None
    return f if math.isfinite(f) else None


def first(header, cards, convert=number) -> tuple[Any, str | None]:
    """The first of ``cards`` present in ``header`` whose value converts (``convert``): (value, card)."""
    for c in cards:
        if c in header:
            v = convert(header[c])
            if v is not None:
                return v, c
    return None, None


def sexagesimal(v) -> float | None:
    """Degrees from a number or a sexagesimal string ('+19 32 09.7', '-155:34:34', '19d32m09s');
    sign taken from the first character so that '-00 30' stays negative."""
    f = number(v)
    if f is not None:
        return f
    if not isinstance(v, str):
        return None
    s = v.strip()
    neg = s.startswith("-")
    parts = [p for p in re.split(r"[\s:dDhHmMsS'\"°]+", s.lstrip("+-")) if p]
    try:
        nums = [float(p) for p in parts]
    except ValueError:
        return None
    if not nums or len(nums) > 3:
        return None
    d = sum(x / 60.0 ** i for i, x in enumerate(nums))
    return -d if neg else d


#: GAIN cards of some cameras are a setting (ZWO / QHY "gain 80"), not e-/ADU: GAIN is read as e-/ADU only when
#: its comment says so or it is a small non-integer
_E_PER_ADU = re.compile(r"e-?\s*/\s*(adu|dn|count)|electrons?\s*(per|/)\s*(adu|dn|count)", re.IGNORECASE)


def header_gain(header) -> Value:
    """Gain [e-/ADU]: ``EGAIN`` (MaxIm DL, SBIG, N.I.N.A.), ``E-GAIN``, ``GAINE``, else ``GAIN`` when its comment
    says e-/ADU or it is a small non-integer (a ZWO/QHY ``GAIN = 80`` is a gain setting)."""
    for c in ("EGAIN", "E-GAIN", "GAINE", "CCDGAIN"):
        v = number(header.get(c))
        if v is not None and 0 < v < 1000:
            return Value(v, "header", c)
    unset = None
    if "GAIN" in header:
        v = number(header["GAIN"])
        comment = header.comments["GAIN"] if hasattr(header, "comments") else ""
        if v is not None and 0 < v < 1000 and (_E_PER_ADU.search(comment or "") or (v < 20 and v != round(v))):
            return Value(v, "header", "GAIN")
        if v == 0:  # HSC writes GAIN = 0.000 [electron/ADU]: not set (its amplifiers' gains are T_GAIN1..4)
            unset = "GAIN = 0: not set"
        elif v is not None:
            return Value(None, "assumed", "GAIN", note=f"GAIN = {v:g} read as a camera setting, not e-/ADU")
    amps = amplifier_gains(header)
    if amps:  # a multi-amplifier CCD (DECam GAINA/GAINB, HSC T_GAIN1..4): the frame may hold any of them
        vals = list(amps.values())
        return Value(float(np.mean(vals)), "header", "/".join(amps),
                     note=(f"{unset}; " if unset else "") + "mean of the amplifiers' gains "
                     + ", ".join(f"{k} = {v:g}" for k, v in amps.items()))
    return Value(None, "assumed", note=unset)


_AMP_GAIN = re.compile(r"^(T_)?GAIN_?([A-H]|[1-9][0-9]?)$")


def amplifier_gains(header) -> dict[str, float]:
    """Per-amplifier gains [e-/ADU] the header gives: ``GAINA``, ``GAINB`` ... (DECam, Mosaic), ``T_GAIN1`` ...
    (Subaru HSC), ``GAIN1`` ...; card -> value."""
    out = {}
    for k in header:
        if _AMP_GAIN.match(str(k)):
            v = number(header[k])
            if v is not None and 0 < v < 1000:
                out[str(k)] = float(v)
    return out


def binning(header) -> Value:
    """Binning factor (square): XBINNING/YBINNING, CCDSUM ('2 2'), BINX/BINY, else 1."""
    v, c = first(header, ("XBINNING", "BINX", "HBIN", "CCDXBIN"))
    if v is None and "CCDSUM" in header:
        parts = str(header["CCDSUM"]).split()
        if parts and number(parts[0]) is not None:
            v, c = number(parts[0]), "CCDSUM"
    if v is None:
        return Value(1, "assumed")
    vy, cy = first(header, ("YBINNING", "BINY", "VBIN", "CCDYBIN"))
    note = None
    if vy is not None and vy != v:
        note = f"{c} = {v:g} but {cy} = {vy:g}: the scene's binning is square ({v:g})"
    return Value(int(v), "header", c, note)


def read_header(header, data: np.ndarray | None = None) -> dict[str, Value]:
    """Every camera/observation value a header gives (see the module docstring); ``data`` (the raw image) for
    the bit depth and the saturation level seen."""
    out: dict[str, Value] = {}

    def get(name, cards, convert=number, check=lambda v: True):
        v, c = first(header, cards, convert)
        out[name] = Value(v, "header", c) if v is not None and check(v) else Value(None, "assumed")

    out["gain_e_per_adu"] = header_gain(header)
    out["binning"] = binning(header)
    get("exptime_s", ("EXPTIME", "EXPOSURE", "ITIME", "EXP_TIME", "TELAPSE"), check=lambda v: v >= 0)
    get("temperature_c", ("CCD-TEMP", "CCD_TEMP", "CCDTEMP", "DET-TEMP", "SENSOR-TEMP", "CAMTEMP", "TEMPERAT", "SET-TEMP"),
        check=lambda v: -200 < v < 150)
    get("pixel_pitch_um", ("XPIXSZ", "PIXSIZE1", "PIXSIZE", "PIXSZ", "XPIXELSZ", "PIXELSIZE"), check=lambda v: 0.5 < v < 100)
    # MaxIm DL / ASCOM: XPIXSZ includes the binning; PIXSIZE1 (N.I.N.A.) too
    if out["pixel_pitch_um"].value is not None and out["binning"].value > 1 and out["pixel_pitch_um"].card in ("XPIXSZ", "PIXSIZE1"):
        pv = out["pixel_pitch_um"]
        out["pixel_pitch_um"] = Value(pv.value / out["binning"].value, "header", pv.card,
                                      note=f"{pv.card} = {pv.value:g} um includes the {out['binning'].value}x binning")
    get("focal_length_mm", ("FOCALLEN", "FOCAL", "FOCLEN"), check=lambda v: v > 0)
    get("aperture_mm", ("APTDIA", "APERTURE", "DIAMETER"), check=lambda v: v > 0)
    get("read_noise_e", ("RDNOISE", "READNOIS", "RON", "RDNOISEA"), check=lambda v: 0 < v < 1000)
    get("saturate_adu", ("SATURATE", "SATLEVEL", "DATAMAX", "SATURATA"), check=lambda v: v > 0)
    get("full_well_e", ("FULLWELL", "FULLWEL", "WELLDPTH"), check=lambda v: v > 0)
    get("bias_adu", ("PEDESTAL", "BLKLEVEL", "OFFSET_ADU", "BIAS"), check=lambda v: v >= 0 or True)
    if out["bias_adu"].card == "PEDESTAL" and out["bias_adu"].value is not None:  # MaxIm: PEDESTAL is negative
        out["bias_adu"] = Value(abs(out["bias_adu"].value), "header", "PEDESTAL")
    # observation time: DATE-OBS (ISO, or DD/MM/YY with TIME-OBS), MJD-OBS, JD
    out["date_obs"] = _date_obs(header)
    # site: SITELAT/SITELONG (MaxIm, sexagesimal), LAT-OBS/LONG-OBS, OBSGEO-B/L/H (FITS WCS paper VII), OBSGEO-X/Y/Z
    out["site"] = _site(header)
    f, c = first(header, ("FILTER", "FILTER1", "FILTNAME", "FLTNAME", "BAND"), convert=lambda v: str(v).strip() or None)
    out["filter"] = Value(f, "header", c) if f else Value(None, "assumed")
    x0, cx = first(header, ("XORGSUBF", "XORGSUB"))
    y0, cy = first(header, ("YORGSUBF", "YORGSUB"))
    if x0 is None and "LTV1" in header:
        x0, cx = -number(header["LTV1"]), "LTV1"
        y0, cy = -(number(header.get("LTV2")) or 0.0), "LTV2"
    out["window_origin"] = (Value([round(x0), round(y0 or 0)], "header", f"{cx}/{cy}") if x0 is not None
                            else Value([0, 0], "assumed"))
    pat, c = first(header, ("BAYERPAT", "COLORTYP", "CFA-PAT", "BAYER"), convert=lambda v: str(v).strip().upper() or None)
    out["bayer"] = (Value(pat, "header", c) if pat in ("RGGB", "BGGR", "GRBG", "GBRG") else Value(None, "assumed"))
    if out["bayer"].value is None:  # a DSLR's raw frame (gphoto2 / PANOPTES): white balance given per RGGB cell
        card = next((k for k in ("WBRGGB", "MEASRGGB") if k in header), None)
        if card:
            out["bayer"] = Value("RGGB", "header", card, note=f"{card}: white balance of RGGB cells (a raw DSLR frame)")
    typ, c = first(header, ("IMAGETYP", "IMAGETYPE", "OBSTYPE", "FRAMETYP", "FRAME"), convert=lambda v: str(v).strip().lower() or None)
    kind = "light"
    if typ:
        kind = ("bias" if ("bias" in typ or "zero" in typ) else "dark" if "dark" in typ
                else "flat" if "flat" in typ else "light")
    out["frame_type"] = Value(kind, "header" if typ else "assumed", c)
    for name, cards in (("telescope", ("TELESCOP",)), ("instrument", ("INSTRUME", "CAMERA")), ("object", ("OBJECT",))):
        v, c = first(header, cards, convert=lambda v: str(v).strip() or None)
        out[name] = Value(v, "header", c) if v else Value(None, "assumed")
    if data is not None:
        out.update(data_levels(header, data))
    return out


def data_levels(header, data: np.ndarray) -> dict[str, Value]:
    """Bit depth and saturation level from the data: the maximum value when a pile of pixels sits exactly at
    it (a clipped ADC or full well), else the header's SATURATE / the bit depth's top."""
    finite = data[np.isfinite(data)]
    top = float(finite.max()) if finite.size else 0.0
    integer = bool(finite.size) and bool(np.all(finite[: 100000] == np.round(finite[: 100000])))
    bitpix = int(header.get("BITPIX", 16))
    if integer and top > 0:
        bits = max(8, math.ceil(math.log2(top + 1)))
        bits = min(bits, 16 if abs(bitpix) <= 16 or bitpix == -32 else 32)
        depth = Value(bits, "measured", note=f"maximum value {top:.0f} ADU (BITPIX {bitpix})")
    else:
        depth = Value(16, "assumed", note=f"floating-point data (BITPIX {bitpix})")
    n_top = int(np.count_nonzero(finite >= top)) if finite.size else 0
    # a clipped full well seen through the read noise: a pile of pixels within 0.3 % below the maximum
    near = finite[finite >= top - 0.003 * abs(top)] if finite.size else finite
    fw = number(header.get("FULLWELL"))
    pile = _clip_pile(finite, top) if integer and n_top < 5 and top > 0 else None
    if n_top >= 5 and top > 0:
        sat = Value(top, "measured", note=f"{n_top} pixels at the maximum {top:.0f} ADU")
    elif pile is not None:
        lv, n_lv, n_above = pile
        sat = Value(lv, "measured", note=f"{n_lv} pixels at {lv:.0f} ADU, the clip of the saturated stars ({n_above} "
                    f"isolated pixels above it, up to {top:.0f} ADU: hot pixels read after the clip, not the level)")
    elif near.size >= 8 and top > 0 and (fw is None):
        sat = Value(float(np.median(near)), "measured", note=f"{near.size} pixels within 0.3 % of the maximum "
                    f"{top:.0f} ADU (a clipped full well under the read noise)")
    else:
        v, c = first(header, ("SATURATE", "SATLEVEL"))
        sat = Value(v, "header", c) if v else Value(float(2 ** depth.value - 1), "assumed",
                                                     note="no pixel pile at the maximum: the bit depth's top")
    if sat.source == "measured":
        # both levels count: the header's (the camera's or the pipeline's own limit, e.g. the full well below
        # the ADC's top) and the clip seen in the data; the lower one is where saturation begins, and a
        # disagreement is said, not hidden
        v, c = first(header, ("SATURATE", "SATLEVEL"))
        if v and v < sat.value:
            sat = Value(float(v), "header", c, note=f"{c} = {v:g} ADU, below the clip seen in the data ({sat.value:.0f} "
                        f"ADU: {sat.note}): the pixels between are saturated or non-linear")
        elif v and v > sat.value:
            sat = Value(sat.value, "measured", note=f"{sat.note}; the header's {c} = {v:g} ADU is above it (the data "
                        "clip first)")
    return {"bit_depth": depth, "saturation_adu": sat}


def _clip_pile(values: np.ndarray, top: float, min_pile: int = 5) -> tuple[float, int, int] | None:
    """A clipped level below the maximum of integer data: the value of the upper tail (the top 30 % of the
    range above the median) that holds at least ``min_pile`` pixels and 10 x the count of any other value
    there, with fewer pixels above it than on it (a DSLR's white level: PANOPTES's saturated stars all read
    13 583 ADU, three hot pixels 13 639-13 863). Returns (level, pixels on it, pixels above it) or None."""
    med = float(np.median(values))
    tail = values[values >= med + 0.7 * (top - med)]
    if tail.size < min_pile:
        return None
    v, c = np.unique(tail, return_counts=True)
    i = int(np.argmax(c))
    others = np.delete(c, i)
    n_above = int(np.count_nonzero(tail > v[i]))
    if c[i] >= min_pile and (others.size == 0 or c[i] >= 10 * others.max()) and n_above < c[i]:
        return float(v[i]), int(c[i]), n_above
    return None


def _date_obs(header) -> Value:
    import warnings

    from astropy.time import Time

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        d = header.get("DATE-OBS") or header.get("DATE_OBS")
        if isinstance(d, str) and d.strip():
            s = d.strip()
            m = re.match(r"^(\d{2})/(\d{2})/(\d{2,3})$", s)
            if m:  # old DD/MM/YY form (with TIME-OBS / UT)
                dd, mm, yy = (int(g) for g in m.groups())
                year = 1900 + yy if yy < 1000 else yy
                s = f"{year:04d}-{mm:02d}-{dd:02d}"
            if "T" not in s and len(s) <= 10:
                t = header.get("TIME-OBS") or header.get("UT") or header.get("UTSTART")
                s = f"{s}T{str(t).strip()}" if t else f"{s}T00:00:00"
            try:
                return Value(Time(s.replace(" ", "T"), format="isot", scale="utc").isot[:19], "header", "DATE-OBS")
            except ValueError:
                pass
        for card, fmt in (("MJD-OBS", "mjd"), ("MJD", "mjd"), ("JD", "jd")):
            v = number(header.get(card))
            if v is not None:
                t = Time(v, format=fmt, scale="utc")
                note = None
                if card == "JD":  # MaxIm: JD is the exposure's mid or end: stated, not corrected
                    note = "JD taken as the start of the exposure"
                return Value(t.isot[:19], "header", card, note)
    return Value("2023-02-01T22:00:00", "assumed", note="no DATE-OBS / MJD-OBS / JD: the scene's default epoch")


def _site(header) -> Value:
    lat, clat = first(header, ("SITELAT", "LAT-OBS", "OBSGEO-B", "LATITUDE", "OBSLAT"), convert=sexagesimal)
    lon, clon = first(header, ("SITELONG", "LONG-OBS", "OBSGEO-L", "LONGITUD", "OBSLONG", "LONGITUDE"), convert=sexagesimal)
    h, ch = first(header, ("SITEELEV", "ALT-OBS", "ELEV-OBS", "OBSGEO-H", "ELEVATIO", "OBSELEV"))
    if lat is None and all(k in header for k in ("OBSGEO-X", "OBSGEO-Y", "OBSGEO-Z")):
        import astropy.units as u
        from astropy.coordinates import EarthLocation

        loc = EarthLocation.from_geocentric(*(number(header[k]) for k in ("OBSGEO-X", "OBSGEO-Y", "OBSGEO-Z")), unit=u.m)
        return Value({"lat_deg": float(loc.lat.deg), "lon_deg": float(loc.lon.deg), "height_m": float(loc.height.to_value(u.m))},
                     "header", "OBSGEO-X/Y/Z")
    if lat is None or lon is None:
        return Value(None, "assumed")
    return Value({"lat_deg": lat, "lon_deg": lon, "height_m": h if h is not None else 0.0}, "header",
                 f"{clat}/{clon}" + (f"/{ch}" if ch else ""))
