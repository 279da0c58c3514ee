"""The paper's pipelines: ``sparsecomm reproduce`` and ``sparsecomm paper-task``, the claims they
judge and the bit-budget frontier they draw. The library does not import them; only the command
line (:mod:`sparsecomm.cli`) does. This package imports none of its modules.

- :mod:`~sparsecomm.pipelines.plan`: a plan's parts (:class:`~.plan.Part`), what a trained part
  runs (:class:`~.plan.Sweep`), the paper's lambdas and budgets;
- :mod:`~sparsecomm.pipelines.runner`: the one runner of a plan, and the frontier rows of the
  parts found under ``out``;
- :mod:`~sparsecomm.pipelines.rows`: the one row schema of the frontier (:class:`~.rows.Row`),
  and :func:`~.rows.from_json`, which reads rows written before a field existed;
- :mod:`~sparsecomm.pipelines.frontier`: the frontier's figures, the budget-matched verdicts and
  targets, and its command line (``python -m sparsecomm.pipelines.frontier``);
- :mod:`~sparsecomm.pipelines.claims`: per-method statistics, the paper's claims, Table I;
- :mod:`~sparsecomm.pipelines.reproduce`: ``sparsecomm reproduce`` (:class:`~.reproduce.Reproduce`):
  the paper's experiments and baselines, then :mod:`~sparsecomm.pipelines.report`'s figures and
  ``report.md``;
- :mod:`~sparsecomm.pipelines.paper_task`: ``sparsecomm paper-task``
  (:class:`~.paper_task.PaperTask`): the paper's task with bit budgets (docs/paper-task.md).
"""
