"""gyrojax: differentiable estimation for gyroscope, inertial-platform and INS bench tests.

Importing gyrojax switches JAX to float64 (``jax_enable_x64``): drift of 1e-5 deg/h against the
15 deg/h Earth rate needs it. This is the only global setting gyrojax changes.
"""

import jax as _jax

_jax.config.update("jax_enable_x64", True)

from . import diagnose as diagnose  # noqa: E402  (the package; its entry is diagnose.diagnose)
from . import earth as earth
from . import rigs as rigs
from . import rotations as rotations
from . import units as units
from ._cache import enable_compilation_cache as enable_compilation_cache  # noqa: E402
from .analysis.observability import observability as observability  # noqa: E402
from .estimate import fit as fit  # noqa: E402
from .estimate import fit_trajectory as fit_trajectory
from .estimate import solve_least_squares as solve_least_squares
from .estimate.multiposition import calibrate_accelerometer as calibrate_accelerometer
from .estimate.multiposition import calibrate_gyro as calibrate_gyro
from .estimate.platform import platform_gauss_newton as platform_gauss_newton
from .estimate.platform import platform_kalman as platform_kalman
from .estimate.platform import platform_regression as platform_regression
from .estimate.schuler import fit_schuler as fit_schuler
from .estimate.schuler import schuler_filter as schuler_filter
from .models import AbstractRig as AbstractRig  # noqa: E402
from .models import ESGConditions as ESGConditions
from .models import ESGRig as ESGRig
from .models import GyrotheodoliteConditions as GyrotheodoliteConditions
from .models import GyrotheodoliteRig as GyrotheodoliteRig
from .models import IMUConditions as IMUConditions
from .models import IMURig as IMURig
from .models import PlatformConditions as PlatformConditions
from .models import PlatformRig as PlatformRig
from .models import SchulerConditions as SchulerConditions
from .models import SchulerRig as SchulerRig
from .params import Param as Param  # noqa: E402
from .params import ParameterSpace as ParameterSpace
from .record import BenchRecord as BenchRecord  # noqa: E402
from .simulate import grid_steps as grid_steps  # noqa: E402
from .simulate import integrate as integrate  # noqa: E402
from .simulate import simulate as simulate

__version__ = "0.2.0"
