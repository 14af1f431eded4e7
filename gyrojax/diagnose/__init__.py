"""Sim-to-real gap diagnosis: where model and record disagree, which catalogued effect causes it,
whether the test can see it at all, and how far the held-out gap shrinks once it is added
(docs/diagnosis.md).

:func:`diagnose` is the entry point; :class:`AbstractGapProblem` the interface a rig implements
(:mod:`gyrojax.rigs` registers it). The statistical building blocks and the rigs' catalogue
constants below are public for the blind validation suites (:mod:`gyrojax.validation`), which
the diagnosis never imports."""

__all__ = ["AbstractGapProblem", "Candidate", "ESGProblem", "ESG_LIBRARY", "ESG_TRANSIENT_TIMES_H",
           "GYROTHEODOLITE_TRANSIENT_TIMES_MIN", "GapReport", "GyrotheodoliteProblem",
           "IMUProblem", "IMU_CYCLE_DESIGN", "IMU_CYCLE_MIN_C", "IMU_LIBRARY",
           "IMU_PRIOR_BY_UNIT", "IMU_TABLE_DESIGN", "PLATFORM_NOMINAL", "PlatformProblem", "Refit",
           "SCHULER_TRANSIENT_TIMES_H", "SHELL_DESIGN_LAMBDAS", "SchulerProblem", "Signature",
           "VISIBLE_MIN", "canonical_correlation", "coefficient_effect", "default_prior",
           "design_log_bf", "diagnose", "effect_family_name", "given_options", "library",
           "ljung_box", "mix_log_bf", "nominal_basis", "nominal_coefficients", "onset_grid",
           "platform_library", "project_out", "screen_designs", "shape_log_bf_scores",
           "shell_design_log_bf", "shell_log_bf", "signature_directions", "table_runs",
           "train_first", "train_slice", "Verdict", "visibility_flag", "visible", "zellner_log_bf"]

from ._bayes import SHELL_DESIGN_LAMBDAS as SHELL_DESIGN_LAMBDAS
from ._bayes import design_log_bf as design_log_bf
from ._bayes import mix_log_bf as mix_log_bf
from ._bayes import shape_log_bf_scores as shape_log_bf_scores
from ._bayes import shell_design_log_bf as shell_design_log_bf
from ._bayes import shell_log_bf as shell_log_bf
from ._bayes import zellner_log_bf as zellner_log_bf
from ._diagnose import default_prior as default_prior
from ._diagnose import diagnose as diagnose
from ._diagnose import given_options as given_options
from ._diagnose import library as library
from ._diagnose import train_first as train_first
from ._diagnose import train_slice as train_slice
from ._esg import ESG_LIBRARY as ESG_LIBRARY
from ._esg import TRANSIENT_TIMES_H as ESG_TRANSIENT_TIMES_H
from ._esg import ESGProblem as ESGProblem
from ._gyrotheodolite import TRANSIENT_TIMES_MIN as GYROTHEODOLITE_TRANSIENT_TIMES_MIN
from ._gyrotheodolite import GyrotheodoliteProblem as GyrotheodoliteProblem
from ._imu import CYCLE_DESIGN as IMU_CYCLE_DESIGN
from ._imu import CYCLE_MIN_C as IMU_CYCLE_MIN_C
from ._imu import IMU_LIBRARY as IMU_LIBRARY
from ._imu import PRIOR_BY_UNIT as IMU_PRIOR_BY_UNIT
from ._imu import TABLE_DESIGN as IMU_TABLE_DESIGN
from ._imu import IMUProblem as IMUProblem
from ._imu import table_runs as table_runs
from ._noise_tests import ljung_box as ljung_box
from ._platform import NOMINAL as PLATFORM_NOMINAL
from ._platform import PlatformProblem as PlatformProblem
from ._platform import nominal_coefficients as nominal_coefficients
from ._platform import platform_library as platform_library
from ._problem import AbstractGapProblem as AbstractGapProblem
from ._records import Candidate as Candidate
from ._records import Refit as Refit
from ._records import Verdict as Verdict
from ._report import GapReport as GapReport
from ._schuler import TRANSIENT_TIMES_H as SCHULER_TRANSIENT_TIMES_H
from ._schuler import SchulerProblem as SchulerProblem
from ._screening import screen_designs as screen_designs
from ._signatures import VISIBLE_MIN as VISIBLE_MIN
from ._signatures import Signature as Signature
from ._signatures import canonical_correlation as canonical_correlation
from ._signatures import coefficient_effect as coefficient_effect
from ._signatures import effect_family_name as effect_family_name
from ._signatures import nominal_basis as nominal_basis
from ._signatures import onset_grid as onset_grid
from ._signatures import project_out as project_out
from ._signatures import signature_directions as signature_directions
from ._signatures import visibility_flag as visibility_flag
from ._signatures import visible as visible
