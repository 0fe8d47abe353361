"""One row of a report (:class:`Row`) and its id (:func:`row_id`).

Where this sits: at the bottom of ``benchmark``, importing nothing of the project, so that
every row builder uses it: the paper's rows (``benchmark.paper_numbers``), the table
runner's measured and chance rows (``benchmark.rows``, which re-exports both names), and the
``editing``, ``speed``, ``stability`` and ``tradeoff`` protocols. A row's
:meth:`Row.to_dict` is the JSON the report holds (``benchmark.schema``).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

__all__ = ["Row", "row_id"]


def row_id(table: str, model: str, dataset: str, source: str) -> str:
    """Stable id of a report row."""
    return f"{table}|{model}|{dataset}|{source}"


@dataclass(frozen=True)
class Row:
    """One row of a report's ``rows`` (``benchmark.schema``): a model on a test dataset.

    Attributes:
        table: the table id (``tab:seg``, ``edit:move``, ``speed``, ``stability``...).
        model: the row's model name, as printed.
        dataset: the test preset (or what the cases run on: ``"synthetic rays"``).
        source: ``"measured"``, ``"baseline"`` or ``"paper"``.
        metrics: metric name -> value, None where it could not be computed.
        null_reasons: metric name -> why it is None (every None metric has one).
        variant: the model variant (None for baselines).
        n_scenes: scenes scored (None: not recorded, as in the paper's rows).
        extra: the row's other report fields, unchanged (``run_key``, ``train_dataset``,
            ``test_fingerprint``, ``nan_counts``, ``eval_wall_s``, ``note``, ``details``,
            ``failed``, ``n_cases``, ``pass``...).
        fixed_id: the row's id where it is not :func:`row_id` of its fields (the
            stability rows name the device instead of the dataset); None = :func:`row_id`.
        has_variant: False for rows that carry no ``variant`` key at all (the speed
            protocol's generator rows, which measure no model).
    """

    table: str
    model: str
    dataset: str
    source: str
    metrics: Mapping[str, Any]
    null_reasons: Mapping[str, str] = field(default_factory=dict)
    variant: str | None = None
    n_scenes: int | None = None
    extra: Mapping[str, Any] = field(default_factory=dict)
    fixed_id: str | None = None
    has_variant: bool = True

    @property
    def id(self) -> str:
        """The row's id: ``fixed_id``, else :func:`row_id` of the row."""
        if self.fixed_id is not None:
            return self.fixed_id
        return row_id(self.table, self.model, self.dataset, self.source)

    def to_dict(self) -> dict[str, Any]:
        """The row as the report's JSON holds it (``extra``'s keys last)."""
        d: dict[str, Any] = {
            "id": self.id,
            "table": self.table,
            "model": self.model,
            "dataset": self.dataset,
            "variant": self.variant,
            "source": self.source,
            "metrics": dict(self.metrics),
            "null_reasons": dict(self.null_reasons),
        }
        if not self.has_variant:
            del d["variant"]
        if self.n_scenes is not None:
            d["n_scenes"] = self.n_scenes
        return {**d, **self.extra}
