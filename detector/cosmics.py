"""Cosmic rays in a silicon sensor: energy loss, shielding, track geometry and rasterisation.

Pure physics functions, no sensor or chain state; the registered adapter is
:mod:`detector.effects.cosmic_rays`.

Model
-----
A charged particle (proton, muon or alpha) of kinetic energy ``T`` crosses, in a straight line, an optional
planar shield and then the sensitive (depleted / epitaxial) silicon layer of thickness ``d``. It loses energy
continuously at the *mean* rate given by the Bethe formula (continuous-slowing-down approximation, CSDA);
the energy lost in the sensitive layer is converted to electron-hole pairs at ``w = 3.6 eV`` per pair and
the charge is spread uniformly along the projection of the track on the pixel plane, rasterised exactly
(each pixel receives the fraction of the projected segment that lies inside it), then optionally blurred by
lateral charge diffusion (a Gaussian).

What the model leaves out (by design; stated so that residuals can be interpreted):

* energy-loss *fluctuations* (Landau/Vavilov straggling): the mean loss is used. For a minimum-ionising
  particle in 10 um of silicon the most probable loss is ~ 70-75 % of the mean (~ 80 e-/um against the
  mean 108 e-/um; PDG ch. 34, "Fluctuations in energy loss"); the long Landau tail is not drawn;
* delta rays that escape the layer (the unrestricted mean loss counts them as deposited);
* the Bragg-peak variation of dE/dx along a track that stops inside the layer (charge is spread uniformly);
* multiple scattering (tracks are straight), nuclear interactions and secondaries from the shield;
* Barkas (z^3) and Bloch (z^4) corrections of the Bethe formula; the shell correction is included. The
  stopping power agrees with PSTAR to 0.4 % from 8 MeV to 10 GeV for protons in Si, Al and Cu; below
  8 MeV a power law stands in for it (CSDA ranges -6 % at 2 MeV, -17 % at 1 MeV).
* the Fano/Poisson fluctuation of the number of pairs: the (fractional) mean charge is added.

References
----------
* R. L. Workman et al. (Particle Data Group), *Review of Particle Physics*, PTEP 2022, 083C01, chapter 34
  "Passage of particles through matter" (eq. 34.4 Tmax, eq. 34.5 Bethe, eq. 34.7 density effect), and
  the PDG "Atomic and nuclear properties of materials" tables (I, Z/A, density, Sternheimer parameters).
  The reference thesis quotes the same formula as its eqs. 11-13.
* R. M. Sternheimer, M. J. Berger, S. M. Seltzer, "Density effect for the ionization loss of charged
  particles in various substances", Atomic Data and Nuclear Data Tables 30, 261 (1984).
* M. J. Berger, J. S. Coursey, M. A. Zucker, J. Chang, ESTAR, PSTAR and ASTAR (NIST Standard Reference
  Database 124; ICRU Report 49, 1993): proton stopping powers and CSDA ranges used in the tests.
* Pair-creation energy in silicon: 3.6 eV per electron-hole pair at room temperature (e.g. J. R. Janesick,
  *Scientific Charge-Coupled Devices*, SPIE 2001; PDG ch. 35 "Particle detectors").
* W. R. Leo, *Techniques for Nuclear and Particle Physics Experiments*, Springer 1994, eq. 2.33 (shell
  correction of Barkas & Berger 1964).
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import numpy as np

# --- constants (PDG 2022, "Physical constants") ------------------------------------------------------------
#: 4 pi N_A r_e^2 m_e c^2 [MeV mol^-1 cm^2] (PDG eq. 34.5 coefficient K)
K_MEV_CM2_PER_MOL = 0.307075
#: electron rest energy m_e c^2 [MeV]
ELECTRON_MASS_MEV = 0.51099895
#: mean energy to create one electron-hole pair in silicon [eV]
SI_PAIR_ENERGY_EV = 3.6


@dataclass(frozen=True)
class Material:
    """A stopping medium: Z/A, density, mean excitation energy and Sternheimer density-effect parameters.

    Values from the PDG "Atomic and nuclear properties of materials" tables (Sternheimer, Berger & Seltzer
    1984): ``x = log10(beta gamma)``; ``delta = 2 ln10 x - C + a (x1 - x)^k`` for ``x0 <= x < x1``,
    ``2 ln10 x - C`` above ``x1``, ``delta0 10^(2 (x - x0))`` below ``x0`` (conductors).
    """

    name: str
    atomic_number: int  #: Z
    atomic_mass: float  #: A [g/mol]
    density_g_cm3: float
    mean_excitation_ev: float  #: I
    c_bar: float
    x0: float
    x1: float
    a: float
    k: float
    delta0: float

    @property
    def z_over_a(self) -> float:
        """<Z/A> [mol/g]."""
        return self.atomic_number / self.atomic_mass


MATERIALS: dict[str, Material] = {
    "Si": Material("silicon", 14, 28.0855, 2.329, 173.0, 4.4355, 0.2015, 2.8716, 0.14921, 3.2546, 0.14),
    "Al": Material("aluminium", 13, 26.9815385, 2.699, 166.0, 4.2395, 0.1708, 3.0127, 0.08024, 3.6345, 0.12),
    "Cu": Material("copper", 29, 63.546, 8.960, 322.0, 4.4190, -0.0254, 3.2792, 0.14339, 2.9044, 0.08),
}

#: Aliases accepted wherever a material name is expected.
MATERIAL_ALIASES = {"silicon": "Si", "aluminium": "Al", "aluminum": "Al", "copper": "Cu"}


@dataclass(frozen=True)
class Particle:
    """A projectile: charge number ``z`` and rest energy ``mass_mev`` (PDG 2022)."""

    name: str
    z: int
    mass_mev: float


PARTICLES: dict[str, Particle] = {
    "proton": Particle("proton", 1, 938.27208816),
    "muon": Particle("muon", 1, 105.6583755),
    "alpha": Particle("alpha", 2, 3727.3794066),
}

PROTON_MASS_MEV = PARTICLES["proton"].mass_mev

#: Lower validity limit (eta = beta*gamma) of the Barkas-Berger shell correction (Leo 1994, eq. 2.33).
SHELL_MIN_BETA_GAMMA = 0.13
#: beta*gamma below which the Bethe formula is replaced by a power law (a 7.9 MeV proton).
BETHE_LOW_BETA_GAMMA = SHELL_MIN_BETA_GAMMA
#: Exponent p of the Bragg-Kleeman range-energy rule R ~ T^p used below ``BETHE_LOW_BETA_GAMMA``
#: (fitted to the PSTAR CSDA ranges of 8 MeV protons in Si and Al).
BRAGG_KLEEMAN_P = 1.72


def material(name: str | Material) -> Material:
    """Look a material up by symbol (``"Si"``, ``"Al"``, ``"Cu"``) or name (``"aluminium"`` ...)."""
    if isinstance(name, Material):
        return name
    key = MATERIAL_ALIASES.get(str(name).lower(), name)
    if key not in MATERIALS:
        raise KeyError(f"unknown material {name!r}; known: {', '.join(MATERIALS)} (or {', '.join(MATERIAL_ALIASES)})")
    return MATERIALS[key]


# --- kinematics ---------------------------------------------------------------------------------------------

def beta_gamma(kinetic_mev, mass_mev: float = PROTON_MASS_MEV) -> np.ndarray:
    """beta*gamma = p/(M c) of a particle of kinetic energy ``T`` [MeV] and rest energy ``M`` [MeV].

    ``gamma = 1 + T/M``, ``beta gamma = sqrt(gamma^2 - 1)`` (special relativity).
    """
    g = 1.0 + np.asarray(kinetic_mev, dtype=np.float64) / mass_mev
    return np.sqrt(np.maximum(g * g - 1.0, 0.0))


def max_energy_transfer_mev(kinetic_mev, mass_mev: float = PROTON_MASS_MEV) -> np.ndarray:
    """Maximum kinetic energy given to a free electron in one collision, Tmax [MeV].

    PDG eq. 34.4: ``Tmax = 2 m_e c^2 (beta gamma)^2 / (1 + 2 gamma m_e/M + (m_e/M)^2)``.

    Parameters
    ----------
    kinetic_mev : array_like
        Kinetic energy T of the projectile [MeV].
    mass_mev : float
        Rest energy M c^2 of the projectile [MeV].
    """
    t = np.asarray(kinetic_mev, dtype=np.float64)
    g = 1.0 + t / mass_mev
    bg2 = g * g - 1.0
    r = ELECTRON_MASS_MEV / mass_mev
    return 2.0 * ELECTRON_MASS_MEV * bg2 / (1.0 + 2.0 * g * r + r * r)


def density_effect(beta_gamma_, mat: str | Material = "Si") -> np.ndarray:
    """Density-effect correction delta(beta gamma) of the Bethe formula [1].

    Sternheimer parameterisation (PDG eq. 34.7; Sternheimer, Berger & Seltzer 1984) with the parameters of
    :class:`Material`; ``x = log10(beta gamma)``.

    Parameters
    ----------
    beta_gamma_ : array_like
        beta*gamma of the projectile [1].
    mat : str or Material
    """
    m = material(mat)
    x = np.log10(np.maximum(np.asarray(beta_gamma_, dtype=np.float64), 1e-300))
    two_ln10 = 2.0 * np.log(10.0)
    mid = two_ln10 * x - m.c_bar + m.a * np.clip(m.x1 - x, 0.0, None) ** m.k
    high = two_ln10 * x - m.c_bar
    low = m.delta0 * 10.0 ** (2.0 * (x - m.x0))
    return np.where(x >= m.x1, high, np.where(x >= m.x0, mid, low))


# --- stopping power -----------------------------------------------------------------------------------------

def shell_correction(beta_gamma_, mean_excitation_ev: float) -> np.ndarray:
    """Shell correction C(eta, I) of the Bethe formula (enters the bracket as -C/Z) [1].

    Empirical fit of Barkas & Berger (1964), as given by W. R. Leo, *Techniques for Nuclear and Particle
    Physics Experiments* (Springer 1994), eq. 2.33, with ``eta = beta gamma`` and I in eV::

        C = (0.422377 eta^-2 + 0.0304043 eta^-4 - 0.00038106 eta^-6) 1e-6 I^2
          + (3.858019 eta^-2 - 0.1667989 eta^-4 + 0.00157955 eta^-6) 1e-9 I^3

    Valid for ``eta >= 0.13`` (protons above ~ 8 MeV); ``eta`` is clamped there.
    """
    e2 = 1.0 / np.maximum(np.asarray(beta_gamma_, dtype=np.float64), SHELL_MIN_BETA_GAMMA) ** 2
    i = float(mean_excitation_ev)
    return ((0.422377 * e2 + 0.0304043 * e2 ** 2 - 0.00038106 * e2 ** 3) * 1e-6 * i * i
            + (3.858019 * e2 - 0.1667989 * e2 ** 2 + 0.00157955 * e2 ** 3) * 1e-9 * i ** 3)


def bethe_mass_stopping_power(kinetic_mev, mat: str | Material = "Si", z: int = 1,
                              mass_mev: float = PROTON_MASS_MEV, with_density_effect: bool = True,
                              with_shell_correction: bool = True) -> np.ndarray:
    """Mean mass stopping power <-dE/dx> of a heavy charged particle, Bethe formula [MeV cm^2/g].

    PDG eq. 34.5 (thesis eqs. 11-13), with the shell correction (PDG sec. 34.2) added::

        -dE/dx = K z^2 (Z/A) / beta^2 [ 1/2 ln(2 m_e c^2 beta^2 gamma^2 Tmax / I^2) - beta^2 - delta/2 - C/Z ]

    with ``K = 0.307075 MeV mol^-1 cm^2``, ``Tmax`` from :func:`max_energy_transfer_mev`, the density
    effect ``delta`` from :func:`density_effect` (Sternheimer parameters) and the shell correction ``C`` from
    :func:`shell_correction`; either can be switched off. Barkas (z^3) and Bloch (z^4) terms are omitted.
    Accurate to ~ 1 % against PSTAR for protons from 10 MeV to 10 GeV in Si, Al and Cu (see the tests);
    not meant below beta gamma ~ 0.13 (:func:`mass_stopping_power` extends it there).

    Parameters
    ----------
    kinetic_mev : array_like
        Kinetic energy T [MeV].
    mat : str or Material
        ``"Si"``, ``"Al"``, ``"Cu"`` (or their names).
    z : int
        Charge number of the projectile.
    mass_mev : float
        Rest energy of the projectile [MeV] (proton 938.272, muon 105.658, alpha 3727.379).

    Returns
    -------
    ndarray
        Mass stopping power [MeV cm^2 g^-1]; multiply by the density [g/cm^3] for MeV/cm.
    """
    m = material(mat)
    t = np.asarray(kinetic_mev, dtype=np.float64)
    g = 1.0 + t / mass_mev
    bg2 = g * g - 1.0
    b2 = bg2 / (g * g)
    tmax = max_energy_transfer_mev(t, mass_mev)
    i_mev = m.mean_excitation_ev * 1e-6
    z_target = m.atomic_number
    with np.errstate(divide="ignore", invalid="ignore"):
        bracket = 0.5 * np.log(2.0 * ELECTRON_MASS_MEV * bg2 * tmax / (i_mev * i_mev)) - b2
        if with_density_effect:
            bracket = bracket - 0.5 * density_effect(np.sqrt(bg2), m)
        if with_shell_correction:
            bracket = bracket - shell_correction(np.sqrt(bg2), m.mean_excitation_ev) / z_target
        return K_MEV_CM2_PER_MOL * z * z * m.z_over_a / b2 * bracket


def mass_stopping_power(kinetic_mev, mat: str | Material = "Si", z: int = 1,
                        mass_mev: float = PROTON_MASS_MEV) -> np.ndarray:
    """Mean mass stopping power over the whole energy range used for CSDA ranges [MeV cm^2/g].

    The Bethe formula (:func:`bethe_mass_stopping_power`) above ``beta gamma_b = 0.13`` (a 7.9 MeV proton;
    the same velocity for other particles), the lower validity limit of its shell correction; below it a
    power law ``S(T) = S(T_b) (T/T_b)^(1-p)``, which integrates to the Bragg-Kleeman range rule
    ``R ~ T^p`` (R. D. Evans, *The Atomic Nucleus*, McGraw-Hill 1955). ``p = 1.72`` makes
    ``R(T_b) = T_b / (p S(T_b))`` match the PSTAR CSDA range of 8 MeV protons in Si and Al (to 1 %; 4 % in
    Cu). CSDA ranges then agree with PSTAR to 0.5 % (Si, Al) and 2.5 % (Cu) from 10 MeV up; below a few
    MeV the power law is crude (-17 % at 1 MeV), which only matters for where a stopping particle ends.
    """
    t = np.asarray(kinetic_mev, dtype=np.float64)
    tb = mass_mev * (np.sqrt(1.0 + BETHE_LOW_BETA_GAMMA ** 2) - 1.0)
    sb = bethe_mass_stopping_power(tb, mat, z, mass_mev)
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        low = sb * (np.maximum(t, 1e-30) / tb) ** (1.0 - BRAGG_KLEEMAN_P)
        high = bethe_mass_stopping_power(np.maximum(t, tb), mat, z, mass_mev)
    return np.where(t >= tb, high, low)


def stopping_power_mev_per_cm(kinetic_mev, mat: str | Material = "Si", z: int = 1,
                              mass_mev: float = PROTON_MASS_MEV) -> np.ndarray:
    """Linear stopping power dE/dx = rho S(T) [MeV/cm] (S from :func:`mass_stopping_power`)."""
    m = material(mat)
    return m.density_g_cm3 * mass_stopping_power(kinetic_mev, m, z, mass_mev)


# --- CSDA range and slowing down ----------------------------------------------------------------------------

@dataclass(frozen=True)
class RangeTable:
    """CSDA range R(T) = integral_0^T dT'/S(T') [g/cm^2] tabulated on a log grid of kinetic energy.

    Both directions (range from energy, energy from range) interpolate linearly in (ln T, ln R) on the
    same nodes, so they are exact inverses of each other.
    """

    log_t: np.ndarray  #: ln T [ln MeV]
    log_r: np.ndarray  #: ln R [ln g/cm^2]

    def range_g_cm2(self, kinetic_mev) -> np.ndarray:
        t = np.maximum(np.asarray(kinetic_mev, dtype=np.float64), 1e-300)
        return np.exp(np.interp(np.log(t), self.log_t, self.log_r, left=-np.inf))

    def energy_mev(self, range_g_cm2) -> np.ndarray:
        r = np.asarray(range_g_cm2, dtype=np.float64)
        out = np.exp(np.interp(np.log(np.maximum(r, 1e-300)), self.log_r, self.log_t, left=-np.inf))
        return np.where(r > 0, out, 0.0)


@lru_cache(maxsize=32)
def range_table(mat: str = "Si", z: int = 1, mass_mev: float = PROTON_MASS_MEV,
                t_min_mev: float = 1e-4, t_max_mev: float = 1e7, points_per_decade: int = 400) -> RangeTable:
    """The CSDA range table of a particle in a material (cached).

    ``R(T) = R(T_0) + integral_{T_0}^{T} dT'/S(T')`` (PDG sec. 34.2, CSDA range), with S from
    :func:`mass_stopping_power`; the part below ``T_0 = t_min_mev`` is the closed form of the power law,
    ``R(T_0) = T_0 / (p S(T_0))``. The integral is taken with the trapezoid rule in ln T
    (``dT/S = T/S d ln T``) on ``points_per_decade`` nodes per decade (relative error < 1e-5).
    """
    m = material(mat)
    n = int(round(np.log10(t_max_mev / t_min_mev) * points_per_decade)) + 1
    log_t = np.linspace(np.log(t_min_mev), np.log(t_max_mev), n)
    t = np.exp(log_t)
    s = mass_stopping_power(t, m, z, mass_mev)
    f = t / s
    r0 = t[0] / (BRAGG_KLEEMAN_P * s[0])
    r = r0 + np.concatenate([[0.0], np.cumsum(0.5 * (f[1:] + f[:-1]) * np.diff(log_t))])
    return RangeTable(log_t, np.log(r))


def _table(mat, particle: Particle | None, z: int, mass_mev: float) -> tuple[Material, RangeTable, int, float]:
    if particle is not None:
        z, mass_mev = particle.z, particle.mass_mev
    m = material(mat)
    key = next(k for k, v in MATERIALS.items() if v == m)
    return m, range_table(key, int(z), float(mass_mev)), int(z), float(mass_mev)


def csda_range_g_cm2(kinetic_mev, mat: str | Material = "Si", z: int = 1, mass_mev: float = PROTON_MASS_MEV,
                     particle: Particle | None = None) -> np.ndarray:
    """CSDA range of a particle of kinetic energy T [MeV] in a material [g/cm^2] (see :func:`range_table`).

    Divide by the density for cm. PSTAR (NIST): 10 MeV protons 0.1705 g/cm^2 in Al, 0.1665 in Si.
    """
    _, tab, _, _ = _table(mat, particle, z, mass_mev)
    return tab.range_g_cm2(kinetic_mev)


def residual_energy_mev(kinetic_mev, thickness_g_cm2, mat: str | Material = "Al", z: int = 1,
                        mass_mev: float = PROTON_MASS_MEV, particle: Particle | None = None) -> np.ndarray:
    """Kinetic energy left after crossing ``thickness_g_cm2`` of material (CSDA) [MeV]; 0 if it stopped.

    ``T_out = R^-1(R(T_in) - t)`` (CSDA, PDG sec. 34.2): the range-energy relation integrates the Bethe
    stopping power exactly along the path, whatever the thickness. For thin layers (t < 1 % of the range)
    the second-order midpoint rule ``dT = S(T - S(T) t/2) t`` is used instead, which avoids the round-off
    of the difference of two large ranges.

    Parameters
    ----------
    kinetic_mev : array_like
        Kinetic energy entering the layer [MeV].
    thickness_g_cm2 : array_like
        Mass thickness traversed along the path, rho x [g/cm^2] (slab thickness / cos(theta)).
    """
    m, tab, z, mass_mev = _table(mat, particle, z, mass_mev)
    t_in = np.asarray(kinetic_mev, dtype=np.float64)
    x = np.broadcast_to(np.asarray(thickness_g_cm2, dtype=np.float64), np.broadcast(t_in, thickness_g_cm2).shape)
    t_in = np.broadcast_to(t_in, x.shape)
    r_in = tab.range_g_cm2(t_in)
    thick = tab.energy_mev(r_in - x)
    s1 = mass_stopping_power(t_in, m, z, mass_mev)
    d1 = s1 * x
    thin = t_in - mass_stopping_power(np.maximum(t_in - 0.5 * d1, 1e-30), m, z, mass_mev) * x
    out = np.where(x < 0.01 * r_in, thin, thick)
    return np.where(r_in > x, np.maximum(out, 0.0), 0.0)


def slow_down_ivp_mev(kinetic_mev: float, thickness_g_cm2: float, mat: str | Material = "Al", z: int = 1,
                      mass_mev: float = PROTON_MASS_MEV, rtol: float = 1e-8) -> float:
    """Reference solution of the CSDA slowing down: integrate ``dT/d(rho x) = -S(T)`` with scipy.

    The CSDA ordinary differential equation solved by ``scipy.integrate.solve_ivp`` (RK45)
    from 0 to ``thickness_g_cm2``, stopping when T reaches 1 keV (returns 0 then). Slow (one particle at a
    time): used to check :func:`residual_energy_mev`.
    """
    from scipy.integrate import solve_ivp

    m = material(mat)

    def rhs(_x, y):
        return [-float(mass_stopping_power(max(y[0], 1e-6), m, z, mass_mev))]

    def stopped(_x, y):
        return y[0] - 1e-3

    stopped.terminal = True
    sol = solve_ivp(rhs, (0.0, float(thickness_g_cm2)), [float(kinetic_mev)], rtol=rtol, atol=1e-9,
                    events=stopped, max_step=max(thickness_g_cm2 / 50.0, 1e-12))
    if sol.status == 1:
        return 0.0
    return float(sol.y[0, -1])


def deposit_in_layer(kinetic_mev, path_cm, mat: str | Material = "Si", z: int = 1,
                     mass_mev: float = PROTON_MASS_MEV, particle: Particle | None = None
                     ) -> tuple[np.ndarray, np.ndarray]:
    """Energy lost in a layer along a straight path, and the path actually travelled (CSDA).

    ``E_dep = T_in - T_out`` with ``T_out`` from :func:`residual_energy_mev` (for a thin layer this is
    ``dE/dx(T) * L`` to second order); a particle whose range ``R(T)/rho`` is shorter than the path stops
    inside and deposits all of ``T_in`` over its range.

    Parameters
    ----------
    kinetic_mev : array_like
        Kinetic energy entering the layer [MeV].
    path_cm : array_like
        Geometric path length through the layer [cm] (thickness / cos(theta)).

    Returns
    -------
    deposit_mev, travelled_cm : ndarray
    """
    m, tab, z, mass_mev = _table(mat, particle, z, mass_mev)
    t = np.asarray(kinetic_mev, dtype=np.float64)
    path = np.asarray(path_cm, dtype=np.float64)
    range_cm = tab.range_g_cm2(t) / m.density_g_cm3
    travelled = np.minimum(path, range_cm)
    t_out = residual_energy_mev(t, travelled * m.density_g_cm3, m, z, mass_mev)
    t_out = np.where(path >= range_cm, 0.0, t_out)
    return t - t_out, travelled


def electrons_from_energy(deposit_mev, pair_energy_ev: float = SI_PAIR_ENERGY_EV) -> np.ndarray:
    """Mean number of electron-hole pairs created by an energy deposit: N = E / w [e-].

    ``w = 3.6 eV`` in silicon (Janesick 2001). A minimum-ionising particle (1.66 MeV cm^2/g,
    3.87 MeV/cm) thus frees 108 e- per micron on average (the most probable value is ~ 80 e-/um).
    """
    return np.asarray(deposit_mev, dtype=np.float64) * 1e6 / pair_energy_ev


# --- sampling -------------------------------------------------------------------------------------------------

def sample_cos_theta(rng: np.random.Generator, n: int, theta_max_deg: float = 90.0) -> np.ndarray:
    """cos(theta) of particles crossing a plane from an isotropic flux: cos(theta) = sqrt(U).

    The rate through a plane per solid angle is ``I cos(theta)``, so ``p(theta) ~ cos(theta) sin(theta)``,
    i.e. ``cos^2(theta)`` is uniform on [0, 1] (Sullivan, NIM 95, 5 (1971): geometric factor of a plane
    detector). Values below ``cos(theta_max)`` are clamped to it (grazing tracks keep a finite length).
    """
    c = np.sqrt(rng.random(n))
    return np.maximum(c, np.cos(np.radians(theta_max_deg)))


def sample_power_law_mev(rng: np.random.Generator, n: int, e_min_mev: float, e_max_mev: float,
                         index: float) -> np.ndarray:
    """Kinetic energies from dN/dE ~ E^-index on [e_min, e_max] by inversion of the CDF [MeV].

    ``E = [E_min^(1-g) - U (E_min^(1-g) - E_max^(1-g))]^(1/(1-g))`` for ``g != 1``, ``E_min (E_max/E_min)^U``
    for ``g = 1``. Galactic cosmic rays follow ``g ~ 2.7`` above a few GeV (PDG "Cosmic rays", sec. 30.1).
    """
    u = rng.random(n)
    if abs(index - 1.0) < 1e-12:
        return e_min_mev * (e_max_mev / e_min_mev) ** u
    a = 1.0 - index
    lo, hi = e_min_mev ** a, e_max_mev ** a
    return (lo + u * (hi - lo)) ** (1.0 / a)


# --- rasterisation ------------------------------------------------------------------------------------------

def rasterise_segments(x0, y0, x1, y1, electrons) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Exact rasterisation of straight segments carrying uniform charge onto the pixel grid.

    Pixel ``(i, j)`` covers ``x in [j - 1/2, j + 1/2)``, ``y in [i - 1/2, i + 1/2)`` (centres on integers,
    like :meth:`Tile.pixel_centres`). Each segment is cut at every crossing of a pixel boundary (parameters
    ``t = (k + 1/2 - x0)/(x1 - x0)`` and the same in y, merged and sorted), and each piece gives the pixel
    that contains its midpoint the charge ``electrons * (t_{k+1} - t_k)``: the charge per pixel is exactly
    proportional to the length of the segment inside it, and the pieces of one segment sum to its charge.
    A zero-length segment puts all its charge in one pixel.

    Parameters
    ----------
    x0, y0, x1, y1 : array_like
        Segment end points [pixels].
    electrons : array_like
        Charge carried by each segment [e-].

    Returns
    -------
    index, rows, cols, charge : ndarray
        For every piece: the segment it belongs to, its pixel row and column, and its charge [e-].
    """
    x0, y0, x1, y1 = (np.asarray(a, dtype=np.float64).ravel() for a in (x0, y0, x1, y1))
    q = np.asarray(electrons, dtype=np.float64).ravel()
    n = x0.size
    dx, dy = x1 - x0, y1 - y0
    cx0, cx1 = np.floor(x0 + 0.5), np.floor(x1 + 0.5)
    cy0, cy1 = np.floor(y0 + 0.5), np.floor(y1 + 0.5)
    nx = np.abs(cx1 - cx0).astype(np.int64)
    ny = np.abs(cy1 - cy0).astype(np.int64)

    # one block per segment: [0, x crossings (increasing t), y crossings (increasing t), 1]
    m = nx + ny + 2
    start = np.cumsum(m) - m
    seg = np.repeat(np.arange(n), m)
    t = np.empty(seg.size)
    t[start] = 0.0
    t[start + m - 1] = 1.0
    for c0, p0, d, cnt, first in ((cx0, x0, dx, nx, start + 1), (cy0, y0, dy, ny, start + 1 + nx)):
        s_ = np.repeat(np.arange(n), cnt)
        k = np.arange(s_.size) - np.repeat(np.cumsum(cnt) - cnt, cnt)  # 0..cnt-1 within a segment
        boundary = c0[s_] + np.sign(d[s_]) * (k + 0.5)
        t[first[s_] + k] = (boundary - p0[s_]) / d[s_]
    np.clip(t, 0.0, 1.0, out=t)
    # sort within blocks only: the key stays in [i, i + 1/2] for block i, and the two runs of each block
    # are already sorted, which the stable (merge) sort exploits
    t = t[np.argsort(seg + 0.5 * t, kind="stable")]
    same = seg[1:] == seg[:-1]
    dt = np.diff(t)[same]
    piece_seg = seg[1:][same]
    tm = 0.5 * (t[1:] + t[:-1])[same]
    keep = dt > 0
    piece_seg, tm, dt = piece_seg[keep], tm[keep], dt[keep]
    xm = x0[piece_seg] + tm * dx[piece_seg]
    ym = y0[piece_seg] + tm * dy[piece_seg]
    cols = np.floor(xm + 0.5).astype(np.int64)
    rows = np.floor(ym + 0.5).astype(np.int64)
    return piece_seg, rows, cols, q[piece_seg] * dt


def diffusion_kernel(sigma_px: float, truncate: float = 4.0) -> np.ndarray:
    """1-D weights of a Gaussian of ``sigma_px`` integrated over unit pixels, normalised to sum 1.

    ``w_k = Phi((k + 1/2)/sigma) - Phi((k - 1/2)/sigma)`` for ``|k| <= ceil(truncate sigma)``, divided by
    their sum so that the blur conserves charge exactly. The 2-D kernel is the outer product (a Gaussian is
    separable). Lateral diffusion of the charge collected from depth in a CCD/CMOS gives such a Gaussian
    spread (Janesick 2001, "charge diffusion"); ``sigma = 0`` returns ``[1]``.
    """
    if sigma_px <= 0:
        return np.ones(1)
    from scipy.special import ndtr

    r = int(np.ceil(truncate * sigma_px))
    k = np.arange(-r, r + 1, dtype=np.float64)
    w = ndtr((k + 0.5) / sigma_px) - ndtr((k - 0.5) / sigma_px)
    return w / w.sum()


def add_charge(image: np.ndarray, rows: np.ndarray, cols: np.ndarray, charge_e: np.ndarray,
               kernel: np.ndarray) -> None:
    """Add point charges to ``image`` in place, each spread by the separable 2-D ``kernel``.

    ``rows``/``cols`` are pixel indices relative to ``image`` (they may lie outside it, within the kernel
    radius: the part of the spread that lands inside is added, the rest belongs to the neighbouring tile).
    The 2-D weights ``kernel[i] kernel[j]`` sum to one (:func:`diffusion_kernel`), so charge is conserved.
    Scatter-add (``np.add.at``) for few charges, a histogram of linear indices (``np.bincount``) for
    more, and for many a histogram of the unblurred charge convolved by the kernel along both axes
    (``scipy.ndimage.convolve1d``): the same sums up to float rounding. The branch depends only on the
    data, never on threads.
    """
    rows = np.asarray(rows, dtype=np.int64)
    cols = np.asarray(cols, dtype=np.int64)
    q = np.asarray(charge_e, dtype=np.float64)
    h, w = image.shape
    k = np.asarray(kernel, dtype=np.float64)
    r = (k.size - 1) // 2
    inside = (rows >= -r) & (rows < h + r) & (cols >= -r) & (cols < w + r)
    rows, cols, q = rows[inside], cols[inside], q[inside]
    if q.size == 0:
        return
    if r > 0 and q.size * k.size * k.size > image.size // 2:
        from scipy.ndimage import convolve1d

        hp, wp = h + 2 * r, w + 2 * r
        patch = np.bincount((rows + r) * wp + cols + r, weights=q, minlength=hp * wp).reshape(hp, wp)
        patch = convolve1d(patch, k, axis=0, mode="constant")[r:r + h]
        patch = convolve1d(patch, k, axis=1, mode="constant")[:, r:r + w]
        image += patch.astype(image.dtype)
        return
    off = np.arange(-r, r + 1)
    rr = (rows[:, None] + np.repeat(off, off.size)[None, :]).ravel()
    cc = (cols[:, None] + np.tile(off, off.size)[None, :]).ravel()
    vv = (q[:, None] * np.outer(k, k).ravel()[None, :]).ravel()
    m = (rr >= 0) & (rr < h) & (cc >= 0) & (cc < w)
    rr, cc, vv = rr[m], cc[m], vv[m]
    if vv.size < image.size // 16:
        np.add.at(image, (rr, cc), vv.astype(image.dtype))
    else:
        image += np.bincount(rr * w + cc, weights=vv, minlength=h * w).reshape(h, w).astype(image.dtype)


# --- environments and track drawing --------------------------------------------------------------------------

@dataclass(frozen=True)
class Environment:
    """A documented default particle environment of the sensor (an explicit flux overrides it)."""

    flux_per_cm2_s: float  #: particles crossing the sensor plane per cm^2 per s (both faces)
    particle: str  #: key of :data:`PARTICLES`
    energy_min_mev: float  #: lower end of the E^-index kinetic-energy spectrum [MeV]
    source: str


#: Default fluxes. "Flux" everywhere in this module is the rate of particles crossing unit area of the
#: sensor plane (what a thin planar detector counts; for an isotropic omnidirectional flux J it is J/2).
ENVIRONMENTS: dict[str, Environment] = {
    "ground": Environment(
        1.0 / 60.0, "muon", 1000.0,
        "Sea-level muons: 'I ~ 1 cm^-2 min^-1 for horizontal detectors' (PDG Review of Particle Physics, "
        "'Cosmic rays', muons at sea level) = 0.0167 cm^-2 s^-1; mean muon energy ~ 4 GeV at sea level "
        "(same section): spectrum from 1 GeV. Natural radioactivity near the camera adds events not modelled."),
    "leo": Environment(
        1.2, "proton", 355.0,
        "Low Earth orbit outside the South Atlantic Anomaly, HST at ~ 540 km: 1.7 events/s on a WF/PC-1 "
        "800x800 15 um CCD (1.44 cm^2; HST Data Handbook, WF/PC-1, sec. 46.5) = 1.2 cm^-2 s^-1. Typical "
        "kinetic energy 534 +- 117 MeV (Miles et al. 2021, arXiv:2006.00909): E_min = 355 MeV puts the "
        "median of an E^-2.7 spectrum at 534 MeV."),
    "saa": Environment(
        1100.0, "proton", 30.0,
        "Peak of the South Atlantic Anomaly at HST altitude, measured on the STIS CCD (i.e. behind HST's "
        "shielding): 1100 particles cm^-2 s^-1 (Miles et al. 2021, arXiv:2006.00909). Trapped protons; "
        "the 30 MeV lower energy (range ~ 1.2 g/cm^2 Al, what light shielding lets through) is an "
        "assumption, not a measurement."),
    "geo": Environment(
        4.3, "proton", 355.0,
        "Geostationary orbit (6.6 Earth radii, above the geomagnetic cutoff of galactic cosmic rays), taken "
        "as the interplanetary GCR rate: JWST NIRSpec at L2 measured 4.3 ions cm^-2 s^-1 at the start of "
        "operations, falling to 2.3 near solar maximum (Rauscher & Fixsen 2025, PASP 137, 095003; "
        "arXiv:2602.02134). GCR spectrum as for 'leo'."),
}

#: Columns of the per-frame track table (sensor pixel coordinates; see :func:`draw_tracks`).
TRACK_DTYPE = np.dtype([("x_sensor", "f8"), ("y_sensor", "f8"), ("x_end_sensor", "f8"), ("y_end_sensor", "f8"),
                        ("theta_deg", "f8"), ("phi_deg", "f8"), ("energy_incident_mev", "f8"),
                        ("energy_mev", "f8"), ("deposit_mev", "f8"), ("electrons", "f8")])


def draw_tracks(rng: np.random.Generator, expected_hits: float, x_range: tuple[float, float],
                y_range: tuple[float, float], pitch_um: float, depletion_um: float,
                particle: Particle | str = "proton", energy_mev: float | None = None,
                energy_min_mev: float = 100.0, energy_max_mev: float = 1e5, spectrum_index: float = 2.7,
                shield_material: str | None = None, shield_mm: float = 0.0, theta_max_deg: float = 89.0,
                pair_energy_ev: float = SI_PAIR_ENERGY_EV) -> np.ndarray:
    """Draw the particle tracks of one exposure and their charge (the whole physics chain of this module).

    1. number of particles ``N ~ Poisson(expected_hits)`` (``expected_hits = F A t``);
    2. entry points uniform on the window ``x_range x y_range`` [sensor pixels]; azimuth ``phi`` uniform;
       ``cos(theta) = sqrt(U)`` (:func:`sample_cos_theta`);
    3. kinetic energy fixed (``energy_mev``) or from ``E^-index`` on [E_min, E_max]
       (:func:`sample_power_law_mev`);
    4. the shield (slab of ``shield_mm``, crossed over ``shield_mm / cos(theta)``) slows each particle
       (:func:`residual_energy_mev`); those that stop are removed;
    5. in the sensitive silicon layer the path is ``d / cos(theta)`` (or the range, if shorter) and the
       deposit ``E_dep`` from :func:`deposit_in_layer`; electrons ``E_dep / w``;
    6. the track's projection on the pixel plane has length ``travelled sin(theta) / pitch`` [pixels] along
       ``phi``, from the entry point.

    All random numbers are drawn for all N particles in a fixed order, so the result depends only on the
    generator state and the arguments.

    Returns
    -------
    ndarray of :data:`TRACK_DTYPE`
        One row per particle that reaches the sensitive layer.
    """
    p = PARTICLES[particle] if isinstance(particle, str) else particle
    n = int(rng.poisson(expected_hits)) if expected_hits > 0 else 0
    x = x_range[0] + (x_range[1] - x_range[0]) * rng.random(n)
    y = y_range[0] + (y_range[1] - y_range[0]) * rng.random(n)
    cos_t = sample_cos_theta(rng, n, theta_max_deg)
    phi = 2.0 * np.pi * rng.random(n)
    if energy_mev is not None:
        e0 = np.full(n, float(energy_mev))
    else:
        e0 = sample_power_law_mev(rng, n, energy_min_mev, energy_max_mev, spectrum_index)
    e = e0
    if shield_material is not None and shield_mm > 0 and n:
        sm = material(shield_material)
        e = residual_energy_mev(e0, sm.density_g_cm3 * shield_mm * 0.1 / cos_t, sm, particle=p)
    keep = e > 0
    x, y, cos_t, phi, e0, e = x[keep], y[keep], cos_t[keep], phi[keep], e0[keep], e[keep]
    path_cm = depletion_um * 1e-4 / cos_t
    dep, travelled = deposit_in_layer(e, path_cm, "Si", particle=p)
    sin_t = np.sqrt(np.maximum(1.0 - cos_t * cos_t, 0.0))
    length_px = travelled * sin_t / (pitch_um * 1e-4)
    out = np.zeros(x.size, dtype=TRACK_DTYPE)
    out["x_sensor"], out["y_sensor"] = x, y
    out["x_end_sensor"] = x + length_px * np.cos(phi)
    out["y_end_sensor"] = y + length_px * np.sin(phi)
    out["theta_deg"] = np.degrees(np.arccos(cos_t))
    out["phi_deg"] = np.degrees(phi)
    out["energy_incident_mev"], out["energy_mev"], out["deposit_mev"] = e0, e, dep
    out["electrons"] = electrons_from_energy(dep, pair_energy_ev)
    return out
