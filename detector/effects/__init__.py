"""The detector effect catalogue (DESIGN.md). Importing this package registers every built-in effect.

Each module holds pure physics functions and their registered adapters:

* ``pixel_response``: ``prnu``, ``dsnu``, ``dead_pixels``, ``gain_regions``, ``nonlinearity``
* ``defects``: ``hot_pixels``, ``column_defects``
* ``readout``: ``row_noise``, ``reset_noise``, ``bias_gradient``, ``crosstalk``
* ``glow``: ``amp_glow``
* ``blooming``: ``blooming``
* ``cosmic_rays``: ``cosmic_rays``
* ``optical``: ``vignetting``
* ``image_plane``: ``psf_blur``, ``jitter``, ``pointing_drift``, ``pointing_offset``, ``distortion``
* ``ghosts``: ``ghost`` (mirrored or shifted, disc / annulus / Gaussian; its geometry found by a Fourier scan)
* ``maps``: ``bias_map``, ``flat_map`` (measured master bias / flat FITS files)
* ``colour``: ``cfa``
* ``sky``: ``sky_gradient``
* ``cti``: ``cti`` (charge-transfer inefficiency, CCD only, with a proton-dose model)
* ``coupling``: ``brighter_fatter``, ``ipc`` (stage COUPLING: on the drawn charge, with neighbour rows)
* ``rts``: ``rts_noise`` (random telegraph signal of CMOS pixels)
* ``persistence``: ``persistence`` (residual image of earlier frames)
* ``thermal``: ``dark_gradient`` (a dark-current gradient from a temperature gradient across the die)
"""

from .base import Effect, EffectParams, Stage, Tile, build_effects, register_effect, registry  # isort: skip
from . import blooming, colour, cosmic_rays, coupling, cti, defects, glow, image_plane  # noqa: F401,I001  (registration)
from . import maps, optical, persistence, pixel_response, readout, rts, sky, thermal  # noqa: F401  (registration)
from . import ghosts  # noqa: F401,E402  (registration: ghost)
