"""gyrojax: differentiable estimation for gyroscope, inertial-platform and INS bench tests.

Importing gyrojax switches JAX to float64 (``jax_enable_x64``): drift of 1e-5 deg/h against the
15 deg/h Earth rate needs it. This is the only global setting gyrojax changes.
"""

import jax as _jax

_jax.config.update("jax_enable_x64", True)

from . import earth as earth  # noqa: E402
from . import rotations as rotations
from . import units as units
from .models.esg import ESGConditions as ESGConditions  # noqa: E402
from .models.esg import ESGRig as ESGRig
from .params import Param as Param  # noqa: E402
from .params import ParameterSpace as ParameterSpace
from .record import BenchRecord as BenchRecord  # noqa: E402
from .simulate import grid_steps as grid_steps  # noqa: E402
from .simulate import integrate as integrate  # noqa: E402
from .simulate import simulate as simulate

__version__ = "0.1.0"
