"""``sparsecomm reproduce``: the paper's experiments, the baselines, the figures and a report.

- :mod:`~sparsecomm.reproduce.plan`: the parts (their table), lambdas, bit budgets and the
  :class:`Reproduce` config;
- :mod:`~sparsecomm.reproduce.runs`: running one part (the sweeps through
  :func:`sparsecomm.experiment.train`, the fixed-width re-evaluation, the scripted policies);
- :mod:`~sparsecomm.reproduce.provenance`: the hardware, git commit and source digest of a run;
- :mod:`~sparsecomm.reproduce.report`: the parts found under ``out`` read back, the figures and
  ``report.md`` (verdicts by the rules of :mod:`sparsecomm.claims`);
- :mod:`~sparsecomm.reproduce.pipeline`: :func:`reproduce`, the command: every selected part,
  ``timings.json``, then the report.
"""

from sparsecomm.reproduce.pipeline import reproduce
from sparsecomm.reproduce.plan import BUDGETS, IL_LAMS, PARTS, RL_LAMS, Reproduce
from sparsecomm.reproduce.report import write_report
from sparsecomm.reproduce.runs import fast_compile

__all__ = [
    "BUDGETS",
    "IL_LAMS",
    "PARTS",
    "RL_LAMS",
    "Reproduce",
    "fast_compile",
    "reproduce",
    "write_report",
]
