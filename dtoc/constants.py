"""Physical constants and defaults, written once (see docs/conventions.md)."""

import math

#: Proton gyromagnetic ratio / (2 pi), Hz/T.
GAMMA_HZ_PER_T: float = 42.577478e6
#: Proton gyromagnetic ratio, rad/s/T.  k [rad/m] = GAMMA_RAD_PER_S_PER_T * integral(G [T/m] dt [s]).
GAMMA_RAD_PER_S_PER_T: float = 2.0 * math.pi * GAMMA_HZ_PER_T
#: Same, for gradients in mT/m: k [rad/m] = GAMMA_RAD_PER_S_PER_MT * integral(G [mT/m] dt [s]).
GAMMA_RAD_PER_S_PER_MT: float = GAMMA_RAD_PER_S_PER_T * 1e-3

#: Default gradient raster (Siemens), s.
DEFAULT_GRAD_RASTER_S: float = 10e-6
#: Default block raster, s.
DEFAULT_BLOCK_RASTER_S: float = 10e-6
#: Default RF raster, s.
DEFAULT_RF_RASTER_S: float = 1e-6
#: Default ADC raster, s.
DEFAULT_ADC_RASTER_S: float = 100e-9

#: Field strength, T, of the built-in phantoms' tissue values (T1, T2, T2*) when neither ``--b0`` nor a
#: config gives one: the same for every command and the library (docs/cli.md).  Not a safety default:
#: it changes the simulated object's contrast, never a limit, the orientation or the hardware model.
DEFAULT_B0_T: float = 3.0

#: Axis names in the order used by every (3, ...) array.
AXES = ("x", "y", "z")

#: The [DEFINITIONS] entry of a ``dtoc optimize`` output naming its base: the base file's sha256 (hex).
#: Provenance, not a property of what plays: ``dtoc diff`` does not compare it; ``--reference`` verifies it.
BASE_HASH_DEFINITION = "DtocBaseSha256"


def hz_per_m_from_mT_per_m(g_mT_per_m):
    """Convert a gradient from mT/m to Pulseq's Hz/m."""
    return g_mT_per_m * 1e-3 * GAMMA_HZ_PER_T


def mT_per_m_from_hz_per_m(g_hz_per_m):
    """Convert a gradient from Pulseq's Hz/m to mT/m."""
    return g_hz_per_m / GAMMA_HZ_PER_T * 1e3


#: Dummy repetitions before the sequence that the image figures assume, by sequence kind: a spoiled GRE in its
#: steady state (the paper's 300), others from equilibrium.  One definition of "before" for ``dtoc simulate``
#: (its ``--dummies`` default) and ``dtoc optimize`` (its ``n_dummies`` default): the same file and hardware give the
#: same NRMSE in both.
DEFAULT_DUMMIES_BY_KIND: dict[str, int] = {"gre": 300, "epi": 0}


def default_dummies(kind: str | None) -> int:
    """:data:`DEFAULT_DUMMIES_BY_KIND` of ``kind`` (0 for any other kind or none)."""
    return DEFAULT_DUMMIES_BY_KIND.get(kind or "", 0)
