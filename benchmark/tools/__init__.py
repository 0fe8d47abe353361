"""Measuring and experiment tools of the model and the generator, each a ``python -m`` command.

Where this sits: beside the benchmark, on top of the libraries. The tools import
``svorf``, ``generators``, ``assets_procedural`` and ``scenefmt`` but no other
``benchmark`` module, and no library imports them; the protocols use a few of them
(the interleaved timing loop of :mod:`.speedbench`, the generator baselines).

- :mod:`.speedbench`: speed of a training step for each speed knob of the model, and
  each knob's error (``python -m benchmark.tools.speedbench``).
- :mod:`.recipe`: the cpu recipe's time-budgeted training with held-out evaluation,
  per-object failure breakdown and curves (``python -m benchmark.tools.recipe
  train-eval|diagnose|plot``).
- :mod:`.compare`: two arms of a recipe change side by side at each seed, from written
  reports (``python -m benchmark.tools.compare --with DIR... --without DIR...``).
- :mod:`.bench_baseline`: ``generate`` against a straightforward bpy script.
- :mod:`.bench_quality`: render error and time of the generator's render settings.
- :mod:`.bench_overhead`: bare Cycles time of a generated split's views.

This file imports nothing, so that ``python -m benchmark.tools.<tool>`` loads only the
tool it runs (the generator tools run without torch).
"""
