"""Estimators: integral regression, Gauss-Newton/LM, square-root Kalman filter, spiral fit,
Luenberger observers."""

from ._fit import METHODS as METHODS
from ._fit import FitReport as FitReport
from ._fit import fit as fit
from ._lstsq import STATIONARY_SE as STATIONARY_SE
from ._lstsq import CappedTrustRegion as CappedTrustRegion
from ._lstsq import LeastSquaresSolution as LeastSquaresSolution
from ._lstsq import ScaledLevenbergMarquardt as ScaledLevenbergMarquardt
from ._lstsq import StationaryStop as StationaryStop
from ._lstsq import TrustRegionDescent as TrustRegionDescent
from ._lstsq import convergence_note as convergence_note
from ._lstsq import dense_jacobian as dense_jacobian
from ._lstsq import solve_least_squares as solve_least_squares
from .kalman import (
    ESGFilterResult as ESGFilterResult,
)
from .kalman import (
    KalmanResult as KalmanResult,
)
from .kalman import (
    esg_augmented_filter as esg_augmented_filter,
)
from .kalman import (
    rts_smoother as rts_smoother,
)
from .kalman import (
    square_root_filter as square_root_filter,
)
from .least_squares import (
    FitResult as FitResult,
)
from .least_squares import (
    fit_trajectory as fit_trajectory,
)
from .least_squares import (
    trajectory_jacobian as trajectory_jacobian,
)
from .observer import (
    DiscreteObserver as DiscreteObserver,
)
from .observer import (
    ackermann_observer as ackermann_observer,
)
from .observer import (
    frequency_response as frequency_response,
)
from .observer import (
    place_observer as place_observer,
)
from .observer import (
    simulate_with_observer as simulate_with_observer,
)
from .regression import (
    RegressionResult as RegressionResult,
)
from .regression import (
    integral_regression as integral_regression,
)
from .regression import (
    regression_design as regression_design,
)
from .spiral import (
    SpiralResult as SpiralResult,
)
from .spiral import (
    fit_spiral as fit_spiral,
)
from .spiral import (
    invert_spiral as invert_spiral,
)
from .spiral import (
    spiral_parameters as spiral_parameters,
)
from .spiral import (
    spiral_trajectory as spiral_trajectory,
)
