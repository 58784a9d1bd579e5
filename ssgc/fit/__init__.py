"""Fitting grammar parameters to data, and measuring how well a fitted grammar matches it.

Also callable: `ssgc.fit(grammar, dataset, iterations=10, ...)` is `ssgc.api.fit`, the
approximate EM of `ssg fit` (docs/fitting.md).
"""
