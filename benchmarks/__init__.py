"""The benchmark harnesses: ``fleet bench`` runs them (:mod:`fleet.bench`), and each runs alone as
``python -m benchmarks.<name>`` (``benchmarks/README.md``).

* :mod:`benchmarks.options` — ``fleet bench``'s options, cheap to import;
* :mod:`benchmarks.bench_scale` (with :mod:`benchmarks.bench_step`) — scale and performance;
* :mod:`benchmarks.bench_liveness` — completion, time to goal and path efficiency on hard scenes;
* :mod:`benchmarks.bench_cpu`, :mod:`benchmarks.bench_targets` — CPU by process and thread, and
  the runtime targets;
* the floors and comparisons: :mod:`benchmarks.bench_zenoh_floor`,
  :mod:`benchmarks.bench_latency_floor`, :mod:`benchmarks.bench_exchange`,
  :mod:`benchmarks.bench_reach`, :mod:`benchmarks.bench_runtime`.
"""
