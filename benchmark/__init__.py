"""sVORF benchmark: the paper's protocols, reports, leaderboard (see benchmark/README.md).

Data flow: datasets (``benchmark.datasets`` -> generator or synthetic) -> models
(``benchmark.adapter``, the only module importing ``svorf``) -> metrics
(``benchmark.metrics``) -> rows (``benchmark.protocols``; the paper's tables through
``benchmark.runner``, with the run context and caches in ``benchmark.context``, training
and evaluation jobs in ``benchmark.jobs`` and rows in ``benchmark.rows``)
-> schema-validated ``report.json`` + figures + ``index.html``.

The measuring and experiment tools of the model and the generator (speed of each model
knob, the cpu recipe's time-budgeted training, the generator's baselines) are commands in
``benchmark.tools``, which imports the libraries and no other module of this package.
"""
