"""newtsim's optics: the Newtonian telescope as data (design files) and, with Mitsuba 3 (llvm variant),
ray-traced straylight, vignetting and PSFs.

This package never calls ``mi.set_variant`` at import: entry points do. ``optics.design`` is pure Python
(no Mitsuba) so the rest of newtsim can read a design without a ray tracer.
"""

from .design import Design, OpticsError, load_design

__all__ = ["Design", "OpticsError", "load_design"]
