"""Sim-to-real gap diagnosis: where model and record disagree, which catalogued effect causes it,
whether the test can see it at all, and how far the held-out gap shrinks once it is added
(spec ``gap-diagnosis.md``). ``diagnose`` is the entry point; ``bench`` the blind harness."""

from ._diagnose import default_prior as default_prior
from ._diagnose import diagnose as diagnose
from ._diagnose import library as library
from ._problem import AbstractGapProblem as AbstractGapProblem
from ._report import GapReport as GapReport
from ._stats import Signature as Signature
