"""The interface every rig's diagnosis problem implements (:class:`AbstractGapProblem`).

A problem is one record as the gap diagnosis sees it: split into train and held-out rows, with
the rig's nominal model, its catalogue of effects and the designs its advisor may propose. The
pipeline (:func:`gyrojax.diagnose.diagnose`) reads a problem through this interface only:
the abstract methods every rig implements, the attributes every constructor sets, and the
optional hooks below with their defaults (override one where the rig needs it). Rig options
(the ESG's ``order``, the platform's ``split``...) are keyword arguments of the concrete
problem's constructor, named in its ``OPTIONS``, and validated there, once.
"""

from __future__ import annotations

import abc
from collections.abc import Callable, Mapping
from typing import Any, ClassVar

import numpy as np

__all__ = ["AbstractGapProblem", "first_difference_level"]


def first_difference_level(resid):
    """Per-channel white-noise level of ``resid`` (``(..., n, c)``) from its first differences
    (von Neumann): the estimator of the data and of the calibrated level's null draws."""
    d = np.diff(resid, axis=-2)
    return np.sqrt(np.mean(d * d, axis=-2) / 2)


class AbstractGapProblem(abc.ABC):
    """One record as the gap diagnosis sees it.

    **Attributes** every constructor sets:

    - `t` ``(N,)`` row times (s) and `y` ``(N, c)`` the rows (SI; block means where the rig
      reduces its record), train rows first: `n_train` of them, then the held-out ones.
    - `channels`: the ``c`` channel names.
    - `noise_std`: the noise level per channel given by the user (SI), or ``None``.
    - `nominal_names`, `nominal_units`, `nominal_display_scales`: the nominal parameters, their
      display units and their Jacobian columns' scales in display units.
    - `effects`: the catalogue screened (names).
    - `lines`: known spectral lines, ``{name: period in s}`` (empty where none).
    - `notes`: list of lines for the report (fits that did not converge, effects not screened).

    **Class attributes:** `OPTIONS`: the rig options the constructor takes beyond ``holdout``,
    ``noise_std`` and ``effects``, ``{name: one-line help}``. `SPLITS`: the held-out plans,
    ``{name: description}`` (one for most rigs). `CATALOGUE_NOTE`: a line ``gyrojax effects``
    prints under the catalogue (empty: none). `NOISE_UNITS`: how the report shows a channel's
    noise level, ``{channel prefix: (scale in SI, unit)}`` (the first prefix a channel starts
    with; none: SI).
    """

    OPTIONS: ClassVar[Mapping[str, str]] = {}
    CATALOGUE_NOTE: ClassVar[str] = ""
    NOISE_UNITS: ClassVar[Mapping[str, tuple[float, str]]] = {}

    @classmethod
    def noise_text(cls, channel: str, std: float) -> str:
        """A channel's noise level ``std`` (SI) in its engineering unit (:attr:`NOISE_UNITS`)."""
        from ..io import by_channel

        scale, unit = by_channel(cls.NOISE_UNITS, channel, (1.0, "(SI)"))
        return f"{std / scale:.3g} {unit}"
    SPLITS: ClassVar[Mapping[str, str]] = {
        "time-ordered": "time-ordered (held-out = the record's end)"}

    t: np.ndarray
    y: np.ndarray
    channels: tuple
    n_train: int
    noise_std: Any
    nominal_names: tuple
    nominal_units: tuple
    nominal_display_scales: np.ndarray
    effects: tuple
    lines: dict
    notes: list

    # -- what every rig implements -------------------------------------------------------
    @classmethod
    @abc.abstractmethod
    def catalogue(cls, **options) -> dict:
        """The effects the rig's diagnosis screens under these options: ``{name: family}``."""

    @abc.abstractmethod
    def fit_nominal(self) -> dict:
        """The nominal model fitted on the train rows: a parameter dict (what :meth:`predict`,
        :meth:`jacobians` and :meth:`refit` take)."""

    @abc.abstractmethod
    def predict(self, params: dict, extra=None) -> np.ndarray:
        """The model's rows ``(N, c)`` over train and held-out for ``params`` (``extra``: rows
        to add, e.g. fitted output columns)."""

    @abc.abstractmethod
    def jacobians(self, params: dict, sigma, *, conditions=None, t=None):
        """``(jn, signatures)``: the nominal Jacobian ``(N c, k)`` (rows time-major, whitened
        by ``sigma`` and the rig's noise model, columns per parameter scale) and one
        :class:`~gyrojax.diagnose._signatures.Signature` per catalogued effect (per prior scale, a
        slice per grid value), over the record or over a candidate design's ``conditions`` and
        ``t`` (from :meth:`designs`)."""

    @abc.abstractmethod
    def refit(self, params0: dict, sig_choices, sigma):
        """The nominal model plus the chosen effects (``[(Signature, grid index)]``) fitted on
        the train rows from ``params0``: ``(rows over the record (N, c), the effects'
        coefficients in display units, the fitted parameter dict)``."""

    @abc.abstractmethod
    def designs(self) -> list:
        """The advisor's candidate designs: ``[(label, conditions, t)]``, each one that
        :meth:`jacobians` evaluates."""

    @abc.abstractmethod
    def display_nominal(self, params: dict) -> dict:
        """The nominal parameters in display units, ``{name: value}``."""

    # -- optional hooks, with their defaults ---------------------------------------------
    @classmethod
    def single_coefficients(cls, **options) -> bool:
        """Whether the catalogue under these options is one of single coefficients ("which
        term of the error model"), where the shell prior is the default
        (:func:`gyrojax.diagnose.default_prior`); ``False``: effect families."""
        return False

    #: train dof of nuisance terms fitted outside the Jacobian (the platform's dwell offsets)
    nuisance_dof: int = 0
    #: terms fitted on the held-out rows themselves (the IMU's held-out poses)
    heldout_dof: int = 0
    #: the held-out gap's expected excess from terms outside the Jacobian (platform offsets)
    heldout_extra: float = 0.0
    #: the held-out rows are another design (the platform's design-shift split)
    design_shift: bool = False
    #: :meth:`jacobians` takes ``grid={effect: index}`` to evaluate one grid value per effect
    design_grid_choice: bool = False
    #: train entries of a second residual block with its own noise level (the IMU's turns
    #: between poses), 0 where there is none. With one, :meth:`jacobians` appends the block's
    #: whitened entries (all of them, train first) after the rows', and the hooks below give
    #: its residual, its map cells and its level's re-estimate in the null draws
    block_train: int = 0

    def block_residual(self, params: dict):
        """The second block's whitened residual entries at ``params``, train first, or
        ``None`` where the problem has no such block."""
        return None

    def block_cells(self) -> list:
        """The gap map's cells on the second block: ``(axis, label, channel, columns
        (block_train, k))``."""
        return []

    def block_rescale(self, z):
        """Null draws ``(b, n c + block_train)`` (unit white, projected) with the block's level
        re-estimated as on the data."""
        return z

    @property
    def split_kind(self) -> str:
        """The held-out plan in words (the report's ``split``)."""
        return next(iter(self.SPLITS.values()))

    @property
    def noise_fit(self) -> dict:
        """Extra fields of the report's ``noise`` (the ESG's flicker level)."""
        return {}

    @property
    def aux_rows(self) -> dict | None:
        """Auxiliary channels' rows ``{name: (N,)}`` (temperatures...), or ``None``."""
        return None

    def noise_level(self, resid) -> tuple:
        """``(sigma (c,), dof, source)`` of the train residual ``resid`` ``(n_train, c)``: the
        given ``noise_std``, else the level from first differences (von Neumann) with its
        dof."""
        if self.noise_std is not None:
            s = np.broadcast_to(np.asarray(self.noise_std, float), (resid.shape[1],)).copy()
            return s, np.inf, "given"
        return (first_difference_level(resid), 2 * (resid.shape[0] - 1) / 3,
                "estimated from first differences of the residual")

    def standardize(self, resid, sigma):
        """``resid`` (rows ``(n, c)``, the record's first ``n``) in noise units."""
        return resid / sigma

    def position_signatures(self, sigma):
        """The gap map's test-position and condition cells (``None``: none)."""
        return None

    def nuisance_columns(self, sigma):
        """Columns of the nuisance terms outside the Jacobian, for the gap map (``None``)."""
        return None

    def aux_signatures(self, sigma):
        """The gap map's auxiliary-channel bins (``None``: none)."""
        return None

    def noise_screen(self, params: dict) -> list:
        """Noise-model rows (tests of noise terms the nominal model lacks): dicts with ``name``,
        ``p``, ``statistic``; empty where the rig has none."""
        return []

    def full_rate_tau_cells(self, params: dict) -> list:
        """Gap-map cells at the record's full rate, reported and never decided on."""
        return []

    def refit_reading(self, effects: tuple) -> dict | None:
        """The rig's physical reading of its last refit of ``effects`` (JSON-ready), or
        ``None``."""
        return None

    def verdict_notes(self, verdict: dict) -> list:
        """Lines the verdict adds for this rig (e.g. a noise model to try)."""
        return []

    def null_sampler(self, u, n: int, c: int, estimated: bool) -> Callable | None:
        """``draw(rng, b) -> (b, n, c)`` whitened null residuals for the calibrated level
        (``(b, n c + block_train)`` with a second block), or ``None`` where a simulation would
        not describe the problem.

        The default draws white noise per channel, takes it off the nominal span ``u`` and, when
        the data's level was estimated, re-estimates it from first differences; a problem with
        nuisance terms outside the Jacobian gets ``None`` unless it overrides this (the
        platform draws its own)."""
        if self.nuisance_dof:
            return None
        mb = self.block_train

        def draw(rng, b):
            z = rng.standard_normal((b, n * c + mb))
            z -= (z @ u) @ u.T
            if mb:  # the second block's level, re-estimated as on the data
                z = self.block_rescale(z)
            grid = z[:, : n * c].reshape(b, n, c)
            if estimated:
                grid = grid / first_difference_level(grid)[:, None, :]
            return np.concatenate([grid.reshape(b, -1), z[:, n * c:]], axis=1) if mb else grid
        return draw
