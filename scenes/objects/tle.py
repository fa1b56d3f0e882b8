"""Two-line element sets (TLE): strict parsing, file look-up, SGP4 propagation in TEME.

A TLE is the mean-element set of the US Space Force catalogue, meaningful only with the SGP4/SDP4 theory
that produced it (Hoots & Roehrich 1980, Spacetrack Report #3; Vallado, Crawford, Hujsak & Kelso 2006,
"Revisiting Spacetrack Report #3", AIAA 2006-6753). Propagation uses the ``sgp4`` package (Rhodes), which
implements Vallado's 2006 code and returns positions and velocities in the TEME frame (True Equator, Mean
Equinox of date) in km and km/s, for UTC Julian dates.

The fixed-column format (CelesTrak, "NORAD Two-Line Element Set Format") is checked here because
``sgp4.api.Satrec.twoline2rv`` silently reads malformed lines as zeros: line lengths, line numbers, the
modulo-10 checksum (digits count their value, ``-`` counts 1, everything else 0), matching catalogue
numbers, and every numeric field the propagator uses.
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .errors import ObjectError

# (name, line, first column, last column) (1-based, inclusive), CelesTrak's TLE format description
_FIELDS_1 = [("epoch (YYDDD.DDDDDDDD)", 19, 32, "float"), ("first derivative of the mean motion", 34, 43, "float"),
             ("second derivative of the mean motion", 45, 52, "exp"), ("BSTAR drag term", 54, 61, "exp")]
_FIELDS_2 = [("inclination [deg]", 9, 16, "float"), ("right ascension of the ascending node [deg]", 18, 25, "float"),
             ("eccentricity (decimal point assumed)", 27, 33, "digits"), ("argument of perigee [deg]", 35, 42, "float"),
             ("mean anomaly [deg]", 44, 51, "float"), ("mean motion [rev/day]", 53, 63, "float")]
_FLOAT = re.compile(r"^[+-]?(\d+\.?\d*|\.\d+)$")
_EXP = re.compile(r"^[+-]?\d+[+-]\d$")  # "-11606-4", " 00000-0", "00000+0" (decimal point assumed)

_SGP4_ERRORS = {
    1: "mean eccentricity outside [0, 1) or semi-major axis below 0.95 Earth radii",
    2: "mean motion below zero",
    3: "perturbed eccentricity outside [0, 1]",
    4: "semi-latus rectum below zero",
    5: "epoch elements are sub-orbital",
    6: "orbit radius below one Earth radius",
}


def tle_checksum(line: str) -> int:
    """The TLE modulo-10 checksum of the first 68 characters (digits by value, ``-`` as 1)."""
    return sum(int(c) if c.isdigit() else (1 if c == "-" else 0) for c in line[:68]) % 10


def _check_line(line: str, number: int, key: str, file: str | None, ctx: str = "") -> str:
    line = line.rstrip()
    where = f"{ctx}line {number}"
    if len(line) != 69:
        raise ObjectError(f"{where} has {len(line)} characters", key=key, file=file,
                          expected="69 characters in the fixed-column NORAD two-line format")
    if line[0] != str(number) or line[1] != " ":
        raise ObjectError(f"{where} starts with {line[:2]!r}", key=key, file=file,
                          expected=f"a line starting with '{number} '")
    if not line[68].isdigit() or tle_checksum(line) != int(line[68]):
        raise ObjectError(f"{where}: checksum {line[68]!r} does not match the computed {tle_checksum(line)}",
                          key=key, file=file, expected="a valid modulo-10 checksum in column 69")
    fields = _FIELDS_1 if number == 1 else _FIELDS_2
    for name, c0, c1, kind in fields:
        text = line[c0 - 1:c1]
        stripped = text.strip()
        ok = {"float": _FLOAT.match(stripped), "exp": _EXP.match(stripped), "digits": stripped.isdigit()}[kind]
        if not ok:
            raise ObjectError(f"{where} columns {c0}-{c1} ({name}) read {text!r}", key=key, file=file,
                              expected="a number in the fixed-column NORAD two-line format")
    return line


@dataclass(frozen=True)
class Tle:
    """A checked two-line element set (``name`` from a three-line set's title line, may be None)."""

    line1: str
    line2: str
    name: str | None = None

    @property
    def norad_id(self) -> str:
        """The catalogue number as written (5 characters, Alpha-5 allowed)."""
        return self.line1[2:7].strip()

    def satrec(self):
        """The ``sgp4`` satellite record (a fresh object, so no state is shared between callers)."""
        from sgp4.api import Satrec

        return Satrec.twoline2rv(self.line1, self.line2)

    @property
    def epoch_jd(self) -> float:
        """The element-set epoch [UTC Julian date]."""
        sat = self.satrec()
        return float(sat.jdsatepoch + sat.jdsatepochF)


def parse_tle(text, *, key: str = "tle", file: str | None = None, context: str = "",
              check_sgp4: bool = True) -> Tle:
    """A :class:`Tle` from two lines, or three with a title line (a string with newlines, or a list).

    Raises :class:`ObjectError` naming ``key`` for a malformed set (length, line number, checksum, a field
    that is not a number, catalogue numbers that differ) and, with ``check_sgp4``, for elements SGP4
    rejects at their epoch. ``context`` prefixes the message (e.g. the file and set number).
    """
    ctx = f"{context}: " if context else ""
    lines = text.splitlines() if isinstance(text, str) else list(text) if isinstance(text, (list, tuple)) else None
    if lines is None or not all(isinstance(x, str) for x in lines):
        raise ObjectError(f"{ctx}the TLE is not text: {text!r}"[:200], key=key, file=file,
                          expected="two (or three) strings")
    lines = [x.rstrip() for x in lines if x.strip()]
    name = None
    if len(lines) == 3:
        name, lines = lines[0].strip(), lines[1:]
        name = name[2:].strip() if name.startswith("0 ") else name
    if len(lines) != 2:
        raise ObjectError(f"{ctx}got {len(lines)} non-empty lines", key=key, file=file,
                          expected="a two-line element set (optionally preceded by a title line)")
    l1 = _check_line(lines[0], 1, key, file, ctx)
    l2 = _check_line(lines[1], 2, key, file, ctx)
    if l1[2:7] != l2[2:7]:
        raise ObjectError(f"{ctx}catalogue numbers differ: line 1 {l1[2:7]!r}, line 2 {l2[2:7]!r}", key=key,
                          file=file, expected="the same satellite number in columns 3-7 of both lines")
    tle = Tle(l1, l2, name)
    return _checked(tle, key, file, context) if check_sgp4 else tle


def _error_text(tle: Tle, code: int, days: float) -> str:
    msg = f"SGP4 error {code} ({_SGP4_ERRORS.get(code, 'unknown error')}) {days:+.3f} days from the element epoch"
    if code in (1, 6):
        label = f"{tle.norad_id} ({tle.name})" if tle.name else tle.norad_id
        msg = f"satellite {label} has decayed: {msg}"
    return msg


def load_tle(path, satellite=None, *, key: str = "tle_file", file: str | None = None) -> Tle:
    """Read one element set from a TLE file (two- or three-line sets, any number of satellites).

    Parameters
    ----------
    path : str or Path
        The file.
    satellite : int or str, optional
        Catalogue (NORAD) number, or the satellite's name from the title line (case-insensitive; an exact
        match wins over a unique substring match). Needed when the file holds more than one set.
    """
    p = Path(path)
    try:
        raw = [x.rstrip() for x in p.read_text().splitlines() if x.strip()]
    except (OSError, UnicodeDecodeError) as exc:
        raise ObjectError(f"cannot read the TLE file {str(p)!r} ({exc})", key=key, file=file,
                          expected="a readable text file of two- or three-line element sets") from None
    sets, i = [], 0
    while i < len(raw):
        if raw[i].startswith("1 ") and i + 1 < len(raw) and raw[i + 1].startswith("2 "):
            sets.append(raw[i:i + 2])
            i += 2
        elif i + 2 < len(raw) and raw[i + 1].startswith("1 ") and raw[i + 2].startswith("2 "):
            sets.append(raw[i:i + 3])
            i += 3
        else:
            raise ObjectError(f"{str(p)!r} line {i + 1} is not part of an element set: {raw[i][:40]!r}", key=key,
                              file=file, expected="two-line sets, each optionally preceded by a title line")
    if not sets:
        raise ObjectError(f"{str(p)!r} holds no element set", key=key, file=file, expected="a TLE file")
    tles = [parse_tle(s, key=key, file=file, context=f"{p.name} set {n + 1}", check_sgp4=False)
            for n, s in enumerate(sets)]
    if satellite is None:
        if len(tles) > 1:
            raise ObjectError(f"{str(p)!r} holds {len(tles)} element sets", key=key, file=file,
                              expected="a 'satellite' key (catalogue number or name) to choose one")
        return _checked(tles[0], key, file, p.name)
    sat_text = str(satellite).strip()
    if sat_text.isdigit():
        hits = [t for t in tles if t.norad_id.isdigit() and int(t.norad_id) == int(sat_text)]
    else:
        hits = [t for t in tles if t.name and t.name.lower() == sat_text.lower()]
        if not hits:
            hits = [t for t in tles if t.name and sat_text.lower() in t.name.lower()]
        if not hits:
            hits = [t for t in tles if t.norad_id.lower() == sat_text.lower()]
    if len(hits) != 1:
        names = ", ".join(f"{t.norad_id} {t.name or ''}".strip() for t in tles)
        raise ObjectError(f"satellite {satellite!r} matches {len(hits)} of the sets in {str(p)!r}",
                          key=key.rsplit(".", 1)[0] + ".satellite" if "." in key else "satellite", file=file,
                          expected=f"one of: {names}")
    return _checked(hits[0], key, file, p.name)


def _checked(tle: Tle, key, file, context) -> Tle:
    sat = tle.satrec()
    if sat.error:
        raise ObjectError((f"{context}: " if context else "") + _error_text(tle, sat.error, 0.0), key=key, file=file,
                          expected="an element set of a satellite in orbit")
    return tle


def propagate_teme(tle: Tle, jd1, jd2, *, key: str = "tle", file: str | None = None,
                   satrec=None) -> tuple[np.ndarray, np.ndarray]:
    """SGP4 positions [km] and velocities [km/s] in TEME at UTC Julian dates ``jd1 + jd2``, shape (N, 3).

    An SGP4 error at any date raises :class:`ObjectError`: codes 1 and 6 after the epoch mean that the
    satellite has decayed (drag lowered the orbit below the Earth's surface), which the message says.
    """
    sat = satrec if satrec is not None else tle.satrec()
    jd1 = np.atleast_1d(np.asarray(jd1, dtype=float))
    jd2 = np.atleast_1d(np.asarray(jd2, dtype=float))
    err, r, v = sat.sgp4_array(jd1, jd2)
    if np.any(err):
        k = int(np.flatnonzero(err)[0])
        code = int(err[k])
        days = float((jd1[k] - sat.jdsatepoch) + (jd2[k] - sat.jdsatepochF))
        raise ObjectError(_error_text(tle, code, days), key=key, file=file,
                          expected="an element set of a satellite still in orbit at the exposure epoch")
    if not np.all(np.isfinite(r)):
        raise ObjectError("SGP4 returned non-finite positions", key=key, file=file, expected="a valid element set")
    return r, v
