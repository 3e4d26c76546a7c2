"""agentsdk benchmarks: ``agentsdk bench`` (see bench/__main__.py).

Every figure is reported next to a raw baseline measured in the same run; see
:mod:`agentsdk.bench.common` for the shared result types.
"""
