"""Analysis: observability, Monte Carlo, mounting-error studies, gyrotheodolite vibration error."""

from .montecarlo import monte_carlo as monte_carlo
from .montecarlo import shutdown_processes as shutdown_processes
from .montecarlo import staged as staged
from .mounting import (
    MountingBudget as MountingBudget,
)
from .mounting import (
    MountingBudgetStats as MountingBudgetStats,
)
from .mounting import (
    MountingTables as MountingTables,
)
from .mounting import (
    mounting_budget_stats as mounting_budget_stats,
)
from .mounting import (
    mounting_error_budget as mounting_error_budget,
)
from .mounting import (
    mounting_error_tables as mounting_error_tables,
)
from .observability import (
    ObservabilityReport as ObservabilityReport,
)
from .observability import (
    analyse_jacobian as analyse_jacobian,
)
from .observability import (
    cramer_rao as cramer_rao,
)
from .observability import (
    format_combination as format_combination,
)
from .observability import (
    observability as observability,
)
from .streaming import LeafStats as LeafStats
from .streaming import MonteCarloStats as MonteCarloStats
from .streaming import load_outputs as load_outputs
from .streaming import monte_carlo_stats as monte_carlo_stats
from .vibration import (
    compensation_monte_carlo as compensation_monte_carlo,
)
from .vibration import (
    constant_vibration_error as constant_vibration_error,
)
from .vibration import (
    frequency_study as frequency_study,
)
