"""iFMI photo-mapping (Pfingsthorn, Birk et al., ICRA 2010): spectral registration with a POMF
covariance and peak-to-noise ratio, and the pieces of a pose-graph photo map."""

from slamreplay.algorithms.ifmi.plan import IfmiConfig, Prepared, affine, prepare
from slamreplay.algorithms.ifmi.registration import (
           Registration,
           SequentialRegistrar,
           Status,
           register,
           register_prepared,
)

__all__ = ["IfmiConfig", "Prepared", "Registration", "SequentialRegistrar", "Status", "affine", "prepare", "register",
           "register_prepared"]
