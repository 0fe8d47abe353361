"""sVORF benchmark: the paper's protocols, reports, leaderboard (see benchmark/README.md).

Data flow: datasets (``benchmark.datasets`` -> generator or synthetic) -> models
(``benchmark.adapter``, the only module importing ``svorf``) -> metrics
(``benchmark.metrics``) -> rows (``benchmark.runner`` / ``benchmark.protocols``)
-> schema-validated ``report.json`` + figures + ``index.html``.
"""
