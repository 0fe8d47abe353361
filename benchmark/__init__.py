"""sVORF benchmark: the paper's protocols, reports, leaderboard (see benchmark/README.md).

Data flow: datasets (``benchmark.datasets`` -> generator or synthetic) -> models
(``benchmark.adapter``, the only module importing ``svorf``) -> metrics
(``benchmark.metrics``) -> rows (``benchmark.protocols``; the paper's tables through
``benchmark.runner``, with the run context and caches in ``benchmark.context``, training
and evaluation jobs in ``benchmark.jobs`` and rows in ``benchmark.rows``)
-> schema-validated ``report.json`` + figures + ``index.html``.
"""
